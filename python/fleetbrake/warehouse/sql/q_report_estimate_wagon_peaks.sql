-- The fleet report (fleetbrake.app.report): per wagon and model revision, over every stored
-- row (per second in the estimate windows, per minute elsewhere: a minute row's maxima and
-- bounds are the minute's extremes, its means the minute's): the virtual sensor's highest
-- contact mean with its 95 % bounds and time, the highest contact maximum with its upper
-- bound, and the extremes of the unexplained power with their bounds (highest: a dragging
-- brake; lowest: a weak brake); seconds: the seconds the rows stand for. No parameters.
WITH estimates AS (
    SELECT
        wagon_id, model_revision, time_utc, resolution_s, contact_mean_c, contact_mean_lo_c,
        contact_mean_hi_c, contact_max_c, contact_max_hi_c, unexplained_power_w,
        unexplained_power_lo_w, unexplained_power_hi_w
    FROM v_contact_estimates
)
SELECT
    wagon_id,
    model_revision,
    sum(resolution_s)                                             AS seconds,
    max(contact_mean_c)                                           AS est_mean_peak_c,
    arg_max(contact_mean_lo_c, contact_mean_c)                    AS est_mean_peak_lo_c,
    arg_max(contact_mean_hi_c, contact_mean_c)                    AS est_mean_peak_hi_c,
    arg_max(time_utc, contact_mean_c)                             AS est_mean_peak_utc,
    max(contact_max_c)                                            AS est_max_peak_c,
    arg_max(contact_max_hi_c, contact_max_c)                      AS est_max_peak_hi_c,
    max(unexplained_power_w)                                      AS power_max_w,
    arg_max(unexplained_power_lo_w, unexplained_power_w)          AS power_max_lo_w,
    arg_max(unexplained_power_hi_w, unexplained_power_w)          AS power_max_hi_w,
    min(unexplained_power_w)                                      AS power_min_w,
    arg_min(unexplained_power_lo_w, unexplained_power_w)          AS power_min_lo_w,
    arg_min(unexplained_power_hi_w, unexplained_power_w)          AS power_min_hi_w
FROM estimates
GROUP BY wagon_id, model_revision
ORDER BY wagon_id, model_revision;
