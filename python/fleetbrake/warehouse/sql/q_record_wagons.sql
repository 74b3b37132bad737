-- Every wagon with samples or events, by id (named when a wagon asked for is unknown).
WITH wagons AS (
    SELECT wagon_id FROM samples
    UNION
    SELECT wagon_id FROM events
)
SELECT wagon_id
FROM wagons
ORDER BY wagon_id;
