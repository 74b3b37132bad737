-- Every stored span, by wagon and start (one row per wagon and stretch of data: the stages
-- compare them with their ledgers).
SELECT wagon_id, span_start_utc, span_end_utc, sample_rows, data_key
FROM spans
ORDER BY wagon_id, span_start_utc;
