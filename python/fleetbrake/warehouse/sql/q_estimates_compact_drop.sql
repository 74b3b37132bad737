-- Drop the minutes of the last compaction (q_estimates_compact_minutes.sql). No parameters.
DROP TABLE IF EXISTS compact_minutes;
