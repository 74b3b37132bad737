-- Every (flag, event) pair where the flag concerns the event: the flag is tied to it, or the
-- flag is tied to no event and its span overlaps the event's (fleetbrake.app.demo.pick_event).
-- `tied` is the flag's own event_id (null for a span flag). No parameters.
WITH flags AS (
    SELECT wagon_id, kind, severity, event_id AS tied, start_utc, end_utc
    FROM v_flags
),
events AS (
    SELECT event_id, wagon_id, start_utc, end_utc
    FROM v_events
)
SELECT f.kind, f.severity, f.tied, e.event_id, e.wagon_id, e.start_utc
FROM flags AS f
JOIN events AS e
  ON e.wagon_id = f.wagon_id
 AND (
        e.event_id = f.tied
        OR (f.tied IS NULL AND e.start_utc <= f.end_utc AND e.end_utc >= f.start_utc)
     );
