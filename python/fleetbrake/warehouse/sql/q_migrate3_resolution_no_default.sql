-- Schema version 3: contact_estimates.resolution_s keeps no default, as in a database made
-- with version 3 (fleetbrake.warehouse.migration). No parameters.
ALTER TABLE contact_estimates ALTER COLUMN resolution_s DROP DEFAULT;
