-- One event, by id (the event a recording is made of). Parameters: $event_id.
SELECT
    event_id, wagon_id, start_utc, end_utc, duration_s, distance_m, v_start_kmh, v_end_kmh,
    p_mean_bar, p_max_bar, t_block_start_c, kind, complete, detected_utc
FROM events
WHERE event_id = $event_id;
