//! What can go wrong talking to PostgreSQL, in words a log or a client can
//! use: the server is named by host and port, never with its password.

use crate::jobs::SchedError;

/// An error of the PostgreSQL store.
#[derive(Debug, thiserror::Error)]
pub enum PgError {
    /// The database URL cannot be used (the reason never quotes the password).
    #[error("invalid database URL: {0}")]
    BadUrl(String),
    /// No connection could be made to the server.
    #[error("cannot connect to PostgreSQL at {target}: {reason}")]
    Connect { target: String, reason: String },
    /// No pooled connection could be had (the server went away, or every
    /// connection stayed busy past the pool's wait).
    #[error("the database is unavailable: {0}")]
    Unavailable(String),
    /// The schema cannot be brought to this binary's version.
    #[error("{0}")]
    Migration(String),
    /// A statement failed.
    #[error("database error: {}", chain(.0))]
    Db(#[from] tokio_postgres::Error),
    /// A row that does not read back as the record it should hold (a
    /// job's, a scene's, a model's or a video's: the id's prefix says which).
    #[error("the record '{id}' in the database cannot be read: {reason}")]
    BadRecord { id: String, reason: String },
    /// An argument the store cannot take (e.g. a lease of no time).
    #[error("{0}")]
    Invalid(String),
    /// The worker's lease on the job is gone (it expired and was reclaimed,
    /// or the job was deleted): it must stop and write nothing more.
    #[error("the lease on job '{0}' was lost: another worker may run it now")]
    LeaseLost(String),
    /// Refused as the embedded queue refuses it (not found, not ready, queue
    /// full, already final...).
    #[error(transparent)]
    Refused(#[from] SchedError),
}

impl From<deadpool_postgres::PoolError> for PgError {
    fn from(e: deadpool_postgres::PoolError) -> Self {
        match e {
            deadpool_postgres::PoolError::Backend(e) => PgError::Unavailable(chain(&e)),
            e => PgError::Unavailable(e.to_string()),
        }
    }
}

/// An error and its causes, outermost first: tokio-postgres says only
/// "db error" or "error connecting to server" and puts the reason in its
/// source.
pub(super) fn chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !s.ends_with(&text) {
            s.push_str(": ");
            s.push_str(&text);
        }
        cause = c.source();
    }
    s
}
