-- Store the segments of one wagon's timeline. `segment_batch` holds one row per segment
-- (fleetbrake.simulation.predictions); the staging only recasts.
INSERT INTO timeline_segments (
    wagon_id, model_revision, span_start_utc, span_end_utc, start_utc, stop_utc, kind,
    event_id, anchor, shift_k, reference_c
)
WITH staged AS (
    SELECT
        CAST(wagon_id AS VARCHAR)         AS wagon_id,
        CAST(model_revision AS VARCHAR)   AS model_revision,
        CAST(span_start_utc AS TIMESTAMP) AS span_start_utc,
        CAST(span_end_utc AS TIMESTAMP)   AS span_end_utc,
        CAST(start_utc AS TIMESTAMP)      AS start_utc,
        CAST(stop_utc AS TIMESTAMP)       AS stop_utc,
        CAST(kind AS VARCHAR)             AS kind,
        CAST(event_id AS VARCHAR)         AS event_id,
        CAST(anchor AS VARCHAR)           AS anchor,
        CAST(shift_k AS DOUBLE)           AS shift_k,
        CAST(reference_c AS DOUBLE)       AS reference_c
    FROM segment_batch
)
SELECT
    wagon_id, model_revision, span_start_utc, span_end_utc, start_utc, stop_utc, kind,
    event_id, anchor, shift_k, reference_c
FROM staged;
