-- How many samples and events one wagon has: a recording of a wagon with neither is refused.
-- Parameters: $wagon_id.
WITH wagon_samples AS (
    SELECT count(*) AS n
    FROM samples
    WHERE wagon_id = $wagon_id
),
wagon_events AS (
    SELECT count(*) AS n
    FROM events
    WHERE wagon_id = $wagon_id
)
SELECT wagon_samples.n AS samples, wagon_events.n AS events
FROM wagon_samples, wagon_events;
