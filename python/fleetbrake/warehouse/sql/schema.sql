-- fleetbrake warehouse: tables of the ingestion and of the event detection (schema version 3).
-- Applied at every open of the database; every statement is idempotent. Views are in v_*.sql,
-- statements the code runs with bound parameters in q_*.sql.

CREATE TABLE IF NOT EXISTS schema_version (
    version     INTEGER   NOT NULL,   -- schema version of the tables below
    applied_utc TIMESTAMP NOT NULL    -- when a fleetbrake of that version first opened the file
);

-- One row per log file seen under <fleet>/logs (hidden files ignored). A file is identified by
-- its path and the sha256 of its bytes: a path seen again with other bytes replaces its row
-- (and its samples) in one transaction.
CREATE TABLE IF NOT EXISTS files (
    file_id              BIGINT    NOT NULL PRIMARY KEY,  -- 1, 2, ... in ingestion order
    path                 VARCHAR   NOT NULL UNIQUE,       -- relative to the fleet directory, '/'
    wagon_id             VARCHAR,                         -- from the path; null if it names none
    sha256               VARCHAR   NOT NULL,              -- of the bytes as stored (gzip or not)
    size_bytes           BIGINT    NOT NULL,
    mtime_ns             BIGINT    NOT NULL,              -- unchanged size and mtime: not re-read
    status               VARCHAR   NOT NULL CHECK (status IN ('ingested', 'quarantined')),
    quarantine_code      VARCHAR,  -- name, registry, size, empty, gzip, binary, header,
                                   -- unreadable, error (the last two and registry: retried),
                                   -- rows (every data row read was rejected)
    reason               VARCHAR,  -- why quarantined, naming the file (and line); for an
                                   -- ingested file, the rows rejected (lines and why)
    rows                 BIGINT    NOT NULL,              -- samples stored from this file
    rows_in_file         BIGINT,   -- data lines read (after the header), = rows + rows_rejected
    rows_no_time         BIGINT,   -- dropped: time cell empty or not a time
    rows_outside_session BIGINT,   -- dropped: time before the file name's or > 48 h after it
    rows_duplicate       BIGINT,   -- dropped: time already seen in the file (first row kept)
    rows_out_of_order    BIGINT,   -- kept, sorted: time earlier than a previous row's
    cells_unparsable     BIGINT,   -- cells with a value that is not a finite number, or that
                                   -- is outside its channel's plausible range: now null
    block_temp_faults    BIGINT,   -- block_temp_c readings out of range: kept as faults
    partial_row_dropped  BOOLEAN,  -- the file ended inside a row (unit lost power)
    repairs              VARCHAR,  -- the repairs above, readable, with line numbers
    first_utc            TIMESTAMP,  -- first and last stored sample
    last_utc             TIMESTAMP,
    ingested_utc         TIMESTAMP NOT NULL  -- when this row was written
);
-- Rows read but not stored (no time, outside the session, a repeated time, a last row cut
-- short): rows_in_file = rows + rows_rejected. Null when no row was read (quarantined before
-- its rows), and for files recorded by schema version 1, which did not count them.
ALTER TABLE files ADD COLUMN IF NOT EXISTS rows_rejected BIGINT;

-- One row per run of consecutive lines of a file rejected for the same reason (v_file_rejections):
-- written and removed with the file's row.
CREATE TABLE IF NOT EXISTS file_rejections (
    file_id    BIGINT  NOT NULL,  -- files.file_id
    first_line BIGINT  NOT NULL,  -- line numbers in the file, the header being line 1
    last_line  BIGINT  NOT NULL,
    rows       BIGINT  NOT NULL,  -- last_line - first_line + 1
    reason     VARCHAR NOT NULL   -- why these rows were rejected
);

-- One row per stored sample (one second of one wagon), sorted by time within a file.
CREATE TABLE IF NOT EXISTS samples (
    wagon_id           VARCHAR   NOT NULL,
    file_id            BIGINT    NOT NULL,   -- files.file_id
    time_utc           TIMESTAMP NOT NULL,
    speed_kmh          DOUBLE,
    distance_m         DOUBLE,    -- since the session (file) began
    elevation_m        DOUBLE,
    lat_deg            DOUBLE,
    lon_deg            DOUBLE,
    brake_pressure_bar DOUBLE,
    block_temp_c       DOUBLE,    -- valid readings only: null where missing or faulty
    block_temp_raw_c   DOUBLE,    -- the raw reading where block_temp_fault is set, else null
    block_temp_fault   BOOLEAN   NOT NULL,  -- reading out of range (below -60 or above 600 degC):
                                          -- a broken wire, not a temperature
    ambient_temp_c     DOUBLE
);

-- Time ranges of a wagon whose samples changed since events were last detected there.
-- Written in the same transaction as the samples; removed when the events are recomputed.
CREATE TABLE IF NOT EXISTS event_dirty (
    wagon_id VARCHAR   NOT NULL,
    from_utc TIMESTAMP NOT NULL,
    to_utc   TIMESTAMP NOT NULL,
    file_id  BIGINT    NOT NULL   -- the file whose ingestion (or replacement) made it dirty
);

-- One row per detected braking event (fleetbrake.events).
CREATE TABLE IF NOT EXISTS events (
    event_id        VARCHAR   NOT NULL PRIMARY KEY,  -- <wagon_id>-<start as YYYYMMDDTHHMMSS>
    wagon_id        VARCHAR   NOT NULL,
    start_utc       TIMESTAMP NOT NULL,  -- activation: pressure leaves its baseline
    end_utc         TIMESTAMP NOT NULL,  -- release: pressure back at its baseline
    duration_s      DOUBLE    NOT NULL,
    distance_m      DOUBLE,              -- travelled between start and end
    v_start_kmh     DOUBLE,
    v_end_kmh       DOUBLE,
    p_mean_bar      DOUBLE,              -- time average of the pressure (paper eq. 1)
    p_max_bar       DOUBLE,
    t_block_start_c DOUBLE,              -- measured at activation; null if missing or faulty
    kind            VARCHAR   NOT NULL CHECK (kind IN ('stop', 'slowdown', 'drag')),
    complete        BOOLEAN   NOT NULL,  -- false: begins or ends at a data gap or session edge
    detected_utc    TIMESTAMP NOT NULL   -- when this row was (re)computed with other values
);
