-- Tessera store (PostgreSQL), schema version 6: row checksums (docs/store.md,
-- "Checksums"), as the SQLite schema's version 7. A SHA-256 over the columns an image
-- depends on, written with every row of jobs, tiles and scenes and verified whenever the
-- row is read (store/checksum.rs). The columns are added empty; the migration's
-- transaction then fills them for every existing row (store/sql.rs).

ALTER TABLE jobs ADD COLUMN checksum BYTEA;
ALTER TABLE tiles ADD COLUMN checksum BYTEA;
ALTER TABLE scenes ADD COLUMN checksum BYTEA;
