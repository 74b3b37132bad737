-- Store contact estimates. `estimate_batch` holds one row per wagon and logged second
-- (fleetbrake.simulation.estimates), stored per second (resolution_s = 1); the staging only
-- recasts. Parameters: none.
INSERT INTO contact_estimates (
    wagon_id, time_utc, model_revision, contact_mean_c, contact_mean_lo_c, contact_mean_hi_c,
    contact_max_c, contact_max_hi_c, smoothed_contact_mean_c, smoothed_contact_mean_lo_c,
    smoothed_contact_mean_hi_c, unexplained_power_w, unexplained_power_lo_w,
    unexplained_power_hi_w, innovation_k, innovation_sd_k, smoothed_contact_max_c,
    smoothed_contact_max_hi_c, smoothed_unexplained_power_w, smoothed_unexplained_power_lo_w,
    smoothed_unexplained_power_hi_w, resolution_s
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)                         AS wagon_id,
        CAST(time_utc AS TIMESTAMP)                       AS time_utc,
        CAST(model_revision AS VARCHAR)                   AS model_revision,
        CAST(contact_mean_c AS DOUBLE)                    AS contact_mean_c,
        CAST(contact_mean_lo_c AS DOUBLE)                 AS contact_mean_lo_c,
        CAST(contact_mean_hi_c AS DOUBLE)                 AS contact_mean_hi_c,
        CAST(contact_max_c AS DOUBLE)                     AS contact_max_c,
        CAST(contact_max_hi_c AS DOUBLE)                  AS contact_max_hi_c,
        CAST(smoothed_contact_mean_c AS DOUBLE)           AS smoothed_contact_mean_c,
        CAST(smoothed_contact_mean_lo_c AS DOUBLE)        AS smoothed_contact_mean_lo_c,
        CAST(smoothed_contact_mean_hi_c AS DOUBLE)        AS smoothed_contact_mean_hi_c,
        CAST(unexplained_power_w AS DOUBLE)               AS unexplained_power_w,
        CAST(unexplained_power_lo_w AS DOUBLE)            AS unexplained_power_lo_w,
        CAST(unexplained_power_hi_w AS DOUBLE)            AS unexplained_power_hi_w,
        CAST(innovation_k AS DOUBLE)                      AS innovation_k,
        CAST(innovation_sd_k AS DOUBLE)                   AS innovation_sd_k,
        CAST(smoothed_contact_max_c AS DOUBLE)            AS smoothed_contact_max_c,
        CAST(smoothed_contact_max_hi_c AS DOUBLE)         AS smoothed_contact_max_hi_c,
        CAST(smoothed_unexplained_power_w AS DOUBLE)      AS smoothed_unexplained_power_w,
        CAST(smoothed_unexplained_power_lo_w AS DOUBLE)   AS smoothed_unexplained_power_lo_w,
        CAST(smoothed_unexplained_power_hi_w AS DOUBLE)   AS smoothed_unexplained_power_hi_w,
        CAST(1 AS INTEGER)                                AS resolution_s
    FROM estimate_batch
)
SELECT
    wagon_id, time_utc, model_revision, contact_mean_c, contact_mean_lo_c, contact_mean_hi_c,
    contact_max_c, contact_max_hi_c, smoothed_contact_mean_c, smoothed_contact_mean_lo_c,
    smoothed_contact_mean_hi_c, unexplained_power_w, unexplained_power_lo_w,
    unexplained_power_hi_w, innovation_k, innovation_sd_k, smoothed_contact_max_c,
    smoothed_contact_max_hi_c, smoothed_unexplained_power_w, smoothed_unexplained_power_lo_w,
    smoothed_unexplained_power_hi_w, resolution_s
FROM staged;
