-- The first event of the first wagon: the demo's recording when nothing else stands out.
-- No parameters.
SELECT event_id, wagon_id
FROM v_events
ORDER BY wagon_id, start_utc
LIMIT 1;
