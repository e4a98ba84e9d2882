-- Tessera store, schema version 4: the adaptive policy's state of a tile, saved with its
-- merged passes (issue 15), so a restart resumes an adaptive job where its policy was and
-- a finished adaptive job's image is rebuilt from the store. NULL for jobs without
-- adaptive stopping and for checkpoints written before the column existed.

ALTER TABLE tiles ADD COLUMN adaptive BLOB;
