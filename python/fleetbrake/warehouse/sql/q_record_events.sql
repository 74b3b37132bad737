-- One wagon's events as a recording shows them, in time order: all of them (the timeline) or
-- those overlapping an event's window. Parameters: $wagon_id; $from_utc, $to_utc (NULL:
-- unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
wagon_events AS (
    SELECT
        event_id, wagon_id, start_utc, end_utc, duration_s, distance_m, v_start_kmh,
        v_end_kmh, p_mean_bar, p_max_bar, t_block_start_c, kind, complete, detected_utc
    FROM events
    WHERE wagon_id = $wagon_id
)
SELECT e.*
FROM wagon_events AS e, window_bounds AS w
WHERE e.end_utc >= w.from_utc
  AND e.start_utc <= w.to_utc
ORDER BY e.start_utc;
