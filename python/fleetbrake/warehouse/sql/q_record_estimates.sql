-- One wagon's contact estimates by one model revision as a recording draws them (the virtual
-- sensor, v_contact_estimates of interface.md v3: resolution_s 1, a second's row; 60, a
-- minute's), in time order: all of them (the timeline) or those inside a window. Parameters: $wagon_id, $model_revision; $from_utc, $to_utc (NULL:
-- unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
revision_estimates AS (
    SELECT
        time_utc, contact_mean_c, contact_mean_lo_c, contact_mean_hi_c, contact_max_c,
        contact_max_hi_c, unexplained_power_w, unexplained_power_lo_w, unexplained_power_hi_w,
        innovation_k, resolution_s
    FROM v_contact_estimates
    WHERE wagon_id = $wagon_id
      AND model_revision = $model_revision
)
SELECT e.*
FROM revision_estimates AS e, window_bounds AS w
WHERE e.time_utc BETWEEN w.from_utc AND w.to_utc
ORDER BY e.time_utc;
