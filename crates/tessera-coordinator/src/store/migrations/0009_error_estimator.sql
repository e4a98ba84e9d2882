-- Tessera store, schema version 9: the name of the estimator a job's stored error
-- estimate was computed with (`tessera_farm::ErrorEstimator::name`, with the bias term
-- of a merging integrator), written with each history point, so that the status of a job
-- read back from the store names the estimate it shows, not this build's estimator (the
-- robust scale's level changed on 2026-12-06, and with it the estimates and the name).
-- NULL for jobs whose history points were all stored before this version: their status
-- names no estimator.

ALTER TABLE jobs ADD COLUMN error_estimator TEXT;
