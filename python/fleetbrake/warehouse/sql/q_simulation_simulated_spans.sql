-- The spans simulated with revision $revision, and from what. Parameters: $revision.
SELECT wagon_id, span_start_utc, span_end_utc, data_key, model_key, simulated_utc, events
FROM simulated_spans
WHERE model_revision = $revision
ORDER BY wagon_id, span_start_utc;
