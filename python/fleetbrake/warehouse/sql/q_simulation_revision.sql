-- One model revision's effects, solver and mesh refinement (null: made before it was
-- recorded, the default mesh). Parameters: $name.
SELECT parameters_json, solver, refinement
FROM model_revisions
WHERE model_revision = $name;
