-- The wagons with samples: every one of them is judged (its flags recomputed).
SELECT DISTINCT wagon_id
FROM samples
ORDER BY wagon_id;
