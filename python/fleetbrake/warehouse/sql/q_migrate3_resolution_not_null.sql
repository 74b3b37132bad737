-- Schema version 3: contact_estimates.resolution_s, added with 1 on the rows of before
-- (schema_estimates.sql), becomes NOT NULL (fleetbrake.warehouse.migration). No parameters.
ALTER TABLE contact_estimates ALTER COLUMN resolution_s SET NOT NULL;
