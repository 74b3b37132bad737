-- v_model_revisions: one row per model revision (interface.md).
CREATE OR REPLACE VIEW v_model_revisions AS
WITH staged AS (
    SELECT
        CAST(model_revision AS VARCHAR)  AS model_revision,
        CAST(parent_revision AS VARCHAR) AS parent_revision,
        CAST(effect AS VARCHAR)          AS effect,
        CAST(parameters_json AS VARCHAR) AS parameters_json,
        CAST(rmse_fit_k AS DOUBLE)       AS rmse_fit_k,
        CAST(rmse_holdout_k AS DOUBLE)   AS rmse_holdout_k,
        CAST(created_utc AS TIMESTAMP)   AS created_utc
    FROM model_revisions
)
SELECT
    model_revision, parent_revision, effect, parameters_json, rmse_fit_k, rmse_holdout_k,
    created_utc
FROM staged;
