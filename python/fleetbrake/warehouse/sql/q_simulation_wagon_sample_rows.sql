-- How many samples each wagon has: what the stages' chunks of wagons are sized by.
SELECT wagon_id, count(*) AS sample_rows
FROM samples
GROUP BY wagon_id;
