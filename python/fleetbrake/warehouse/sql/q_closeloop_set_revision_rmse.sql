-- Record revision $name's RMSE on the fit and holdout events of its closed loop.
-- Parameters: $name, $rmse_fit_k, $rmse_holdout_k.
UPDATE model_revisions
SET rmse_fit_k = $rmse_fit_k,
    rmse_holdout_k = $rmse_holdout_k
WHERE model_revision = $name;
