-- Forget what revision $revision stored in predictions inside the spans' time ranges (replaced next
-- in the same transaction, or the spans no longer exist): range i is wagon $wagon_ids[i] in
-- [$from_utc[i], $to_utc[i]]. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the
-- same length), $revision, $lo_utc and $hi_utc (the first range's start and the last's end:
-- the row groups outside them are skipped by their time bounds, not read).
DELETE FROM predictions AS t
WHERE t.model_revision = $revision
  AND list_contains(CAST($wagon_ids AS VARCHAR[]), t.wagon_id)
  AND t.time_utc BETWEEN $lo_utc AND $hi_utc
  AND EXISTS (
      SELECT 1
      FROM (
          SELECT
              unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
              unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
              unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
      ) AS r
      WHERE r.wagon_id = t.wagon_id AND t.time_utc BETWEEN r.from_utc AND r.to_utc
  );
