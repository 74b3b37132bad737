-- The sigma_w fitted for revision $revision (none: the default applies).
-- Parameters: $revision.
SELECT measurement_k, power_w_per_sqrt_s, method, fit_wagons, fit_readings, log_likelihood,
       at_floor, created_utc
FROM estimator_noise
WHERE model_revision = $revision;
