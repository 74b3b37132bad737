-- Forget what wagon $wagon_id was estimated from (all revisions: its samples are gone).
-- Parameters: $wagon_id.
DELETE FROM estimated_wagons WHERE wagon_id = $wagon_id;
