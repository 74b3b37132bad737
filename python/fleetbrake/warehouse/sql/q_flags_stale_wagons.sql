-- The wagons with samples whose flags may not be what their data, revision $revision and
-- flag configuration $config_key give now: never judged with the revision (or never judged),
-- judged before a file of theirs was ingested or their timeline or estimates of the revision
-- were last written (a run that stopped between its simulation and its flags leaves such
-- wagons; the next run judges them), judged with other thresholds (or before the
-- configuration was recorded), or whose stored flags are not those the judgement left (rows
-- of `flags` removed or added since).
-- Parameters: $revision, $config_key.
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
    SELECT wagon_id, max(updated_utc) AS judged_utc,
           bool_and(config_key IS NOT DISTINCT FROM $config_key) AS same_config,
           sum(flag_count) AS flag_count
    FROM flagged_wagons
    WHERE model_revision = $revision
    GROUP BY wagon_id
),
stored AS (
    SELECT wagon_id, count(*) AS flag_count
    FROM flags
    GROUP BY wagon_id
)
SELECT w.wagon_id
FROM wagons AS w
LEFT JOIN ingested AS i USING (wagon_id)
LEFT JOIN simulated AS s USING (wagon_id)
LEFT JOIN estimated AS e USING (wagon_id)
LEFT JOIN judged AS j USING (wagon_id)
LEFT JOIN stored AS f USING (wagon_id)
WHERE j.judged_utc IS NULL
   OR j.judged_utc < greatest(i.written_utc, s.written_utc, e.written_utc)
   OR NOT j.same_config
   OR j.flag_count IS DISTINCT FROM coalesce(f.flag_count, 0)
ORDER BY w.wagon_id;
