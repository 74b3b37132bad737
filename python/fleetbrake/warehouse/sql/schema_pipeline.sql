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

-- Which events were simulated with which revision (incremental runs; re-simulation when an
-- event's samples changed).
CREATE TABLE IF NOT EXISTS simulated_events (
    event_id       VARCHAR   NOT NULL,
    model_revision VARCHAR   NOT NULL,
    detected_utc   TIMESTAMP NOT NULL,  -- events.detected_utc the simulation saw
    simulated_utc  TIMESTAMP NOT NULL
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
