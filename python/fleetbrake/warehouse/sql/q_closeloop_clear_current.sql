-- No revision is current any more (the closed loop is about to insert the new current one, in
-- the same transaction).
UPDATE model_revisions
SET is_current = FALSE;
