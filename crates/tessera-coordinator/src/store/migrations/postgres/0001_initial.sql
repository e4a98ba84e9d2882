-- Tessera PostgreSQL store, schema version 1: the tables of the SQLite schema at its
-- version 3 (migrations/000*.sql), in PostgreSQL's types. Integers that are u64 in Rust
-- are BIGINT (times and ids are below 2^63), so both stores decode rows with the same
-- code (store/rows.rs). No commit generation: the commit marker is SQLite's alone
-- (docs/store.md).

CREATE TABLE jobs (
    -- From a sequence: never reused, even after a rolled-back insert.
    id                    BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    idempotency_key       TEXT UNIQUE,
    name                  TEXT,
    scene_ref             TEXT NOT NULL,
    settings_json         TEXT NOT NULL,
    plan_width            BIGINT NOT NULL,
    plan_height           BIGINT NOT NULL,
    plan_tile_size        BIGINT NOT NULL,
    plan_samples_per_pass BIGINT NOT NULL,
    plan_passes           BIGINT NOT NULL,
    first_frame           BIGINT NOT NULL,
    last_frame            BIGINT NOT NULL,
    passes_per_unit       BIGINT NOT NULL,
    priority              BIGINT NOT NULL,
    state                 TEXT NOT NULL
        CHECK (state IN ('queued', 'running', 'done', 'failed', 'canceled')),
    error                 TEXT,
    created_unix_ms       BIGINT NOT NULL,
    started_unix_ms       BIGINT,
    finished_unix_ms      BIGINT,
    -- The crash-loop guard (docs/store.md, "No crash loop").
    resumes               BIGINT NOT NULL DEFAULT 0,
    resume_passes         BIGINT NOT NULL DEFAULT 0
);

CREATE INDEX jobs_by_state ON jobs (state, id);

CREATE TABLE scenes (
    hash            TEXT PRIMARY KEY,
    size            BIGINT NOT NULL,
    data            BYTEA NOT NULL,
    stored_unix_ms  BIGINT NOT NULL
);

-- One merged checkpoint per (job, frame, tile); blob formats in store/mod.rs.
CREATE TABLE tiles (
    job               BIGINT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    frame             BIGINT NOT NULL,
    tile              BIGINT NOT NULL,
    merged_passes     BIGINT NOT NULL,
    stats             BYTEA NOT NULL,
    units             BYTEA NOT NULL,
    rejected_samples  BIGINT NOT NULL DEFAULT 0,
    PRIMARY KEY (job, frame, tile)
);

CREATE TABLE counters (
    name   TEXT PRIMARY KEY,
    value  BIGINT NOT NULL
);

INSERT INTO counters (name, value) VALUES
    ('lease_high_water', 0),
    -- 1 while no coordinator runs on the store after a graceful shutdown.
    ('clean_shutdown', 1),
    -- The job a starting coordinator is resuming (0: none).
    ('resuming_job', 0);

CREATE TABLE history (
    seq              BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    job              BIGINT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    elapsed_seconds  DOUBLE PRECISION NOT NULL,
    spp              DOUBLE PRECISION NOT NULL,
    error_estimate   DOUBLE PRECISION
);

CREATE INDEX history_by_job ON history (job, seq);

-- No foreign key on job: a fault may concern a job that does not exist (a bogus result).
CREATE TABLE faults (
    id       BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
    worker   TEXT NOT NULL,
    job      BIGINT,
    kind     TEXT NOT NULL,
    message  TEXT NOT NULL,
    unix_ms  BIGINT NOT NULL
);

CREATE INDEX faults_by_job ON faults (job, id);
CREATE INDEX faults_by_worker ON faults (worker, id);
