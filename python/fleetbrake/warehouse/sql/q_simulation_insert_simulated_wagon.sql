-- Record that wagon $wagon_id was simulated with revision $revision from these keys.
-- Parameters: $wagon_id, $revision, $data_key, $model_key, $events, $simulated_utc.
INSERT INTO simulated_wagons (
    wagon_id, model_revision, data_key, model_key, events, simulated_utc
)
VALUES ($wagon_id, $revision, $data_key, $model_key, $events, $simulated_utc);
