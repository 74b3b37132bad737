-- One wagon's flags as a recording shows them, in time order: all of them (the timeline), or
-- those tied to the event recorded and those overlapping its window.
-- Parameters: $wagon_id; $event_id (NULL: none); $from_utc, $to_utc (NULL: unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
wagon_flags AS (
    SELECT flag_id, event_id, kind, severity, start_utc, end_utc, evidence
    FROM flags
    WHERE wagon_id = $wagon_id
),
shown AS (
    SELECT f.*
    FROM wagon_flags AS f, window_bounds AS w
    WHERE f.event_id = CAST($event_id AS VARCHAR)
       OR (f.end_utc >= w.from_utc AND f.start_utc <= w.to_utc)
)
SELECT flag_id, event_id, kind, severity, start_utc, end_utc, evidence
FROM shown
ORDER BY start_utc, flag_id;
