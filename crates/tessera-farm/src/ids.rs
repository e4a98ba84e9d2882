//! The identifiers of jobs and workers: a leaf shared by the scheduler and the spot
//! checks, so that neither depends on the other for its vocabulary.

/// Identifier of a job.
pub type JobId = u64;
/// Identifier of a worker.
pub type WorkerId = u64;
