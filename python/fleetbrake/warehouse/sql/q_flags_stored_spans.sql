-- The flags stored in the spans' time ranges (those starting there), to keep the
-- detected_utc of those found again: range i is wagon $wagon_ids[i] in
-- [$from_utc[i], $to_utc[i]]. Parameters: $wagon_ids, $from_utc, $to_utc (lists of the same
-- length).
WITH ranges AS (
    SELECT
        unnest(CAST($wagon_ids AS VARCHAR[]))   AS wagon_id,
        unnest(CAST($from_utc AS TIMESTAMP[]))  AS from_utc,
        unnest(CAST($to_utc AS TIMESTAMP[]))    AS to_utc
)
SELECT f.flag_id, f.event_id, f.kind, f.severity, f.start_utc, f.end_utc, f.evidence,
       f.detected_utc
FROM flags AS f
JOIN ranges AS r
  ON f.wagon_id = r.wagon_id
 AND f.start_utc BETWEEN r.from_utc AND r.to_utc
WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), f.wagon_id);
