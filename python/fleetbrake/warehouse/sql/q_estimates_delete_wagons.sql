-- Forget the contact estimates of revision $revision for the wagons $wagon_ids (replaced next,
-- in the same transaction). Parameters: $wagon_ids (a list), $revision.
DELETE FROM contact_estimates
WHERE model_revision = $revision AND list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
