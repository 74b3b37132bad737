-- Forget the flags starting in the spans' time ranges (replaced next in the same
-- transaction, or the spans no longer exist): range i is wagon $wagon_ids[i] in
-- [$from_utc[i], $to_utc[i]]. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same
-- length).
DELETE FROM flags AS t
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), t.wagon_id)
  AND EXISTS (
      SELECT 1
      FROM (
          SELECT
              unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
              unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
              unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
      ) AS r
      WHERE r.wagon_id = t.wagon_id AND t.start_utc BETWEEN r.from_utc AND r.to_utc
  );
