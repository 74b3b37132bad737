-- The minutes to compact (fleetbrake.warehouse.estimate_windows): those of the per-second rows
-- of revision $revision inside the ranges of `compact_ranges` (wagon_id, start_utc, end_utc;
-- null: unbounded), each range rounded outward to whole minutes, that no estimate window
-- touches. The estimate windows (interface.md, v3): the event windows of the revision's
-- predictions (first to last second of each event), the flags' windows, and the stretches of
-- per-second rows whose unexplained power's 95 % band excludes zero; each widened by
-- $margin_s on both sides, then rounded outward to whole minutes. The windows are read near
-- the ranges only ($margin_s and a minute beyond them), which leaves their part inside the
-- ranges unchanged. $scan_from_utc, $scan_to_utc (null: unbounded) bound every time read
-- (the ranges' reach), so that DuckDB skips the row groups outside them.
-- Parameters: $revision, $margin_s, $scan_from_utc, $scan_to_utc.
CREATE OR REPLACE TEMP TABLE compact_minutes AS
WITH scan AS (
    SELECT
        coalesce(CAST($scan_from_utc AS TIMESTAMP), TIMESTAMP '-infinity') AS from_utc,
        coalesce(CAST($scan_to_utc AS TIMESTAMP), TIMESTAMP 'infinity')    AS to_utc
),
ranges AS (
    SELECT
        CAST(wagon_id AS VARCHAR)                                              AS wagon_id,
        coalesce(date_trunc('minute', CAST(start_utc AS TIMESTAMP)), TIMESTAMP '-infinity')
            AS from_utc,
        coalesce(date_trunc('minute', CAST(end_utc AS TIMESTAMP)) + INTERVAL 1 MINUTE,
                 TIMESTAMP 'infinity')                                         AS to_utc
    FROM compact_ranges
),
reach AS (
    SELECT
        wagon_id,
        from_utc - to_seconds(CAST($margin_s AS DOUBLE) + 60.0) AS from_utc,
        to_utc + to_seconds(CAST($margin_s AS DOUBLE) + 60.0)   AS to_utc
    FROM ranges
),
seconds AS (
    SELECT
        e.wagon_id,
        e.time_utc,
        e.unexplained_power_lo_w > 0 OR e.unexplained_power_hi_w < 0 AS significant
    FROM contact_estimates AS e
    JOIN reach AS r
      ON e.wagon_id = r.wagon_id AND e.time_utc >= r.from_utc AND e.time_utc < r.to_utc
    WHERE e.model_revision = $revision AND e.resolution_s = 1
      AND e.time_utc >= (SELECT from_utc FROM scan) AND e.time_utc < (SELECT to_utc FROM scan)
),
stretch_ids AS (
    SELECT
        wagon_id, time_utc, significant,
        sum(CAST(significant IS DISTINCT FROM prev_significant AS INTEGER))
            OVER (PARTITION BY wagon_id ORDER BY time_utc) AS stretch
    FROM (
        SELECT wagon_id, time_utc, significant,
               lag(significant) OVER (PARTITION BY wagon_id ORDER BY time_utc) AS prev_significant
        FROM seconds
    )
),
power_windows AS (
    SELECT wagon_id, min(time_utc) AS start_utc, max(time_utc) AS end_utc
    FROM stretch_ids
    WHERE significant
    GROUP BY wagon_id, stretch
),
event_windows AS (
    SELECT p.wagon_id, min(p.time_utc) AS start_utc, max(p.time_utc) AS end_utc
    FROM predictions AS p
    JOIN reach AS r
      ON p.wagon_id = r.wagon_id AND p.time_utc >= r.from_utc AND p.time_utc < r.to_utc
    WHERE p.model_revision = $revision
      AND p.time_utc >= (SELECT from_utc FROM scan) AND p.time_utc < (SELECT to_utc FROM scan)
    GROUP BY p.wagon_id, p.event_id
),
flag_windows AS (
    SELECT f.wagon_id, greatest(f.start_utc, r.from_utc) AS start_utc,
           least(f.end_utc, r.to_utc) AS end_utc
    FROM flags AS f
    JOIN reach AS r
      ON f.wagon_id = r.wagon_id AND f.end_utc >= r.from_utc AND f.start_utc < r.to_utc
),
windows AS (
    SELECT wagon_id, start_utc, end_utc FROM power_windows
    UNION ALL
    SELECT wagon_id, start_utc, end_utc FROM event_windows
    UNION ALL
    SELECT wagon_id, start_utc, end_utc FROM flag_windows
),
kept_minutes AS (
    SELECT DISTINCT
        wagon_id,
        unnest(generate_series(
            date_trunc('minute', start_utc - to_seconds(CAST($margin_s AS DOUBLE))),
            date_trunc('minute', end_utc + to_seconds(CAST($margin_s AS DOUBLE))),
            INTERVAL 1 MINUTE
        )) AS minute_utc
    FROM windows
),
second_minutes AS (
    SELECT DISTINCT s.wagon_id, date_trunc('minute', s.time_utc) AS minute_utc
    FROM seconds AS s
    JOIN ranges AS r
      ON s.wagon_id = r.wagon_id AND s.time_utc >= r.from_utc AND s.time_utc < r.to_utc
)
SELECT m.wagon_id, m.minute_utc
FROM second_minutes AS m
ANTI JOIN kept_minutes AS k ON m.wagon_id = k.wagon_id AND m.minute_utc = k.minute_utc;
