//! Where the service's shared state can live beyond one machine
//! (docs/design/scale-out.md): for now only `pg`, the PostgreSQL job queue
//! and its records, which nothing in the service uses yet. The embedded
//! store (`jobs` and `storage`) remains the default.

use crate::jobs::JobSpec;

pub mod pg;

/// A job to enqueue: what the API hands a job store.
#[derive(Clone, Debug)]
pub struct NewJob {
    /// The job's id, chosen by the caller (from `storage::new_id("job")`)
    /// when a record must name the job first; `None`: a fresh one.
    pub id: Option<String>,
    pub spec: JobSpec,
    /// Video: the model rendered (training jobs start without one).
    pub model_id: Option<String>,
    /// Estimated peak memory of the job, bytes.
    pub memory_estimate: u64,
}
