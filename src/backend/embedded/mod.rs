//! The embedded stores: one data directory (`storage`), the scheduler with
//! its redb job database (`jobs`), and the files beside it, on this one
//! machine. The default deployment: the code paths are the scheduler's and
//! the data directory's own, with the file and database work run on
//! tokio's blocking threads as the API's handlers used to.
//!
//! The two stores share the data directory: an upload is staged in
//! `tmp/ID/` ([`EmbeddedArtifacts`]) and appears, files and record
//! together, when [`EmbeddedJobs::insert_scene`] renames it into
//! `scenes/ID/`.
//!
//! [`EmbeddedJobs::insert_scene`]: crate::backend::JobStore::insert_scene

use std::io;
use std::path::Path;

use crate::datadir::DataDir;
use crate::jobs::{Scheduler, SchedulerConfig};

mod artifacts;
mod jobs;

pub use artifacts::EmbeddedArtifacts;
pub use jobs::EmbeddedJobs;

/// Opens the data directory (creating its layout, clearing what an
/// interrupted upload or deletion left), resumes the job queue and starts
/// the scheduler: the job store and the artifact store over it.
pub fn open(data_dir: &Path, config: SchedulerConfig) -> io::Result<(EmbeddedJobs, EmbeddedArtifacts)> {
    let storage = DataDir::open(data_dir)?;
    let scheduler = Scheduler::open(storage.clone(), config)?;
    Ok((EmbeddedJobs::new(scheduler, storage.clone()), EmbeddedArtifacts::new(storage)))
}

/// Runs file or database work on tokio's blocking threads.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> io::Result<T> {
    tokio::task::spawn_blocking(f).await.map_err(|e| io::Error::other(format!("worker task failed: {e}")))
}

/// An argument a store refuses (ids are made by the service: a bad one is
/// a caller's mistake, answered rather than acted on).
fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}
