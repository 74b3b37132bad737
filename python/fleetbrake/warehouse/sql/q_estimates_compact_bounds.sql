-- The time bounds of the minutes to compact (q_estimates_compact_minutes.sql): the first
-- minute's start and the last one's end (null, null: none). No parameters.
SELECT min(minute_utc) AS from_utc, max(minute_utc) + INTERVAL 1 MINUTE AS to_utc
FROM compact_minutes;
