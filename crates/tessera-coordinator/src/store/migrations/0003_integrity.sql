-- Tessera store, schema version 3: storage integrity and the crash-loop guard
-- (docs/store.md).

-- Incremented in every transaction an answer depends on (a new job, a job's state
-- change, a stored scene); the commit marker file next to the database records it after
-- the commit, so a database that lost acknowledged commits is refused at open.
INSERT INTO counters (name, value) VALUES ('commit_generation', 0);

-- 1 while no coordinator runs on the store after a graceful shutdown; set to 0 at open.
-- A start that finds 0 follows a crash. A store written by an older build counts as
-- shut down cleanly.
INSERT INTO counters (name, value) VALUES ('clean_shutdown', 1);

-- The job a starting coordinator is resuming (0: none). Found set at the next start,
-- the previous start died while resuming that job.
INSERT INTO counters (name, value) VALUES ('resuming_job', 0);

-- Consecutive restarts after a crash that resumed the job without any new merged pass,
-- and the merged passes when it was last resumed.
ALTER TABLE jobs ADD COLUMN resumes INTEGER NOT NULL DEFAULT 0;
ALTER TABLE jobs ADD COLUMN resume_passes INTEGER NOT NULL DEFAULT 0;
