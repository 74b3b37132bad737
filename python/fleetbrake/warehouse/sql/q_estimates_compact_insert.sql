-- One row per minute of `compact_minutes` (q_estimates_compact_minutes.sql) from the minute's
-- per-second rows of revision $revision (interface.md, v3): time_utc the minute's start, the
-- means the minute's means, contact_max_c, contact_max_hi_c and every *_hi_* the minute's
-- largest, every *_lo_* its smallest, innovation_k and innovation_sd_k the minute's root mean
-- squares (null: no reading in the minute); resolution_s 60. $scan_from_utc, $scan_to_utc:
-- the minutes' time bounds (row groups outside are skipped).
-- Parameters: $revision, $scan_from_utc, $scan_to_utc.
INSERT INTO contact_estimates (
    wagon_id, time_utc, model_revision, contact_mean_c, contact_mean_lo_c, contact_mean_hi_c,
    contact_max_c, contact_max_hi_c, smoothed_contact_mean_c, smoothed_contact_mean_lo_c,
    smoothed_contact_mean_hi_c, unexplained_power_w, unexplained_power_lo_w,
    unexplained_power_hi_w, innovation_k, innovation_sd_k, smoothed_contact_max_c,
    smoothed_contact_max_hi_c, smoothed_unexplained_power_w, smoothed_unexplained_power_lo_w,
    smoothed_unexplained_power_hi_w, resolution_s
)
WITH minute_seconds AS (
    SELECT e.*, c.minute_utc
    FROM contact_estimates AS e
    JOIN compact_minutes AS c
      ON e.wagon_id = c.wagon_id AND date_trunc('minute', e.time_utc) = c.minute_utc
    WHERE e.model_revision = $revision AND e.resolution_s = 1
      AND e.time_utc >= CAST($scan_from_utc AS TIMESTAMP)
      AND e.time_utc < CAST($scan_to_utc AS TIMESTAMP)
)
SELECT
    wagon_id,
    minute_utc                                   AS time_utc,
    model_revision,
    avg(contact_mean_c)                          AS contact_mean_c,
    min(contact_mean_lo_c)                       AS contact_mean_lo_c,
    max(contact_mean_hi_c)                       AS contact_mean_hi_c,
    max(contact_max_c)                           AS contact_max_c,
    max(contact_max_hi_c)                        AS contact_max_hi_c,
    avg(smoothed_contact_mean_c)                 AS smoothed_contact_mean_c,
    min(smoothed_contact_mean_lo_c)              AS smoothed_contact_mean_lo_c,
    max(smoothed_contact_mean_hi_c)              AS smoothed_contact_mean_hi_c,
    avg(unexplained_power_w)                     AS unexplained_power_w,
    min(unexplained_power_lo_w)                  AS unexplained_power_lo_w,
    max(unexplained_power_hi_w)                  AS unexplained_power_hi_w,
    sqrt(avg(innovation_k * innovation_k))       AS innovation_k,
    sqrt(avg(innovation_sd_k * innovation_sd_k)) AS innovation_sd_k,
    max(smoothed_contact_max_c)                  AS smoothed_contact_max_c,
    max(smoothed_contact_max_hi_c)               AS smoothed_contact_max_hi_c,
    avg(smoothed_unexplained_power_w)            AS smoothed_unexplained_power_w,
    min(smoothed_unexplained_power_lo_w)         AS smoothed_unexplained_power_lo_w,
    max(smoothed_unexplained_power_hi_w)         AS smoothed_unexplained_power_hi_w,
    60                                           AS resolution_s
FROM minute_seconds
GROUP BY wagon_id, minute_utc, model_revision;
