-- Record one log file seen (ingested or quarantined). Parameters: one per column.
INSERT INTO files (
    file_id, path, wagon_id, sha256, size_bytes, mtime_ns, status, quarantine_code, reason,
    rows, rows_in_file, rows_no_time, rows_outside_session, rows_duplicate, rows_out_of_order,
    cells_unparsable, block_temp_faults, partial_row_dropped, repairs, first_utc, last_utc,
    ingested_utc
)
VALUES (
    $file_id, $path, $wagon_id, $sha256, $size_bytes, $mtime_ns, $status, $quarantine_code,
    $reason, $rows, $rows_in_file, $rows_no_time, $rows_outside_session, $rows_duplicate,
    $rows_out_of_order, $cells_unparsable, $block_temp_faults, $partial_row_dropped, $repairs,
    $first_utc, $last_utc, $ingested_utc
);
