-- One wagon's virtual-sensor estimates of revision $revision, by time, as the flags' estimator
-- detectors read them (fleetbrake.flags.estimated): after the fact, so the smoothed contact
-- temperature and unexplained power with their bounds where the stage stored them (the
-- filtered ones otherwise), and the filtered innovation; the per-second rows only (the
-- flags judge estimates the same run stored per second). Parameters: $wagon_id, $revision.
SELECT
    time_utc,
    coalesce(smoothed_contact_mean_c, contact_mean_c)                AS contact_mean_c,
    coalesce(smoothed_contact_mean_lo_c, contact_mean_lo_c)          AS contact_mean_lo_c,
    coalesce(smoothed_contact_mean_hi_c, contact_mean_hi_c)          AS contact_mean_hi_c,
    coalesce(smoothed_contact_max_c, contact_max_c)                  AS contact_max_c,
    coalesce(smoothed_contact_max_hi_c, contact_max_hi_c)            AS contact_max_hi_c,
    coalesce(smoothed_unexplained_power_w, unexplained_power_w)      AS unexplained_power_w,
    coalesce(smoothed_unexplained_power_lo_w, unexplained_power_lo_w) AS unexplained_power_lo_w,
    coalesce(smoothed_unexplained_power_hi_w, unexplained_power_hi_w) AS unexplained_power_hi_w,
    innovation_k
FROM contact_estimates
WHERE wagon_id = $wagon_id AND model_revision = $revision AND resolution_s = 1
ORDER BY time_utc;
