-- Forget the stored registry entries of the wagons in `registry_batch` (replaced next).
DELETE FROM wagon_registry
WHERE wagon_id IN (SELECT wagon_id FROM registry_batch);
