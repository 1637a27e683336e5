//! A real S3 server for tests: `s3s-fs` (an S3 server over a folder,
//! Apache-2.0: HTTP, sigv4 with a fixed key pair, multipart uploads,
//! ListObjectsV2), one per test on a free 127.0.0.1 port, in a temporary
//! folder, with one bucket; or an existing server named by the
//! `RADIANCE_TEST_S3_*` variables. Each test keeps its objects under a
//! prefix of its own, so both behave alike. A test that needs it fails when
//! `s3s-fs` is missing, it does not skip; `scripts/setup` installs it.
//!
//! The server gets SIGKILL when the test's thread ends, even if the test
//! process is killed (`PR_SET_PDEATHSIG`), and from `Drop`, which then
//! removes its folder.
//!
//! An existing server: `RADIANCE_TEST_S3_ENDPOINT` (`http://host:port`),
//! `RADIANCE_TEST_S3_ACCESS_KEY_ID`, `RADIANCE_TEST_S3_SECRET_ACCESS_KEY`,
//! and optionally `RADIANCE_TEST_S3_BUCKET` (default `radiance-test`, which
//! must exist) and `RADIANCE_TEST_S3_REGION` (default `us-east-1`).

use std::ffi::OsStr;
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use object_store::{ObjectStore, ObjectStoreExt};
use radiance::backend::object::{S3Keys, S3Options, open_url};

/// The s3s-fs release `scripts/setup` installs.
pub const S3S_FS_VERSION: &str = "0.14.1";
/// How to install it.
pub const INSTALL: &str = "cargo install --locked s3s-fs@0.14.1 --features binary";
/// How long a new server may take to answer a listing.
const READY_WITHIN: Duration = Duration::from_secs(30);
/// The bucket of a server of our own.
const BUCKET: &str = "radiance-test";
/// The region requests are signed for (s3s-fs takes any; not AWS's
/// default, so a region that does not reach the signature would show).
const REGION: &str = "radiance-local";

/// An S3 bucket for one test: where it is, how to sign, and a key prefix
/// of the test's own.
pub struct S3 {
    endpoint: String,
    bucket: String,
    region: String,
    keys: S3Keys,
    prefix: String,
    server: Option<Server>,
}

/// A server of our own.
struct Server {
    child: Child,
    /// The folder it serves (the bucket is `root/radiance-test`); removed
    /// when dropped, after the server has stopped.
    root: tempfile::TempDir,
}

impl S3 {
    /// A fresh server answering listings of its bucket (or the existing
    /// server of `RADIANCE_TEST_S3_ENDPOINT`). Panics, failing the test,
    /// when `s3s-fs` is missing or does not start.
    pub async fn start() -> S3 {
        let prefix = format!("t-{}", uuid::Uuid::now_v7().simple());
        let mut s3 = match std::env::var("RADIANCE_TEST_S3_ENDPOINT") {
            Ok(endpoint) => existing(endpoint, prefix),
            Err(_) => spawn(prefix),
        };
        s3.wait_ready().await;
        s3
    }

    /// `s3://BUCKET/PREFIX`: the test's part of the bucket.
    pub fn url(&self) -> String {
        format!("s3://{}/{}", self.bucket, self.prefix)
    }

    /// The settings `ObjectArtifacts::open` needs for [`S3::url`] (given
    /// explicitly: tests cannot change their process's environment).
    pub fn options(&self) -> S3Options {
        S3Options {
            endpoint: Some(self.endpoint.clone()),
            region: Some(self.region.clone()),
            allow_http: Some(true),
            keys: Some(self.keys.clone()),
        }
    }

    /// The same settings as the environment of a radiance process.
    pub fn env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint.clone()),
            ("AWS_ALLOW_HTTP", "true".into()),
            ("AWS_REGION", self.region.clone()),
            ("AWS_ACCESS_KEY_ID", self.keys.access_key_id.clone()),
            ("AWS_SECRET_ACCESS_KEY", self.keys.secret_access_key.clone()),
        ]
    }

    /// The server's URL, `http://127.0.0.1:PORT`.
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// The folder a server of our own serves (`None` on an existing one).
    pub fn root(&self) -> Option<&Path> {
        self.server.as_ref().map(|s| s.root.path())
    }

    /// The parts of incomplete multipart uploads a server of our own holds
    /// (s3s-fs writes each part whole, then renames it to
    /// `.upload_id-<id>.part-<n>` in its data folder): their file names,
    /// sorted. Empty on an existing server, which this cannot see.
    pub fn multipart_parts(&self) -> Vec<String> {
        let Some(root) = self.root() else { return Vec::new() };
        let mut parts: Vec<String> = std::fs::read_dir(root.join("data"))
            .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
            .unwrap_or_default();
        parts.retain(|n| n.starts_with(".upload_id-") && n.contains(".part-"));
        parts.sort();
        parts
    }

    /// The files under the test's prefix as a server of our own keeps them
    /// (readable while the server is paused), relative to the prefix.
    pub fn files_on_disk(&self) -> Vec<String> {
        fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
            for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(root, &p, out);
                } else {
                    out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
                }
            }
        }
        let Some(root) = self.root() else { return Vec::new() };
        let prefix = root.join("data").join(&self.bucket).join(&self.prefix);
        let mut files = Vec::new();
        walk(&prefix, &prefix, &mut files);
        files.sort();
        files
    }

    /// SIGSTOP to a server of our own: requests in flight and new ones
    /// wait until [`S3::resume`]. Panics on an existing server.
    pub fn pause(&self) {
        self.signal(libc::SIGSTOP);
    }

    /// SIGCONT after [`S3::pause`].
    pub fn resume(&self) {
        self.signal(libc::SIGCONT);
    }

    fn signal(&self, signal: libc::c_int) {
        let server = self.server.as_ref().expect("only a server of our own can be paused");
        // SAFETY: a plain kill(2) of our own child, which has not been waited for.
        let rc = unsafe { libc::kill(server.child.id() as libc::pid_t, signal) };
        assert_eq!(rc, 0, "kill({signal}) of s3s-fs: {}", std::io::Error::last_os_error());
    }

    /// The object store of the test's prefix.
    pub fn store(&self) -> Arc<dyn ObjectStore> {
        open_url(&self.url(), &self.options()).unwrap_or_else(|e| panic!("cannot open {}: {e}", self.url()))
    }

    /// Polls until a listing of the test's prefix succeeds, the server
    /// exits, or [`READY_WITHIN`] passes.
    async fn wait_ready(&mut self) {
        let store = self.store();
        let deadline = Instant::now() + READY_WITHIN;
        let mut last = String::new();
        while Instant::now() < deadline {
            if let Some(server) = &mut self.server
                && let Ok(Some(status)) = server.child.try_wait()
            {
                panic!("s3s-fs exited ({status}) before it answered:\n{}", self.log_tail());
            }
            let remaining = deadline.saturating_duration_since(Instant::now());
            let mut listing = store.list(None);
            match tokio::time::timeout(remaining.min(Duration::from_secs(5)), listing.next()).await {
                Ok(None | Some(Ok(_))) => return,
                Ok(Some(Err(e))) => last = e.to_string(),
                Err(_) => last = "no answer within 5 s".into(),
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!(
            "the S3 server at {} answered no listing within {READY_WITHIN:?} (last: {last})\n{}",
            self.endpoint,
            self.log_tail()
        );
    }

    /// The end of a server of our own's log, for a panic message.
    pub fn log_tail(&self) -> String {
        let Some(server) = &self.server else { return String::new() };
        let log = std::fs::read_to_string(server.log_path()).unwrap_or_default();
        let lines: Vec<&str> = log.lines().collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }
}

impl Server {
    fn log_path(&self) -> PathBuf {
        self.root.path().join("s3s-fs.log")
    }
}

impl Drop for S3 {
    /// Kills a server of our own (its folder goes with it); on an existing
    /// server, deletes the test's objects (best effort, within 10 s).
    fn drop(&mut self) {
        if let Some(server) = &mut self.server {
            let _ = server.child.kill();
            let _ = server.child.wait();
            return;
        }
        // Drop may run inside a runtime: a thread of its own.
        let store = self.store();
        let (done, wait) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
            rt.block_on(async {
                let keys: Vec<_> =
                    store.list(None).filter_map(|m| async { m.ok().map(|m| m.location) }).collect().await;
                for key in keys {
                    let _ = store.delete(&key).await;
                }
            });
            let _ = done.send(());
        });
        let _ = wait.recv_timeout(Duration::from_secs(10));
    }
}

/// The server of the `RADIANCE_TEST_S3_*` variables.
fn existing(endpoint: String, prefix: String) -> S3 {
    let var = |name: &str| {
        std::env::var(name).unwrap_or_else(|_| panic!("RADIANCE_TEST_S3_ENDPOINT is set, but {name} is not"))
    };
    S3 {
        endpoint,
        bucket: std::env::var("RADIANCE_TEST_S3_BUCKET").unwrap_or_else(|_| BUCKET.into()),
        region: std::env::var("RADIANCE_TEST_S3_REGION").unwrap_or_else(|_| "us-east-1".into()),
        keys: S3Keys {
            access_key_id: var("RADIANCE_TEST_S3_ACCESS_KEY_ID"),
            secret_access_key: var("RADIANCE_TEST_S3_SECRET_ACCESS_KEY"),
        },
        prefix,
        server: None,
    }
}

/// `s3s-fs` on a port of its choosing, serving a new temporary folder
/// with the bucket in it; its address comes from its log.
fn spawn(prefix: String) -> S3 {
    let bin = s3s_fs().unwrap_or_else(|e| panic!("{e}"));
    let root = tempfile::Builder::new().prefix("radiance-s3-").tempdir().unwrap();
    let data = root.path().join("data");
    std::fs::create_dir_all(data.join(BUCKET)).unwrap();
    let keys = S3Keys {
        access_key_id: "radiance-test-key".into(),
        secret_access_key: format!("secret-{}", uuid::Uuid::now_v7().simple()),
    };
    let log_path = root.path().join("s3s-fs.log");
    let log = File::create(&log_path).unwrap();
    let mut cmd = Command::new(&bin);
    cmd.args(["--host", "127.0.0.1", "--port", "0", "--access-key", &keys.access_key_id])
        .args(["--secret-key", &keys.secret_access_key])
        .arg(&data)
        .env("RUST_LOG", "s3s_fs=info")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(log.try_clone().unwrap())
        .stderr(log);
    // SAFETY: prctl is async-signal-safe; nothing is allocated.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL as libc::c_ulong) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let child = cmd.spawn().unwrap_or_else(|e| panic!("cannot run {}: {e}", bin.display()));
    let mut server = Server { child, root };
    let port = match listening_port(&mut server) {
        Ok(port) => port,
        Err(why) => {
            let log = std::fs::read_to_string(&log_path).unwrap_or_default();
            panic!("s3s-fs did not start: {why}\n{log}");
        }
    };
    S3 {
        endpoint: format!("http://127.0.0.1:{port}"),
        bucket: BUCKET.into(),
        region: REGION.into(),
        keys,
        prefix,
        server: Some(server),
    }
}

/// The port in the server's "server is running at http://ADDR" line,
/// waited for up to [`READY_WITHIN`].
fn listening_port(server: &mut Server) -> Result<u16, String> {
    let deadline = Instant::now() + READY_WITHIN;
    while Instant::now() < deadline {
        if let Ok(Some(status)) = server.child.try_wait() {
            return Err(format!("it exited ({status})"));
        }
        let log = std::fs::read_to_string(server.log_path()).unwrap_or_default();
        if let Some(port) = port_in_log(&log) {
            return Ok(port);
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Err(format!("it logged no address within {READY_WITHIN:?}"))
}

/// The port of `server is running at http://127.0.0.1:PORT` in a log.
pub fn port_in_log(log: &str) -> Option<u16> {
    let (_, rest) = log.split_once("server is running at http://127.0.0.1:")?;
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// `s3s-fs`: `$RADIANCE_S3S_FS`, else on `PATH`, else in cargo's bin
/// folder (`$CARGO_HOME/bin`, `~/.cargo/bin`: where `cargo install` puts
/// it, not always on `PATH`); or what to install.
pub fn s3s_fs() -> Result<PathBuf, String> {
    let cargo_home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cargo")));
    find_s3s_fs(
        std::env::var_os("RADIANCE_S3S_FS").as_deref(),
        std::env::var_os("PATH").as_deref(),
        cargo_home.as_deref(),
    )
}

/// [`s3s_fs`] with its environment given.
pub fn find_s3s_fs(env: Option<&OsStr>, path: Option<&OsStr>, cargo_home: Option<&Path>) -> Result<PathBuf, String> {
    if let Some(bin) = env {
        let bin = PathBuf::from(bin);
        return if bin.is_file() { Ok(bin) } else { Err(format!("RADIANCE_S3S_FS={} is no file", bin.display())) };
    }
    let cargo_bin = cargo_home.map(|home| home.join("bin"));
    let on_path = path.map(|p| std::env::split_paths(p).collect::<Vec<_>>()).unwrap_or_default();
    on_path.into_iter().chain(cargo_bin).map(|d| d.join("s3s-fs")).find(|p| p.is_file()).ok_or_else(|| {
        format!(
            "these tests need a real S3 server: s3s-fs {S3S_FS_VERSION}, found neither on PATH nor in cargo's bin \
             folder. Install it as scripts/setup does ({INSTALL}), or set RADIANCE_S3S_FS to the binary, or \
             RADIANCE_TEST_S3_ENDPOINT (and _ACCESS_KEY_ID, _SECRET_ACCESS_KEY, _BUCKET) to a server"
        )
    })
}
