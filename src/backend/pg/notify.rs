//! Notices of job changes: the `jobs` trigger announces each change on the
//! [`CHANNEL`] with the payload `<event>:<job id>`, delivered at commit. A
//! [`Listener`] holds a connection of its own (LISTEN is per session, so not
//! a pooled one) and hands the notices out in order.
//!
//! Notices are hints: one sent while no listener was connected is lost, so
//! after a reconnect the reader reads the rows again rather than trusting
//! it has seen every change. Reconnecting is the caller's (a `Listener`
//! whose connection ended answers `None`; start another).

use tokio::sync::mpsc;
use tokio::task::JoinHandle;
use tokio_postgres::{AsyncMessage, Client};

use super::connect::Database;
use super::error::{PgError, chain};

/// The channel the `jobs` trigger notifies (`migrations/0001_init.sql`).
pub const CHANNEL: &str = "radiance";

/// A change of a job, as the trigger announces it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Notice {
    /// The job became claimable (enqueued, or queued again).
    Queued(String),
    /// A client asked the running job to stop.
    Cancel(String),
    /// Any other change (claimed, progress, finished...).
    Changed(String),
}

impl Notice {
    /// Reads a payload `queued:<id>`, `cancel:<id>` or `job:<id>`.
    pub fn parse(payload: &str) -> Option<Notice> {
        let (event, id) = payload.split_once(':')?;
        if id.is_empty() {
            return None;
        }
        let id = id.to_string();
        match event {
            "queued" => Some(Notice::Queued(id)),
            "cancel" => Some(Notice::Cancel(id)),
            "job" => Some(Notice::Changed(id)),
            _ => None,
        }
    }

    pub fn job_id(&self) -> &str {
        match self {
            Notice::Queued(id) | Notice::Cancel(id) | Notice::Changed(id) => id,
        }
    }
}

/// A connection LISTENing on [`CHANNEL`].
pub struct Listener {
    /// Kept so the session (and its LISTEN) lasts as long as the listener.
    _client: Client,
    notices: mpsc::UnboundedReceiver<Notice>,
    task: JoinHandle<()>,
}

impl Listener {
    /// Connects and LISTENs; notices of changes committed from now on
    /// arrive in [`Self::recv`].
    pub async fn start(db: &Database) -> Result<Listener, PgError> {
        let (client, mut connection) = db.connect_raw().await?;
        let (tx, notices) = mpsc::unbounded_channel();
        let target = db.target().to_string();
        // Polling for messages is also what drives the connection: the
        // LISTEN below goes out through this task.
        let task = tokio::spawn(async move {
            loop {
                match std::future::poll_fn(|cx| connection.poll_message(cx)).await {
                    Some(Ok(AsyncMessage::Notification(n))) if n.channel() == CHANNEL => {
                        match Notice::parse(n.payload()) {
                            Some(notice) => {
                                if tx.send(notice).is_err() {
                                    break; // the listener was dropped
                                }
                            }
                            None => tracing::warn!(payload = n.payload(), "unexpected job notice"),
                        }
                    }
                    Some(Ok(_)) => {} // other channels, server notices
                    Some(Err(e)) => {
                        tracing::warn!(database = %target, error = %chain(&e), "the listener's connection ended");
                        break;
                    }
                    None => break,
                }
            }
        });
        client.batch_execute(&format!("LISTEN {CHANNEL}")).await?;
        Ok(Listener { _client: client, notices, task })
    }

    /// The next notice, in commit order; `None` once the connection is lost.
    pub async fn recv(&mut self) -> Option<Notice> {
        self.notices.recv().await
    }
}

impl Drop for Listener {
    fn drop(&mut self) {
        self.task.abort();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn payloads_are_read_as_the_trigger_writes_them() {
        assert_eq!(Notice::parse("queued:job_1"), Some(Notice::Queued("job_1".into())));
        assert_eq!(Notice::parse("cancel:job_2"), Some(Notice::Cancel("job_2".into())));
        assert_eq!(Notice::parse("job:job_3").map(|n| n.job_id().to_string()), Some("job_3".into()));
        for bad in ["", "queued", "queued:", "deleted:job_1", ":job_1"] {
            assert_eq!(Notice::parse(bad), None, "{bad}");
        }
    }
}
