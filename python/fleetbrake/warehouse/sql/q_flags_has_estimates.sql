-- Whether the warehouse holds the estimation stage's tables (estimated_spans and
-- contact_estimates, behind v_contact_estimates): 2 when both are there.
SELECT count(*) AS present
FROM duckdb_tables()
WHERE table_name IN ('estimated_spans', 'contact_estimates');
