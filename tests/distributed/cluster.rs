//! A distributed deployment for a test: a throwaway PostgreSQL
//! (`common::pg`), an object store shared by the nodes ([`Backend`]: a
//! `file://` folder in a tempdir, or a real S3 server of the test's own
//! from `common::s3`, whose `AWS_*` settings every node gets; or the store
//! `RADIANCE_TEST_OBJECT_STORE` names in place of the `file://` folder),
//! and `radiance serve` nodes as child processes of the built binary.
//!
//! Each node has its own data directory (scratch and cache) and writes its
//! log to `node.log` there; a test that fails prints the logs' tails.
//! Nodes are killed (SIGKILL) when dropped. Tests take [`serial`] first:
//! several clusters at once would starve the heartbeats on two cores.

use std::io::BufRead;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::pg::Pg;
use crate::common::s3::S3;

/// The lease the tests' workers take: a dead worker's job moves on after
/// about this long. Not shorter: a worker fences itself after 0.8 of it
/// without a heartbeat (one a second, `worker::heartbeat_every`), so with
/// several processes on two cores a starved but healthy worker must keep
/// its job for 8 s, or the tests' exact counts of runs would break.
pub const LEASE_SECONDS: u64 = 10;

/// How long a node may take to print its address.
const START_WITHIN: Duration = Duration::from_secs(60);

static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// Held for the whole of a test: one cluster at a time (an async mutex: it
/// is held across awaits, and a failed test does not poison it).
pub async fn serial() -> tokio::sync::MutexGuard<'static, ()> {
    SERIAL.lock().await
}

/// Where a cluster keeps its objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// A `file://` folder in a tempdir (or `RADIANCE_TEST_OBJECT_STORE`).
    File,
    /// A real S3 server started for the test (`common::s3`; it fails, not
    /// skips, without `s3s-fs`).
    S3,
}

/// The shared stores.
pub struct Cluster {
    /// `None` once [`Cluster::stop_database`] stopped it.
    pg: Option<Pg>,
    pub database_url: String,
    pub object_store: String,
    /// The `file://` store's folder, when the tests made one.
    _store_dir: Option<tempfile::TempDir>,
    /// The S3 server of a [`Backend::S3`] cluster.
    pub s3: Option<S3>,
    /// What every node's environment gets on top of the test's (the S3
    /// server's `AWS_*` settings).
    env: Vec<(&'static str, String)>,
}

/// A `radiance serve` process.
pub struct Node {
    pub name: String,
    pub child: Child,
    /// `http://127.0.0.1:PORT`.
    pub base: String,
    pub dir: tempfile::TempDir,
}

impl Cluster {
    /// A cluster over a `file://` store (or `RADIANCE_TEST_OBJECT_STORE`).
    pub async fn start() -> Cluster {
        Cluster::start_on(Backend::File).await
    }

    /// A cluster whose objects are kept by `backend`.
    pub async fn start_on(backend: Backend) -> Cluster {
        let pg = Pg::start().await;
        let database_url = pg.database().await;
        let (object_store, store_dir, s3) = match (backend, std::env::var("RADIANCE_TEST_OBJECT_STORE")) {
            (Backend::S3, _) => {
                let s3 = S3::start().await;
                (s3.url(), None, Some(s3))
            }
            (Backend::File, Ok(url)) => (url, None, None),
            (Backend::File, Err(_)) => {
                let dir = tempfile::Builder::new().prefix("radiance-store-").tempdir().unwrap();
                (format!("file://{}", dir.path().display()), Some(dir), None)
            }
        };
        let env = s3.as_ref().map(S3::env).unwrap_or_default();
        Cluster { pg: Some(pg), database_url, object_store, _store_dir: store_dir, s3, env }
    }

    /// Starts a node with `role` (`api`, `worker`, `all`) named `name`,
    /// with `extra` arguments; returns once it listens.
    pub fn node(&self, role: &str, name: &str, extra: &[&str]) -> Node {
        self.node_with_lease(role, name, LEASE_SECONDS, extra)
    }

    /// [`Cluster::node`] with a lease of `lease_seconds` instead of
    /// [`LEASE_SECONDS`] (the measurements compare leases).
    pub fn node_with_lease(&self, role: &str, name: &str, lease_seconds: u64, extra: &[&str]) -> Node {
        let dir = tempfile::Builder::new().prefix(&format!("radiance-{name}-")).tempdir().unwrap();
        self.start_node(role, name, lease_seconds, extra, dir)
    }

    /// [`Cluster::node`] on an existing data directory (e.g. a killed
    /// node's, from [`Node::into_dir`]); its log is appended to.
    pub fn node_in(&self, role: &str, name: &str, extra: &[&str], dir: tempfile::TempDir) -> Node {
        self.start_node(role, name, LEASE_SECONDS, extra, dir)
    }

    /// Starts a node in `dir` with a lease of `lease_seconds`.
    fn start_node(&self, role: &str, name: &str, lease_seconds: u64, extra: &[&str], dir: tempfile::TempDir) -> Node {
        let log = std::fs::OpenOptions::new().create(true).append(true).open(dir.path().join("node.log")).unwrap();
        let lease = lease_seconds.to_string();
        let mut child = Command::new(env!("CARGO_BIN_EXE_radiance"))
            .args(["serve", "--addr", "127.0.0.1:0", "--threads", "1", "--role", role, "--node-id", name])
            .args(["--lease-seconds", &lease, "--checkpoint-every", "0.2", "--startup-wait-seconds", "20"])
            .arg("--database-url")
            .arg(&self.database_url)
            .arg("--object-store")
            .arg(&self.object_store)
            .arg("--data-dir")
            .arg(dir.path())
            .args(extra)
            .env_remove("RADIANCE_API_KEY")
            .envs(self.env.iter().map(|(k, v)| (*k, v.as_str())))
            .env("RUST_LOG", "info,tower_http=warn")
            .env("NO_COLOR", "1")
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .unwrap();
        // The first line is the address; a node that fails to start closes
        // its output (bounded by --startup-wait-seconds).
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = std::io::BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let line = rx.recv_timeout(START_WITHIN).unwrap_or_default();
        let Some(addr) = line.trim().strip_prefix("listening on ") else {
            let _ = child.kill();
            let _ = child.wait();
            panic!("node {name} did not start ({line:?}):\n{}", tail(&dir.path().join("node.log")));
        };
        Node { name: name.to_string(), child, base: addr.to_string(), dir }
    }

    /// Stops the PostgreSQL server (immediate shutdown), as an outage.
    pub fn stop_database(&mut self) {
        drop(self.pg.take());
    }

    /// A connection to the cluster's database (for the tests' own checks).
    pub async fn sql(&self) -> tokio_postgres::Client {
        let (client, connection) = tokio_postgres::connect(&self.database_url, tokio_postgres::NoTls).await.unwrap();
        tokio::spawn(connection);
        client
    }
}

impl Node {
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("node.log")).unwrap_or_default()
    }

    /// The value of the unlabelled series `name` in the node's `/metrics`.
    pub async fn metric(&self, name: &str) -> f64 {
        let text = crate::common::http_client().get(format!("{}/metrics", self.base)).send().await.unwrap();
        let text = text.text().await.unwrap();
        let prefix = format!("{name} ");
        let line = text.lines().find_map(|l| l.strip_prefix(prefix.as_str()));
        line.unwrap_or_else(|| panic!("no {name} in the metrics of {}:\n{text}", self.name)).parse().unwrap()
    }

    /// SIGKILL: no chance to checkpoint, record or release anything.
    pub fn kill9(&mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    /// Kills the node (SIGKILL) and hands back its data directory, for a
    /// node started on it again ([`Cluster::node_in`]).
    pub fn into_dir(mut self) -> tempfile::TempDir {
        self.kill9();
        let placeholder = tempfile::Builder::new().prefix("radiance-gone-").tempdir().unwrap();
        std::mem::replace(&mut self.dir, placeholder)
    }

    /// SIGTERM, then waits up to `within` for the process to exit; its
    /// exit status.
    pub fn terminate(&mut self, within: Duration) -> std::process::ExitStatus {
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let t0 = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(t0.elapsed() < within, "node {} did not exit within {within:?} of SIGTERM", self.name);
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if std::thread::panicking() {
            eprintln!("--- log of node {} ---\n{}", self.name, tail(&self.dir.path().join("node.log")));
        }
    }
}

/// The last lines of a log.
fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(60)..].join("\n")
}
