//! The node's feed of job changes: one [`Listener`] (its own connection)
//! whose notices are handed to every follower of a job (an events stream)
//! through a broadcast channel, so a thousand followers cost one LISTEN.
//!
//! Notices are hints (see `notify`): when the listener's connection ends,
//! the feed connects again after [`RECONNECT_AFTER`] (until the feed is
//! dropped), and notices sent meanwhile are lost. Followers therefore also
//! read the job again after a bounded wait of their own
//! (`PgJobStore::job_changed`'s fallback), which covers the gap.

use std::time::Duration;

use tokio::sync::broadcast;
use tokio::task::JoinHandle;

use super::connect::Database;
use super::error::{PgError, chain};
use super::notify::Listener;

/// How long the feed waits before connecting again after its listener's
/// connection ended (or a new one failed).
pub const RECONNECT_AFTER: Duration = Duration::from_secs(1);

/// Notices kept for a follower that has not read them yet; one that falls
/// further behind is told it lagged (and reads the job again).
const BACKLOG: usize = 1024;

/// The ids of changed jobs, as they are announced.
pub struct Changes {
    ids: broadcast::Sender<String>,
    task: JoinHandle<()>,
}

impl Changes {
    /// Connects a listener (an error if it cannot: the database is then
    /// unreachable) and starts handing out its notices.
    pub async fn start(db: &Database) -> Result<Changes, PgError> {
        let first = Listener::start(db).await?;
        let (ids, _) = broadcast::channel(BACKLOG);
        let task = tokio::spawn(feed(db.clone(), first, ids.clone()));
        Ok(Changes { ids, task })
    }

    /// A receiver of the ids of jobs changed from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<String> {
        self.ids.subscribe()
    }

    /// Stops listening (also done when dropped).
    pub fn stop(&self) {
        self.task.abort();
    }
}

impl Drop for Changes {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Forwards the listener's notices; when its connection ends, connects a
/// new one every [`RECONNECT_AFTER`] until one succeeds. Ends when aborted.
async fn feed(db: Database, first: Listener, ids: broadcast::Sender<String>) {
    let mut listener = Some(first);
    loop {
        if let Some(mut l) = listener.take() {
            while let Some(notice) = l.recv().await {
                // No receiver now is fine: nobody follows a job.
                let _ = ids.send(notice.job_id().to_string());
            }
            tracing::warn!(database = %db.target(), "job change notices stopped: connecting again");
        }
        tokio::time::sleep(RECONNECT_AFTER).await;
        match Listener::start(&db).await {
            Ok(l) => {
                tracing::info!(database = %db.target(), "job change notices resumed");
                listener = Some(l);
            }
            Err(e) => tracing::warn!(error = %chain(&e), "cannot listen for job changes"),
        }
    }
}
