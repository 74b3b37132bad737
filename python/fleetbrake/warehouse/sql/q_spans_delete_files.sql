-- Forget the files $file_ids (a list) as the spans saw them (recorded again next, as they are
-- now, in the same transaction).
DELETE FROM spanned_files
WHERE list_contains(CAST($file_ids AS BIGINT[]), file_id);
