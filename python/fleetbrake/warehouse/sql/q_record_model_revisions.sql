-- The model revisions in the order they were made, and which is current (the revision whose
-- predictions a recording shows unless another is asked for).
SELECT model_revision, is_current
FROM model_revisions
ORDER BY created_utc;
