-- One wagon's predictions by one model revision as a recording draws them, in time order: all
-- of them (the timeline) or those inside an event's window.
-- Parameters: $wagon_id, $model_revision; $from_utc, $to_utc (NULL: unbounded).
WITH window_bounds AS (
    SELECT
        coalesce(CAST($from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
revision_predictions AS (
    SELECT
        time_utc, event_id, measured_sensor_c, predicted_sensor_c, predicted_contact_mean_c,
        predicted_contact_max_c, ambient_c, flux_w_m2
    FROM predictions
    WHERE wagon_id = $wagon_id
      AND model_revision = $model_revision
)
SELECT p.*
FROM revision_predictions AS p, window_bounds AS w
WHERE p.time_utc BETWEEN w.from_utc AND w.to_utc
ORDER BY p.time_utc, p.event_id;
