-- Tessera store, schema version 2: per tile checkpoint, the samples the renderers dropped
-- as NaN, infinite or negative radiance in its merged units (a diagnostic summed per job
-- in the job status). Checkpoints written before the column existed read as 0.

ALTER TABLE tiles ADD COLUMN rejected_samples INTEGER NOT NULL DEFAULT 0;
