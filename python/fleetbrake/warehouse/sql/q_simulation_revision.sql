-- One model revision's effects and solver. Parameters: $name.
SELECT parameters_json, solver
FROM model_revisions
WHERE model_revision = $name;
