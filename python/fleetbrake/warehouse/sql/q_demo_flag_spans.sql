-- Every flag's wagon, kind and span, to compare with the anomalies the generator injected.
-- No parameters.
SELECT wagon_id, kind, start_utc, end_utc
FROM v_flags
ORDER BY wagon_id, start_utc;
