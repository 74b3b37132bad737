-- The wagons estimated with revision $revision, from what and with which noise.
-- Parameters: $revision.
SELECT wagon_id, data_key, model_key, seconds, created_utc, measurement_k, power_w_per_sqrt_s
FROM estimated_wagons
WHERE model_revision = $revision
ORDER BY wagon_id;
