-- Record the sigma_w fitted for revision $revision (replacing one fitted before: the close
-- loop refits when it changes the revision's effects).
-- Parameters: $revision, $measurement_k, $power_w_per_sqrt_s, $method, $fit_wagons,
-- $fit_readings, $log_likelihood, $at_floor, $created_utc.
INSERT OR REPLACE INTO estimator_noise (
    model_revision, measurement_k, power_w_per_sqrt_s, method, fit_wagons, fit_readings,
    log_likelihood, at_floor, created_utc
)
VALUES (
    $revision, $measurement_k, $power_w_per_sqrt_s, $method, $fit_wagons, $fit_readings,
    $log_likelihood, $at_floor, $created_utc
);
