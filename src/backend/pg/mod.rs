//! The PostgreSQL job queue (docs/design/scale-out.md, section 2.3): many
//! API nodes enqueue, many workers claim, and the database decides who runs
//! what.
//!
//! - `connect`: a pool from a `postgres://` URL, with errors that name the
//!   server (never the password);
//! - `migrate`: the schema (`migrations/NNNN_name.sql`), applied once under
//!   an advisory lock, each migration checked by its sha256;
//! - `rows`: a `jobs` row as the [`Job`](crate::jobs::Job) clients see;
//! - `queue`: the API's side: enqueue (in `seq` order), cancel, read;
//! - `lease`: the workers' side: claim (`FOR UPDATE SKIP LOCKED`, a lease
//!   with a fencing token), heartbeat, finish, reclaim of expired leases
//!   with crash counting, the fenced model publish;
//! - `publish`: the checkpoint a job resumes from, the fenced video publish;
//! - `notify`: LISTEN for the `radiance` channel the `jobs` trigger
//!   announces changes on;
//! - `changes`: one listener per node whose notices every follower of a
//!   job shares, connecting again when its connection ends;
//! - `records`: the records of scenes, models and videos (read, list,
//!   delete unless in use);
//! - `jobs`: [`PgJobStore`], the [`JobStore`](crate::backend::JobStore) over
//!   all of these (records only: files are the artifact store's).
//!
//! Every write a worker makes for a job is fenced by its lease's token: once
//! the lease is lost (expired and reclaimed), the old owner can change
//! nothing. Lease times come from the database clock.

mod changes;
mod connect;
mod error;
mod jobs;
mod lease;
pub mod migrate;
mod notify;
mod publish;
mod queue;
mod records;
mod rows;

pub use connect::Database;
pub use error::PgError;
pub use jobs::{CHANGE_FALLBACK, PgJobStore, PgStoreConfig, READY_WITHIN};
pub use lease::{Admission, Claimed, Heartbeat, Lease, Reclaimed, RunEnd, RunState};
pub use notify::{CHANNEL, Listener, Notice};
pub use queue::{PgQueue, QueueConfig};
