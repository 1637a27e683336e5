//! Distributed mode (docs/design/scale-out.md, section 2.5): the shared
//! stores a node opens when it is given a database and an object store,
//! and the worker it runs unless its role is `api`.
//!
//! A node started before its database or object store is up (a compose
//! file starts them together) retries for [`Distributed::startup_wait`],
//! saying in the log what it waits for, and then gives up with an error
//! naming the store and the last reason. A schema this binary cannot use
//! or a malformed URL is an error at once: waiting would not help.

use std::io;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::Role;
use crate::backend::ArtifactStore;
use crate::backend::object::{ObjectArtifacts, ObjectConfig};
use crate::backend::pg::{Database, PgError, PgJobStore, PgStoreConfig, QueueConfig};
use crate::jobs::SchedulerConfig;
use crate::worker::{Worker, WorkerConfig};

/// How often start-up tries an unreachable store again.
const RETRY_EVERY: Duration = Duration::from_secs(1);

/// The shared stores of a node of a distributed deployment.
#[derive(Clone)]
pub struct Distributed {
    /// `postgres://…` (`--database-url`; may hold a password: never logged).
    pub database_url: String,
    /// `s3://BUCKET/PREFIX` or `file:///PATH` (`--object-store`).
    pub object_store: String,
    /// This node's id in leases and logs (`--node-id`).
    pub node_id: String,
    /// How long a worker's lease on a job lasts without a heartbeat.
    pub lease: Duration,
    /// Bound on the local cache of scenes and checkpoints, bytes.
    pub cache_max_bytes: u64,
    /// Connections in the database pool.
    pub db_pool_size: usize,
    /// How long start-up waits for the database and the object store.
    pub startup_wait: Duration,
}

/// Not derived: the database URL may hold a password, so it shows as the
/// server it names.
impl std::fmt::Debug for Distributed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let database = Database::parse(&self.database_url).map(|d| d.target().to_string());
        f.debug_struct("Distributed")
            .field("database", &database.unwrap_or_else(|_| "(an invalid URL)".into()))
            .field("object_store", &self.object_store)
            .field("node_id", &self.node_id)
            .field("lease", &self.lease)
            .field("cache_max_bytes", &self.cache_max_bytes)
            .field("db_pool_size", &self.db_pool_size)
            .field("startup_wait", &self.startup_wait)
            .finish()
    }
}

/// The stores a distributed node opened, and its worker.
pub(super) struct Opened {
    pub jobs: Arc<PgJobStore>,
    pub artifacts: Arc<ObjectArtifacts>,
    pub worker: Option<Worker>,
}

/// Opens the shared stores (retrying, see the module comment) and starts
/// the worker of a `worker` or `all` node.
pub(super) async fn open(
    d: &Distributed,
    role: Role,
    data_dir: &Path,
    scheduler: &SchedulerConfig,
) -> io::Result<Opened> {
    let db =
        Database::parse(&d.database_url).map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e.to_string()))?;
    let deadline = Instant::now() + d.startup_wait;
    let database = db.target().to_string();
    let store_config =
        PgStoreConfig { pool_size: d.db_pool_size, queue: QueueConfig { max_queued: scheduler.max_queued } };
    let jobs = retry(deadline, &format!("PostgreSQL ({})", db.target()), || async {
        match PgJobStore::open(&db, store_config.clone()).await {
            Ok(s) => Ok(s),
            Err(e @ (PgError::Connect { .. } | PgError::Unavailable(_) | PgError::Db(_))) => Err(Retry::Again(e)),
            Err(e) => Err(Retry::Fatal(e)),
        }
    })
    .await?;
    let object_config = ObjectConfig { cache_max_bytes: d.cache_max_bytes, ..ObjectConfig::default() };
    let artifacts = Arc::new(ObjectArtifacts::open(data_dir, &d.object_store, object_config)?);
    retry(deadline, &format!("the object store {}", d.object_store), || async {
        artifacts.ready().await.map_err(Retry::Again)
    })
    .await?;
    let jobs = Arc::new(jobs);
    let worker = match role {
        Role::Api => None,
        Role::Worker | Role::All => {
            let config = WorkerConfig {
                node: d.node_id.clone(),
                lease: d.lease,
                scheduler: scheduler.clone(),
                scratch: data_dir.join("cache").join("jobs"),
            };
            Some(Worker::start(config, db, jobs.queue().clone(), artifacts.clone())?)
        }
    };
    tracing::info!(role = %role, node = %d.node_id, database = %database,
        object_store = %d.object_store, "distributed mode: the shared stores are open");
    Ok(Opened { jobs, artifacts, worker })
}

/// Whether a failed attempt is worth another.
enum Retry<E> {
    Again(E),
    Fatal(E),
}

/// `attempt` until it succeeds, fails for good, or `deadline` passes; the
/// error names `what` and the last reason.
async fn retry<T, E, F, Fut>(deadline: Instant, what: &str, mut attempt: F) -> io::Result<T>
where
    E: std::fmt::Display,
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, Retry<E>>>,
{
    let started = Instant::now();
    loop {
        match attempt().await {
            Ok(v) => return Ok(v),
            Err(Retry::Fatal(e)) => return Err(io::Error::other(format!("{what}: {e}"))),
            Err(Retry::Again(e)) if Instant::now() + RETRY_EVERY < deadline => {
                tracing::warn!(error = %e, "waiting for {what}");
                tokio::time::sleep(RETRY_EVERY).await;
            }
            Err(Retry::Again(e)) => {
                return Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("{what} is not reachable after {:.0} s: {e}", started.elapsed().as_secs_f64()),
                ));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn debug_never_shows_the_database_password() {
        let d = Distributed {
            database_url: "postgres://radiance:s3cret@db.example:5433/radiance".into(),
            object_store: "file:///srv/store".into(),
            node_id: "w1".into(),
            lease: Duration::from_secs(10),
            cache_max_bytes: 1 << 30,
            db_pool_size: 8,
            startup_wait: Duration::from_secs(60),
        };
        let shown = format!("{d:?}");
        assert!(!shown.contains("s3cret") && shown.contains("db.example:5433"), "{shown}");
    }

    #[tokio::test]
    async fn start_up_retries_until_its_deadline_and_names_the_store() {
        let mut tries = 0;
        let t = Instant::now();
        let e = retry(t + Duration::from_secs(4), "the object store file:///x", || {
            tries += 1;
            async { Err::<(), _>(Retry::Again("no answer")) }
        })
        .await
        .unwrap_err();
        let took = t.elapsed();
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);
        assert!(e.to_string().starts_with("the object store file:///x is not reachable after"), "{e}");
        assert!(e.to_string().ends_with(": no answer"), "{e}");
        // Tried again (a first try within 3 s of the 4 s deadline leaves room
        // for one more), and never more often than once a second.
        assert!(tries >= 2, "{tries} tries in {took:?}");
        assert!(tries <= 1 + took.as_secs() as usize, "{tries} tries in {took:?}");

        let mut tries = 0;
        let e = retry(Instant::now() + Duration::from_secs(60), "PostgreSQL", || {
            tries += 1;
            async { Err::<(), _>(Retry::Fatal("schema too new")) }
        })
        .await
        .unwrap_err();
        assert_eq!((tries, e.to_string()), (1, "PostgreSQL: schema too new".to_string()), "no retry when hopeless");

        let mut tries = 0;
        let v = retry(Instant::now() + Duration::from_secs(60), "x", || {
            tries += 1;
            let n = tries;
            async move { if n < 2 { Err(Retry::Again("not yet")) } else { Ok(n) } }
        })
        .await
        .unwrap();
        assert_eq!(v, 2);
    }
}
