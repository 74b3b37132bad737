-- v_events: one row per detected braking event (interface.md).
CREATE OR REPLACE VIEW v_events AS
WITH staged AS (
    SELECT
        CAST(event_id AS VARCHAR)        AS event_id,
        CAST(wagon_id AS VARCHAR)        AS wagon_id,
        CAST(start_utc AS TIMESTAMP)     AS start_utc,
        CAST(end_utc AS TIMESTAMP)       AS end_utc,
        CAST(duration_s AS DOUBLE)       AS duration_s,
        CAST(distance_m AS DOUBLE)       AS distance_m,
        CAST(v_start_kmh AS DOUBLE)      AS v_start_kmh,
        CAST(v_end_kmh AS DOUBLE)        AS v_end_kmh,
        CAST(p_mean_bar AS DOUBLE)       AS p_mean_bar,
        CAST(t_block_start_c AS DOUBLE)  AS t_block_start_c
    FROM events
)
SELECT
    event_id, wagon_id, start_utc, end_utc, duration_s, distance_m,
    v_start_kmh, v_end_kmh, p_mean_bar, t_block_start_c
FROM staged;
