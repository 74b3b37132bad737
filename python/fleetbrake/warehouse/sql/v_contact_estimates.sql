-- v_contact_estimates: the virtual sensor's contact-temperature estimate per wagon and model
-- revision (interface.md, v3): a row per logged second inside the estimate windows
-- (resolution_s = 1), a row per minute elsewhere (resolution_s = 60).
CREATE OR REPLACE VIEW v_contact_estimates AS
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)                   AS wagon_id,
        CAST(time_utc AS TIMESTAMP)                 AS time_utc,
        CAST(model_revision AS VARCHAR)             AS model_revision,
        CAST(resolution_s AS INTEGER)               AS resolution_s,
        CAST(contact_mean_c AS DOUBLE)              AS contact_mean_c,
        CAST(contact_mean_lo_c AS DOUBLE)           AS contact_mean_lo_c,
        CAST(contact_mean_hi_c AS DOUBLE)           AS contact_mean_hi_c,
        CAST(contact_max_c AS DOUBLE)               AS contact_max_c,
        CAST(contact_max_hi_c AS DOUBLE)            AS contact_max_hi_c,
        CAST(smoothed_contact_mean_c AS DOUBLE)     AS smoothed_contact_mean_c,
        CAST(smoothed_contact_mean_lo_c AS DOUBLE)  AS smoothed_contact_mean_lo_c,
        CAST(smoothed_contact_mean_hi_c AS DOUBLE)  AS smoothed_contact_mean_hi_c,
        CAST(unexplained_power_w AS DOUBLE)         AS unexplained_power_w,
        CAST(unexplained_power_lo_w AS DOUBLE)      AS unexplained_power_lo_w,
        CAST(unexplained_power_hi_w AS DOUBLE)      AS unexplained_power_hi_w,
        CAST(innovation_k AS DOUBLE)                AS innovation_k
    FROM contact_estimates
)
SELECT
    wagon_id, time_utc, model_revision, resolution_s, contact_mean_c, contact_mean_lo_c,
    contact_mean_hi_c, contact_max_c, contact_max_hi_c, smoothed_contact_mean_c, smoothed_contact_mean_lo_c,
    smoothed_contact_mean_hi_c, unexplained_power_w, unexplained_power_lo_w,
    unexplained_power_hi_w, innovation_k
FROM staged;
