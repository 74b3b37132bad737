-- Why each quarantined file of one wagon was refused (its reason, else its path), by path: the
-- explanation when a wagon asked for has no samples. Parameters: $wagon_id.
SELECT coalesce(reason, path) AS reason
FROM files
WHERE wagon_id = $wagon_id
  AND status = 'quarantined'
ORDER BY path;
