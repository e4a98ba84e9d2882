-- Tessera store, schema version 1.
-- Integers that are u64 in Rust are stored as INTEGER (i64): times and ids are below
-- 2^63; unit digests are stored by their bits inside a blob.

CREATE TABLE jobs (
    id                    INTEGER PRIMARY KEY AUTOINCREMENT,  -- never reused
    idempotency_key       TEXT UNIQUE,
    name                  TEXT,
    scene_ref             TEXT NOT NULL,
    settings_json         TEXT NOT NULL,
    plan_width            INTEGER NOT NULL,
    plan_height           INTEGER NOT NULL,
    plan_tile_size        INTEGER NOT NULL,
    plan_samples_per_pass INTEGER NOT NULL,
    plan_passes           INTEGER NOT NULL,
    first_frame           INTEGER NOT NULL,
    last_frame            INTEGER NOT NULL,
    passes_per_unit       INTEGER NOT NULL,
    priority              INTEGER NOT NULL,
    state                 TEXT NOT NULL
        CHECK (state IN ('queued', 'running', 'done', 'failed', 'canceled')),
    error                 TEXT,
    created_unix_ms       INTEGER NOT NULL,
    started_unix_ms       INTEGER,
    finished_unix_ms      INTEGER
) STRICT;

CREATE INDEX jobs_by_state ON jobs (state, id);

CREATE TABLE scenes (
    hash            TEXT PRIMARY KEY,
    size            INTEGER NOT NULL,
    data            BLOB NOT NULL,
    stored_unix_ms  INTEGER NOT NULL
) STRICT;

-- One merged checkpoint per (job, frame, tile); blob formats in store/mod.rs.
CREATE TABLE tiles (
    job            INTEGER NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    frame          INTEGER NOT NULL,
    tile           INTEGER NOT NULL,
    merged_passes  INTEGER NOT NULL,
    stats          BLOB NOT NULL,
    units          BLOB NOT NULL,
    PRIMARY KEY (job, frame, tile)
) STRICT;

CREATE TABLE counters (
    name   TEXT PRIMARY KEY,
    value  INTEGER NOT NULL
) STRICT;

INSERT INTO counters (name, value) VALUES ('lease_high_water', 0);

CREATE TABLE history (
    seq              INTEGER PRIMARY KEY,
    job              INTEGER NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    elapsed_seconds  REAL NOT NULL,
    spp              REAL NOT NULL,
    error_estimate   REAL
) STRICT;

CREATE INDEX history_by_job ON history (job, seq);

-- No foreign key on job: a fault may concern a job that does not exist (a bogus result).
CREATE TABLE faults (
    id       INTEGER PRIMARY KEY,
    worker   TEXT NOT NULL,
    job      INTEGER,
    kind     TEXT NOT NULL,
    message  TEXT NOT NULL,
    unix_ms  INTEGER NOT NULL
) STRICT;

CREATE INDEX faults_by_job ON faults (job, id);
CREATE INDEX faults_by_worker ON faults (worker, id);
