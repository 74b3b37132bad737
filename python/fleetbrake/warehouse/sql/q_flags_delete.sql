-- Forget the flags of the wagons $wagon_ids (a list): they are replaced next, in the same
-- transaction.
DELETE FROM flags
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
