-- Record that wagon $wagon_id was estimated with revision $revision from these keys, and the
-- noise it was estimated with.
-- Parameters: $wagon_id, $revision, $data_key, $model_key, $seconds, $measurement_k,
-- $power_w_per_sqrt_s, $created_utc.
INSERT INTO estimated_wagons (
    wagon_id, model_revision, data_key, model_key, seconds, measurement_k, power_w_per_sqrt_s,
    created_utc
)
VALUES (
    $wagon_id, $revision, $data_key, $model_key, $seconds, $measurement_k, $power_w_per_sqrt_s,
    $created_utc
);
