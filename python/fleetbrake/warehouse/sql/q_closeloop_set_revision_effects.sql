-- Replace the effects (and their parameters) of revision $name: the closed loop refits them
-- after judging the flags again with the new revision.
-- Parameters: $name, $parameters_json.
UPDATE model_revisions
SET parameters_json = $parameters_json
WHERE model_revision = $name;
