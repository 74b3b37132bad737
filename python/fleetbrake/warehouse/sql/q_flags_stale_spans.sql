-- The spans whose flags may not be what their data, revision $revision and flag
-- configuration $config_key give now: never judged with the revision, judged from other data
-- (spans.data_key) or another end, judged before their timeline or estimates of the
-- revision were last written (a run that stopped between its simulation and its flags
-- leaves such spans; the next run judges them), judged with other thresholds, or whose
-- stored flags (those starting in the span, or a second after it) are not those the
-- judgement left (rows of `flags` removed or added since). Reads the ledgers and the flags,
-- not the samples.
-- Parameters: $revision, $config_key.
WITH judged AS (
    SELECT wagon_id, span_start_utc, span_end_utc, data_key, config_key, flag_count,
           updated_utc
    FROM flagged_spans
    WHERE model_revision = $revision
),
simulated AS (
    SELECT wagon_id, span_start_utc, simulated_utc AS written_utc
    FROM simulated_spans
    WHERE model_revision = $revision
),
estimated AS (
    SELECT wagon_id, span_start_utc, created_utc AS written_utc
    FROM estimated_spans
    WHERE model_revision = $revision
),
stored AS (
    SELECT s.wagon_id, s.span_start_utc, count(f.flag_id) AS flag_count
    FROM spans AS s
    JOIN flags AS f
      ON f.wagon_id = s.wagon_id
     AND f.start_utc BETWEEN s.span_start_utc AND s.span_end_utc + INTERVAL 1 SECOND
    GROUP BY s.wagon_id, s.span_start_utc
)
SELECT s.wagon_id, s.span_start_utc
FROM spans AS s
LEFT JOIN judged AS j USING (wagon_id, span_start_utc)
LEFT JOIN simulated AS m USING (wagon_id, span_start_utc)
LEFT JOIN estimated AS e USING (wagon_id, span_start_utc)
LEFT JOIN stored AS f USING (wagon_id, span_start_utc)
WHERE j.updated_utc IS NULL
   OR j.data_key <> s.data_key
   OR j.span_end_utc <> s.span_end_utc
   OR j.config_key <> $config_key
   OR j.updated_utc < greatest(m.written_utc, e.written_utc)
   OR j.flag_count <> coalesce(f.flag_count, 0)
ORDER BY s.wagon_id, s.span_start_utc;
