-- The flags stored for the wagons $wagon_ids (a list), to keep the detected_utc of those
-- found again.
WITH wanted AS (
    SELECT DISTINCT unnest(CAST($wagon_ids AS VARCHAR[])) AS wagon_id
)
SELECT f.flag_id, f.event_id, f.kind, f.severity, f.start_utc, f.end_utc, f.evidence,
       f.detected_utc
FROM flags AS f
JOIN wanted AS w USING (wagon_id);
