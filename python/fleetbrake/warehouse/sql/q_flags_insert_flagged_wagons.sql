-- Record that the wagons $wagon_ids (a list) were judged with revision $revision and the flag
-- configuration $config_key at $updated_utc, with the number of flags each has in `flags`
-- (run after their flags are stored, in the same transaction).
WITH judged AS (
    SELECT unnest(CAST($wagon_ids AS VARCHAR[])) AS wagon_id
),
stored AS (
    SELECT wagon_id, count(*) AS flag_count
    FROM flags
    WHERE list_contains(CAST($wagon_ids AS VARCHAR[]), wagon_id)
    GROUP BY wagon_id
)
INSERT INTO flagged_wagons (wagon_id, model_revision, updated_utc, config_key, flag_count)
SELECT j.wagon_id, $revision, $updated_utc, $config_key, coalesce(s.flag_count, 0)
FROM judged AS j
LEFT JOIN stored AS s USING (wagon_id);
