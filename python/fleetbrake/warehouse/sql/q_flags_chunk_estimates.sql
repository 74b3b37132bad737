-- Several wagons' virtual-sensor estimates of revision $revision (a chunk), as
-- q_flags_estimates.sql reads one wagon's (the same columns: a test compares them), with
-- wagon_ix (the wagon's 1-based position in $wagon_ids: q_simulation_chunk_samples.sql says why
-- not its name); the reader splits them by wagon and sorts each by time_utc. The per-second
-- rows only: the flags judge estimates the same run stored per second (the minute rows of a
-- compacted range are not theirs). Parameters: $wagon_ids (a list), $revision.
SELECT
    CAST(list_position($wagon_ids, wagon_id) AS INTEGER) AS wagon_ix,
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
WHERE list_contains($wagon_ids, wagon_id) AND model_revision = $revision AND resolution_s = 1;
