-- The spans estimated with revision $revision, from what and with which noise.
-- Parameters: $revision.
SELECT wagon_id, span_start_utc, span_end_utc, data_key, model_key, created_utc, seconds,
       measurement_k, power_w_per_sqrt_s
FROM estimated_spans
WHERE model_revision = $revision
ORDER BY wagon_id, span_start_utc;
