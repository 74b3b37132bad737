-- Delete the per-second rows of revision $revision in the minutes of `compact_minutes`
-- (their minute rows were inserted first, in the same transaction:
-- q_estimates_compact_insert.sql). $scan_from_utc, $scan_to_utc: the minutes' time bounds
-- (row groups outside are skipped). Parameters: $revision, $scan_from_utc, $scan_to_utc.
DELETE FROM contact_estimates AS e
USING compact_minutes AS c
WHERE e.wagon_id = c.wagon_id
  AND date_trunc('minute', e.time_utc) = c.minute_utc
  AND e.model_revision = $revision
  AND e.resolution_s = 1
  AND e.time_utc >= CAST($scan_from_utc AS TIMESTAMP)
  AND e.time_utc < CAST($scan_to_utc AS TIMESTAMP);
