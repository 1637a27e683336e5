//! What a worker counts for `/metrics`: the training counters its jobs
//! update (as the embedded scheduler's), and its own: claims, jobs taken
//! back from dead workers, leases it lost, jobs running now.

use std::sync::atomic::{AtomicU64, Ordering};

use crate::jobs::Counters;

/// A worker's counters.
#[derive(Default)]
pub struct WorkerStats {
    /// Training steps, rays and time of the jobs it ran.
    pub train: Counters,
    /// Jobs it claimed.
    pub claims: AtomicU64,
    /// Jobs it took back from workers whose lease expired.
    pub reclaimed: AtomicU64,
    /// Runs it stopped because it may have lost their lease.
    pub leases_lost: AtomicU64,
    /// Jobs it runs now.
    pub running: AtomicU64,
}

impl WorkerStats {
    /// `(name, help, type, value)` of each of its own series.
    pub fn series(&self) -> [(&'static str, &'static str, &'static str, u64); 4] {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        [
            ("radiance_worker_running_jobs", "Jobs this worker runs now.", "gauge", get(&self.running)),
            ("radiance_worker_claims_total", "Jobs this worker claimed.", "counter", get(&self.claims)),
            (
                "radiance_jobs_reclaimed_total",
                "Jobs this worker took back from workers whose lease expired.",
                "counter",
                get(&self.reclaimed),
            ),
            (
                "radiance_worker_leases_lost_total",
                "Runs this worker stopped because it may have lost their lease.",
                "counter",
                get(&self.leases_lost),
            ),
        ]
    }
}
