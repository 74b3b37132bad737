-- Record the declared model's revision, the current one, predicting with $solver on the mesh
-- of $refinement. Parameters: $name, $parameters_json, $solver, $refinement, $created_utc.
INSERT INTO model_revisions (
    model_revision, parent_revision, effect, parameters_json, rmse_fit_k, rmse_holdout_k,
    solver, is_current, created_utc, refinement
)
VALUES ($name, NULL, NULL, $parameters_json, NULL, NULL, $solver, TRUE, $created_utc, $refinement);
