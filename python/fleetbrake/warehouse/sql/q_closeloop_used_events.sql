-- The events the closed loop may use (fleetbrake.closeloop): every event with predictions of
-- revision $revision, and whether it is disturbed. An event is disturbed when its window
-- overlaps, or starts less than $settle_us microseconds after the end of, a disturbance of
-- its wagon: an anomaly flag (dragging or weak brake, sensor fault), or the window of an
-- event cut by a data gap (`complete` false: part of its heat input was never logged).
-- Parameters: $revision, $settle_us.
WITH windows AS (
    -- each event's prediction window
    SELECT event_id, wagon_id, min(time_utc) AS t0, max(time_utc) AS t1
    FROM predictions
    WHERE model_revision = $revision
    GROUP BY event_id, wagon_id
),
anomalies AS (
    SELECT wagon_id, start_utc AS d0, end_utc AS d1
    FROM flags
    WHERE kind IN ('dragging_brake', 'weak_brake', 'sensor_fault')
),
cut_by_gap AS (
    SELECT w.wagon_id, w.t0 AS d0, w.t1 AS d1
    FROM windows AS w
    JOIN events AS e USING (event_id)
    WHERE NOT e.complete
),
disturbances AS (
    SELECT wagon_id, d0, d1 FROM anomalies
    UNION ALL
    SELECT wagon_id, d0, d1 FROM cut_by_gap
),
disturbed AS (
    SELECT DISTINCT w.event_id
    FROM windows AS w
    JOIN disturbances AS d
      ON d.wagon_id = w.wagon_id
     AND d.d0 <= w.t1
     AND d.d1 + to_microseconds(CAST($settle_us AS BIGINT)) >= w.t0
)
SELECT
    e.event_id, e.wagon_id, e.start_utc, e.end_utc, e.detected_utc,
    e.event_id IN (SELECT event_id FROM disturbed) AS flagged
FROM events AS e
JOIN windows AS w USING (event_id)
ORDER BY e.wagon_id, e.start_utc;
