-- What each wagon's contact estimates depend on in the warehouse, one key per wagon with
-- samples: its ingested files (identity and bytes) and its samples' count and time range (not
-- its events: the estimator runs over every logged second). A key that changed means the
-- wagon's data changed since it was estimated.
WITH wagon_samples AS (
    SELECT wagon_id, count(*) AS sample_rows, min(time_utc) AS first_utc,
           max(time_utc) AS last_utc
    FROM samples
    GROUP BY wagon_id
),
wagon_files AS (
    SELECT wagon_id,
           md5(string_agg(CAST(file_id AS VARCHAR) || ':' || sha256, ',' ORDER BY file_id))
               AS files_md5
    FROM files
    WHERE status = 'ingested' AND wagon_id IS NOT NULL
    GROUP BY wagon_id
)
SELECT
    s.wagon_id,
    concat_ws('|', coalesce(f.files_md5, '-'), s.sample_rows, s.first_utc, s.last_utc)
        AS data_key
FROM wagon_samples AS s
LEFT JOIN wagon_files AS f USING (wagon_id)
ORDER BY s.wagon_id;
