-- The spans judged with revision $revision, from what and with which thresholds.
-- Parameters: $revision.
SELECT wagon_id, span_start_utc, span_end_utc, data_key, config_key, updated_utc, flag_count
FROM flagged_spans
WHERE model_revision = $revision
ORDER BY wagon_id, span_start_utc;
