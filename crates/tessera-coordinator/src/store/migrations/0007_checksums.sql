-- Tessera store, schema version 7: row checksums (docs/store.md, "Checksums"). A SHA-256
-- over the columns an image depends on, written with every row of jobs, tiles and scenes
-- and verified whenever the row is read (store/checksum.rs). The columns are added
-- empty; the migration's transaction then fills them for every existing row (the Rust
-- side of the migration, store/sql.rs), so after it every row has a checksum.

ALTER TABLE jobs ADD COLUMN checksum BLOB;
ALTER TABLE tiles ADD COLUMN checksum BLOB;
ALTER TABLE scenes ADD COLUMN checksum BLOB;
