-- Tessera store, schema version 5: the quarantine list (issue 15), so a restarted
-- coordinator keeps distrusting a worker a spot check found faulty. A quarantine follows
-- what a worker registers as: its name and the common name of its TLS client certificate
-- ('' without mutual TLS). One row per (worker, identity), kept from the first
-- quarantine until an operator lifts it (DELETE /api/v1/workers/{name}/quarantine).

CREATE TABLE quarantines (
    worker    TEXT NOT NULL,
    identity  TEXT NOT NULL,
    reason    TEXT NOT NULL,
    unix_ms   INTEGER NOT NULL,
    PRIMARY KEY (worker, identity)
) STRICT;
