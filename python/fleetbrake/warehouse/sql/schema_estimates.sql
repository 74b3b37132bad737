-- fleetbrake warehouse: the virtual sensor's tables (fleetbrake.simulation.estimates).
-- Applied with schema.sql at every open; idempotent.

-- The contact-temperature estimate per wagon and model revision: a Kalman filter (live) and
-- Rauch-Tung-Striebel smoother (after the fact) on the reduced model's state with the
-- unexplained friction-face heat power as an unknown input (docs/estimator.md), run through
-- every logged second. Stored per second (resolution_s = 1) inside the estimate windows and
-- per minute (resolution_s = 60: the minute's means, extremes and root mean squares, at the
-- minute's start) elsewhere (fleetbrake.warehouse.estimate_windows). Behind
-- v_contact_estimates; the columns after innovation_k are for the flags and the recordings.
-- Bounds are 95 % (mean ± 1.96 sd).
CREATE TABLE IF NOT EXISTS contact_estimates (
    wagon_id                    VARCHAR   NOT NULL,
    time_utc                    TIMESTAMP NOT NULL,
    model_revision              VARCHAR   NOT NULL,
    contact_mean_c              DOUBLE    NOT NULL,  -- filtered friction-face mean
    contact_mean_lo_c           DOUBLE    NOT NULL,
    contact_mean_hi_c           DOUBLE    NOT NULL,
    contact_max_c               DOUBLE    NOT NULL,  -- filtered friction-face maximum
    contact_max_hi_c            DOUBLE    NOT NULL,
    smoothed_contact_mean_c     DOUBLE,              -- null until smoothed
    smoothed_contact_mean_lo_c  DOUBLE,
    smoothed_contact_mean_hi_c  DOUBLE,
    unexplained_power_w         DOUBLE    NOT NULL,  -- filtered heat into the friction face, W
    unexplained_power_lo_w      DOUBLE    NOT NULL,
    unexplained_power_hi_w      DOUBLE    NOT NULL,
    innovation_k                DOUBLE,              -- reading - predicted reading; null: no reading
    innovation_sd_k             DOUBLE,              -- its standard deviation (sqrt S)
    smoothed_contact_max_c      DOUBLE,
    smoothed_contact_max_hi_c   DOUBLE,
    smoothed_unexplained_power_w    DOUBLE,
    smoothed_unexplained_power_lo_w DOUBLE,
    smoothed_unexplained_power_hi_w DOUBLE,
    resolution_s                INTEGER   NOT NULL   -- 1: the second's row; 60: the minute's
);
-- Databases of schema version 2 gain the column, 1 on their rows (per-second rows; the
-- migration to version 3 then compacts them and drops the default).
ALTER TABLE contact_estimates ADD COLUMN IF NOT EXISTS resolution_s INTEGER DEFAULT 1;

-- Which wagons were estimated with which revision, and from what (incremental runs: a wagon
-- is estimated again when its data, its registry entry, the revision or the noise changed).
CREATE TABLE IF NOT EXISTS estimated_wagons (
    wagon_id       VARCHAR   NOT NULL,
    model_revision VARCHAR   NOT NULL,
    data_key       VARCHAR   NOT NULL,  -- the wagon's files and samples as estimated
    model_key      VARCHAR   NOT NULL,  -- its registry entry, the revision, the noise, the config
    seconds        BIGINT    NOT NULL,  -- rows stored in contact_estimates
    created_utc    TIMESTAMP NOT NULL
);
-- The noise each wagon was estimated with: sigma_v its own (from its readings) unless given,
-- sigma_w the revision's (added after the table was first made: warehouses of before get it).
ALTER TABLE estimated_wagons ADD COLUMN IF NOT EXISTS measurement_k DOUBLE;
ALTER TABLE estimated_wagons ADD COLUMN IF NOT EXISTS power_w_per_sqrt_s DOUBLE;

-- A model revision's sigma_w (the unexplained power's diffusion), fitted by maximum
-- likelihood on the innovations of the close loop's fit days when it made the revision
-- (method 'ml'); a revision without a row uses the documented default. measurement_k: the
-- median of the fit wagons' own sigma_v (for the record: each wagon is estimated with its own,
-- estimated_wagons.measurement_k).
CREATE TABLE IF NOT EXISTS estimator_noise (
    model_revision     VARCHAR   NOT NULL PRIMARY KEY,
    measurement_k      DOUBLE    NOT NULL,  -- sigma_v, K
    power_w_per_sqrt_s DOUBLE    NOT NULL,  -- sigma_w, W/sqrt(s)
    method             VARCHAR   NOT NULL CHECK (method IN ('ml', 'given')),
    fit_wagons         VARCHAR,             -- the wagons (and seconds) of the fit data, JSON
    fit_readings       BIGINT,
    log_likelihood     DOUBLE,
    at_floor           BOOLEAN,             -- sigma_w ended at its floor
    created_utc        TIMESTAMP NOT NULL
);
