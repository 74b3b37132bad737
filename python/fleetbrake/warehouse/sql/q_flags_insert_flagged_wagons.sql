-- Record that the wagons $wagon_ids (a list) were judged with revision $revision at
-- $updated_utc.
INSERT INTO flagged_wagons (wagon_id, model_revision, updated_utc)
SELECT unnest(CAST($wagon_ids AS VARCHAR[])), $revision, $updated_utc;
