-- Schema version 3 keeps the contact estimates of `declared` and of the current revision (the
-- one the last close-loop recorded) only: delete those of every other revision a closed loop
-- made (fleetbrake.warehouse.migration). No parameters.
DELETE FROM contact_estimates
WHERE model_revision IN (
    SELECT model_revision
    FROM model_revisions
    WHERE parent_revision IS NOT NULL AND NOT is_current
);
