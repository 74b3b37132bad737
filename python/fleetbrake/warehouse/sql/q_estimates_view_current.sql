-- Whether v_contact_estimates is of interface v3 (it has resolution_s): 1, else 0 (a database
-- of schema version 2 read without being opened for writing, which would migrate it).
-- No parameters.
SELECT count(*) AS current
FROM duckdb_columns()
WHERE table_name = 'v_contact_estimates' AND column_name = 'resolution_s';
