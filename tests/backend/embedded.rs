//! The contract on the embedded pair: a scheduler and a fresh data
//! directory per check.

use std::sync::Arc;

use radiance::backend::embedded;
use radiance::jobs::SchedulerConfig;

use crate::contract::{Opening, Settings, Stores};

/// The embedded stores over a temporary data directory (removed when the
/// stores are dropped), saving checkpoints every 0.2 s of training.
fn open(settings: Settings) -> Opening {
    Box::pin(async move {
        let dir = tempfile::tempdir().unwrap();
        let config = SchedulerConfig {
            max_queued: settings.max_queued,
            run_jobs: settings.run_jobs,
            checkpoint_every: 0.2,
            ..SchedulerConfig::default()
        };
        let path = dir.path().to_path_buf();
        let opened = tokio::task::spawn_blocking(move || embedded::open(&path, config)).await.unwrap();
        let (jobs, artifacts) = opened.unwrap();
        Stores { jobs: Arc::new(jobs), artifacts: Arc::new(artifacts), _keep: Box::new(dir) }
    })
}

contract_tests!(open);
