-- fleetbrake warehouse: tables of the simulation, the flags and the closed loop.
-- Applied with schema.sql at every open; idempotent.

-- One row per model revision. `declared` is the model of block-model.md; each closed loop
-- adds a child with the effect it found and its fitted parameters.
CREATE TABLE IF NOT EXISTS model_revisions (
    model_revision  VARCHAR   NOT NULL PRIMARY KEY,
    parent_revision VARCHAR,             -- null for `declared`
    effect          VARCHAR,             -- interface.md vocabulary; '+'-joined when several
    parameters_json VARCHAR   NOT NULL,  -- the effects and their parameters, JSON
    rmse_fit_k      DOUBLE,              -- measured vs predicted on the fit events
    rmse_holdout_k  DOUBLE,              -- ... and on the holdout events
    solver          VARCHAR   NOT NULL CHECK (solver IN ('rom', 'full')),  -- what predicted
    is_current      BOOLEAN   NOT NULL,  -- the revision `run` simulates new events with
    created_utc     TIMESTAMP NOT NULL
);
-- The mesh refinement of the revision's model (1.0: the default mesh; null in databases made
-- before it was recorded: the default). A closed loop's child keeps its parent's.
ALTER TABLE model_revisions ADD COLUMN IF NOT EXISTS refinement DOUBLE;

-- Predictions per event, per second, per model revision: from activation until 600 s after
-- release, or the next event, or the end of the data, whichever is first.
CREATE TABLE IF NOT EXISTS predictions (
    event_id                 VARCHAR   NOT NULL,
    wagon_id                 VARCHAR   NOT NULL,
    time_utc                 TIMESTAMP NOT NULL,
    model_revision           VARCHAR   NOT NULL,
    phase                    VARCHAR   NOT NULL CHECK (phase IN ('heating', 'cooling')),
    measured_sensor_c        DOUBLE,    -- null where the reading is missing or faulty
    predicted_sensor_c       DOUBLE    NOT NULL,
    predicted_contact_mean_c DOUBLE    NOT NULL,  -- mean over the friction face
    predicted_contact_max_c  DOUBLE    NOT NULL,  -- maximum over the friction face
    speed_kmh                DOUBLE,
    brake_pressure_bar       DOUBLE,
    ambient_c                DOUBLE    NOT NULL,  -- the air temperature the model used
    flux_w_m2                DOUBLE    NOT NULL   -- the heat input the model used
);

-- The block simulated through each span of a wagon's data, per model revision, at every logged
-- second: the timeline the flags judge (fleetbrake.simulation.chains). Re-anchored to the
-- measurement at the start of every segment (timeline_segments), so measured - predicted
-- starts at zero in each and shows what the model cannot explain.
CREATE TABLE IF NOT EXISTS timeline (
    wagon_id                 VARCHAR   NOT NULL,
    model_revision           VARCHAR   NOT NULL,
    time_utc                 TIMESTAMP NOT NULL,
    predicted_sensor_c       DOUBLE    NOT NULL,
    predicted_contact_mean_c DOUBLE    NOT NULL,  -- mean over the friction face
    predicted_contact_max_c  DOUBLE    NOT NULL   -- maximum over the friction face
);

-- The chain state of each timeline: its segments (a braking, a quiet window, a data gap),
-- each re-anchored at its start, within spans of data simulated from a uniform start.
CREATE TABLE IF NOT EXISTS timeline_segments (
    wagon_id       VARCHAR   NOT NULL,
    model_revision VARCHAR   NOT NULL,
    span_start_utc TIMESTAMP NOT NULL,  -- first sample of the span (a longer gap before it)
    span_end_utc   TIMESTAMP NOT NULL,  -- last sample of the span
    start_utc      TIMESTAMP NOT NULL,  -- the segment: [start_utc, stop_utc)
    stop_utc       TIMESTAMP NOT NULL,
    kind           VARCHAR   NOT NULL CHECK (kind IN ('braking', 'quiet', 'gap')),
    event_id       VARCHAR,             -- the event whose activation starts a braking segment
    anchor         VARCHAR   NOT NULL CHECK (anchor IN ('start', 'before', 'after', 'none')),
    shift_k        DOUBLE    NOT NULL,  -- uniform shift of the field at start_utc
    reference_c    DOUBLE    NOT NULL   -- the field's reference temperature after it
);

-- One row per anomaly raised.
CREATE TABLE IF NOT EXISTS flags (
    flag_id      VARCHAR   NOT NULL PRIMARY KEY,
    wagon_id     VARCHAR   NOT NULL,
    event_id     VARCHAR,   -- null when not tied to one event
    kind         VARCHAR   NOT NULL CHECK (kind IN ('dragging_brake', 'weak_brake', 'sensor_fault', 'overheating')),
    severity     VARCHAR   NOT NULL CHECK (severity IN ('info', 'warning', 'alarm')),
    start_utc    TIMESTAMP NOT NULL,
    end_utc      TIMESTAMP NOT NULL,
    evidence     VARCHAR   NOT NULL,   -- a sentence a maintainer can act on
    detected_utc TIMESTAMP NOT NULL
);

-- The registry entries the last `run` used (so that commands given only --db, like
-- close-loop, simulate each wagon as `run` did).
CREATE TABLE IF NOT EXISTS wagon_registry (
    wagon_id    VARCHAR   NOT NULL PRIMARY KEY,
    config_json VARCHAR   NOT NULL,  -- the WagonConfig's fields, JSON
    source      VARCHAR   NOT NULL,  -- the fleet.toml it came from
    updated_utc TIMESTAMP NOT NULL
);

-- The spans of each wagon's data: maximal stretches of its samples without a gap longer than
-- ChainParams.bridge_max_s (6 h), the cut the simulation makes. The unit of work of the
-- simulation, the estimate and the flags: a stage recomputes a span whose data_key changed.
-- Maintained after the event detection from the files that changed (spanned_files), over the
-- samples of the affected time ranges only (fleetbrake.ingest.spans).
CREATE TABLE IF NOT EXISTS spans (
    wagon_id       VARCHAR   NOT NULL,
    span_start_utc TIMESTAMP NOT NULL,  -- its first sample
    span_end_utc   TIMESTAMP NOT NULL,  -- its last sample
    sample_rows    BIGINT    NOT NULL,  -- samples in it (what the stages' chunks are sized by)
    data_key       VARCHAR   NOT NULL   -- its files (identity, bytes, rows in it), its
                                        -- samples' count and its events
);

-- The ingested files as the spans were last cut from them: a file added, removed or replaced
-- since marks its time range for cutting again.
CREATE TABLE IF NOT EXISTS spanned_files (
    file_id   BIGINT    NOT NULL,
    wagon_id  VARCHAR   NOT NULL,
    sha256    VARCHAR   NOT NULL,
    rows      BIGINT    NOT NULL,
    first_utc TIMESTAMP NOT NULL,
    last_utc  TIMESTAMP NOT NULL
);

-- Which spans were simulated with which revision, and from what (a span is simulated again
-- when its data_key or what it is simulated with changed; the rows of a span that no longer
-- exists are deleted).
CREATE TABLE IF NOT EXISTS simulated_spans (
    wagon_id       VARCHAR   NOT NULL,
    model_revision VARCHAR   NOT NULL,
    span_start_utc TIMESTAMP NOT NULL,
    span_end_utc   TIMESTAMP NOT NULL,
    data_key       VARCHAR   NOT NULL,  -- spans.data_key as simulated
    model_key      VARCHAR   NOT NULL,  -- its registry entry, the revision, the parameters
    events         BIGINT    NOT NULL,  -- event windows stored in predictions
    simulated_utc  TIMESTAMP NOT NULL
);

-- Which spans were estimated with which revision, from what and with which noise.
CREATE TABLE IF NOT EXISTS estimated_spans (
    wagon_id           VARCHAR   NOT NULL,
    model_revision     VARCHAR   NOT NULL,
    span_start_utc     TIMESTAMP NOT NULL,
    span_end_utc       TIMESTAMP NOT NULL,
    data_key           VARCHAR   NOT NULL,  -- spans.data_key as estimated
    model_key          VARCHAR   NOT NULL,  -- registry entry, revision, sigma_w, configuration
    seconds            BIGINT    NOT NULL,  -- seconds estimated
    measurement_k      DOUBLE,              -- sigma_v, the span's own unless given
    power_w_per_sqrt_s DOUBLE,              -- sigma_w, the revision's
    created_utc        TIMESTAMP NOT NULL
);

-- When each span's flags were last judged, with which revision, data and thresholds, and how
-- many flags (those starting in the span) that stored.
CREATE TABLE IF NOT EXISTS flagged_spans (
    wagon_id       VARCHAR   NOT NULL,
    model_revision VARCHAR   NOT NULL,
    span_start_utc TIMESTAMP NOT NULL,
    span_end_utc   TIMESTAMP NOT NULL,
    data_key       VARCHAR   NOT NULL,  -- spans.data_key as judged
    config_key     VARCHAR   NOT NULL,  -- FlagConfig.key()
    flag_count     BIGINT    NOT NULL,
    updated_utc    TIMESTAMP NOT NULL
);
