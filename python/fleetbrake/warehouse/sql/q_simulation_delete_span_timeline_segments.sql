-- Forget what revision $revision stored in timeline_segments for the spans overlapping the time ranges
-- (replaced next in the same transaction, or the spans no longer exist): range i is wagon
-- $wagon_ids[i] in [$from_utc[i], $to_utc[i]]. Parameters: $wagon_ids, $from_utc,
-- $to_utc (lists of the same length), $revision.
DELETE FROM timeline_segments AS t
WHERE t.model_revision = $revision
  AND list_contains(CAST($wagon_ids AS VARCHAR[]), t.wagon_id)
  AND EXISTS (
      SELECT 1
      FROM (
          SELECT
              unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
              unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
              unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
      ) AS r
      WHERE r.wagon_id = t.wagon_id
        AND t.span_start_utc <= r.to_utc
        AND t.span_end_utc >= r.from_utc
  );
