-- The braking events of one span of a wagon (activation in [$from_utc, $to_utc]), by
-- activation. Parameters: $wagon_id, $from_utc, $to_utc.
SELECT event_id, start_utc, end_utc, complete
FROM events
WHERE wagon_id = $wagon_id AND start_utc BETWEEN $from_utc AND $to_utc
ORDER BY start_utc;
