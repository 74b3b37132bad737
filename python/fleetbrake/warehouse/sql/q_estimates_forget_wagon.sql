-- Forget every contact estimate of wagon $wagon_id (all revisions: its samples are gone).
-- Parameters: $wagon_id.
DELETE FROM contact_estimates WHERE wagon_id = $wagon_id;
