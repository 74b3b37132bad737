-- The fleet report (fleetbrake.app.report): the prediction rows of the chosen events, every
-- revision. Parameters: $event_ids (a list of event ids).
SELECT
    event_id,
    wagon_id,
    time_utc,
    model_revision,
    measured_sensor_c,
    predicted_sensor_c,
    predicted_contact_max_c
FROM v_predictions
WHERE list_contains($event_ids, event_id)
ORDER BY event_id, model_revision, time_utc;
