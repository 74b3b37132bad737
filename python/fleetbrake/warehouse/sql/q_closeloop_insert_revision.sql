-- Record the closed loop's new model revision as the current one. It predicts with the solver
-- of its parent ($solver: the parent's), so that before and after compare one model form.
-- The same for its mesh ($refinement: the parent's).
-- Parameters: $name, $parent, $effect, $parameters_json, $solver, $refinement, $created_utc.
INSERT INTO model_revisions (
    model_revision, parent_revision, effect, parameters_json, rmse_fit_k, rmse_holdout_k,
    solver, is_current, created_utc, refinement
)
WITH staged AS (
    SELECT
        CAST($name AS VARCHAR)             AS model_revision,
        CAST($parent AS VARCHAR)           AS parent_revision,
        CAST($effect AS VARCHAR)           AS effect,
        CAST($parameters_json AS VARCHAR)  AS parameters_json,
        CAST(NULL AS DOUBLE)               AS rmse_fit_k,
        CAST(NULL AS DOUBLE)               AS rmse_holdout_k,
        CAST($solver AS VARCHAR)           AS solver,
        TRUE                               AS is_current,
        CAST($created_utc AS TIMESTAMP)    AS created_utc,
        CAST($refinement AS DOUBLE)        AS refinement
)
SELECT
    model_revision, parent_revision, effect, parameters_json, rmse_fit_k, rmse_holdout_k,
    solver, is_current, created_utc, refinement
FROM staged;
