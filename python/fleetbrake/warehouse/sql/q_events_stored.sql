-- The stored events of one wagon overlapping [$from_utc, $to_utc], with the columns the event
-- detection computes (no detected_utc), to compare with a new detection
-- (fleetbrake.ingest.events). Parameters: $wagon_id, $from_utc, $to_utc.
WITH overlapping AS (
    SELECT
        event_id, wagon_id, start_utc, end_utc, duration_s, distance_m, v_start_kmh,
        v_end_kmh, p_mean_bar, p_max_bar, t_block_start_c, kind, complete
    FROM events
    WHERE wagon_id = $wagon_id
      AND start_utc <= $to_utc
      AND end_utc >= $from_utc
)
SELECT
    event_id, wagon_id, start_utc, end_utc, duration_s, distance_m, v_start_kmh, v_end_kmh,
    p_mean_bar, p_max_bar, t_block_start_c, kind, complete
FROM overlapping;
