-- Forget when the wagons $wagon_ids (a list) were judged: they are recorded again next, in the
-- same transaction as their flags.
DELETE FROM flagged_wagons
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id);
