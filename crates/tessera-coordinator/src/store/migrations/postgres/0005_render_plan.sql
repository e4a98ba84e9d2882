-- Tessera store (PostgreSQL), schema version 5: a job's render plan and its error
-- estimate's caveat (issue 15), written when the job is accepted, so the status of a job
-- read back from the store (a finished job after a restart, or on another coordinator of
-- the same database) still says which effects the plan found and why its error estimate
-- may be optimistic. NULL for jobs accepted before this version, and for a job whose
-- estimate has no caveat.

ALTER TABLE jobs ADD COLUMN render_plan_json TEXT;
ALTER TABLE jobs ADD COLUMN error_estimate_caveat TEXT;
