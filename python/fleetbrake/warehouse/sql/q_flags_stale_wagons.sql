-- The wagons with samples whose flags may not be what their data and revision $revision give
-- now: never judged with the revision, or judged before a file of theirs was ingested or their
-- timeline or estimates of the revision were last written (a unit that stopped between its
-- simulation and its flags leaves such wagons; the next unit judges them).
-- Parameters: $revision.
WITH wagons AS (
    SELECT DISTINCT wagon_id FROM samples
),
ingested AS (
    SELECT wagon_id, max(ingested_utc) AS written_utc
    FROM files
    WHERE wagon_id IS NOT NULL
    GROUP BY wagon_id
),
simulated AS (
    SELECT wagon_id, max(simulated_utc) AS written_utc
    FROM simulated_wagons
    WHERE model_revision = $revision
    GROUP BY wagon_id
),
estimated AS (
    SELECT wagon_id, max(created_utc) AS written_utc
    FROM estimated_wagons
    WHERE model_revision = $revision
    GROUP BY wagon_id
),
judged AS (
    SELECT wagon_id, max(updated_utc) AS judged_utc
    FROM flagged_wagons
    WHERE model_revision = $revision
    GROUP BY wagon_id
)
SELECT w.wagon_id
FROM wagons AS w
LEFT JOIN ingested AS i USING (wagon_id)
LEFT JOIN simulated AS s USING (wagon_id)
LEFT JOIN estimated AS e USING (wagon_id)
LEFT JOIN judged AS j USING (wagon_id)
WHERE j.judged_utc IS NULL
   OR j.judged_utc < greatest(i.written_utc, s.written_utc, e.written_utc)
ORDER BY w.wagon_id;
