-- The fleet report (fleetbrake.app.report): per event and model revision, the virtual sensor's
-- peak contact temperature over the event's window (the seconds v_predictions holds for it):
-- the highest filtered contact mean with its 95 % bounds at that second, and the highest
-- contact maximum with its upper bound. An event window's estimates are stored per second
-- (it is an estimate window). No parameters.
WITH event_windows AS (
    SELECT event_id, wagon_id, min(time_utc) AS from_utc, max(time_utc) AS to_utc
    FROM v_predictions
    GROUP BY event_id, wagon_id
),
inside AS (
    SELECT
        w.event_id, e.wagon_id, e.model_revision, e.contact_mean_c, e.contact_mean_lo_c,
        e.contact_mean_hi_c, e.contact_max_c, e.contact_max_hi_c
    FROM event_windows AS w
    JOIN v_contact_estimates AS e
      ON e.wagon_id = w.wagon_id
     AND e.time_utc BETWEEN w.from_utc AND w.to_utc
)
SELECT
    event_id,
    wagon_id,
    model_revision,
    max(contact_mean_c)                          AS est_mean_peak_c,
    arg_max(contact_mean_lo_c, contact_mean_c)   AS est_mean_peak_lo_c,
    arg_max(contact_mean_hi_c, contact_mean_c)   AS est_mean_peak_hi_c,
    max(contact_max_c)                           AS est_max_peak_c,
    arg_max(contact_max_hi_c, contact_max_c)     AS est_max_peak_hi_c
FROM inside
GROUP BY event_id, wagon_id, model_revision
ORDER BY wagon_id, event_id, model_revision;
