-- Delete the contact estimates of the wagons $wagon_ids of every revision a closed loop made
-- (one with a parent) that is neither $revision nor the current one: estimates are kept for
-- `declared` and for the revision the last close-loop recorded (the current one), whose
-- estimates replace the older's (interface.md, v3). Run with the insert of $revision's rows,
-- in the same transaction. Parameters: $wagon_ids (a list), $revision.
DELETE FROM contact_estimates
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id)
  AND model_revision <> $revision
  AND model_revision IN (
      SELECT model_revision
      FROM model_revisions
      WHERE parent_revision IS NOT NULL AND NOT is_current
  );
