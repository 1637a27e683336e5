//! A real PostgreSQL for tests: a throwaway cluster per test (`initdb`, then
//! the postmaster on a free 127.0.0.1 port, as our child), or an existing
//! server named by `RADIANCE_TEST_DATABASE_URL`. A test that needs it fails
//! when PostgreSQL is missing, it does not skip.
//!
//! The binaries: `$RADIANCE_PG_BIN`, else `initdb` on `PATH`, else the
//! highest `/usr/lib/postgresql/*/bin` (Debian keeps them off `PATH`). Both
//! refuse to run as root, so as root they run as the `postgres` user (or
//! `$RADIANCE_TEST_PG_USER`). The postmaster gets SIGQUIT (immediate
//! shutdown) when the test's thread ends, even if the test process is
//! killed (`PR_SET_PDEATHSIG`), and from `Drop`, which then removes its
//! folder.

use std::ffi::{CString, OsStr};
use std::fs::File;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How long a new cluster may take to accept connections.
const READY_WITHIN: Duration = Duration::from_secs(30);

/// A PostgreSQL server for one test; [`Pg::database`] makes it a database.
pub struct Pg {
    /// A URL of the server's maintenance database, where databases are made.
    admin_url: String,
    cluster: Option<Cluster>,
    /// Databases made on an existing server: dropped at the end.
    made: Mutex<Vec<String>>,
}

struct Cluster {
    child: Child,
    port: u16,
    /// Removed when dropped, after the postmaster has stopped.
    _dir: tempfile::TempDir,
}

impl Pg {
    /// A fresh cluster, accepting connections (or the server of
    /// `RADIANCE_TEST_DATABASE_URL`). Panics, failing the test, when
    /// PostgreSQL is missing or does not start.
    pub async fn start() -> Pg {
        if let Ok(url) = std::env::var("RADIANCE_TEST_DATABASE_URL") {
            return Pg { admin_url: url, cluster: None, made: Mutex::new(Vec::new()) };
        }
        let bin = bin_dir(
            std::env::var_os("RADIANCE_PG_BIN").as_deref(),
            std::env::var_os("PATH").as_deref(),
            Path::new("/usr/lib/postgresql"),
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let owner = run_as();
        let dir = tempfile::Builder::new().prefix("radiance-pg-").tempdir().unwrap();
        if let Some((uid, gid)) = owner {
            std::os::unix::fs::chown(dir.path(), Some(uid), Some(gid)).unwrap();
        }
        let data = dir.path().join("data");
        let mut initdb = Command::new(bin.join("initdb"));
        initdb.arg("-D").arg(&data);
        initdb.args(["-U", "radiance", "--auth=trust", "--no-sync", "-E", "UTF8", "--locale=C"]);
        let out = as_owner(&mut initdb, owner, libc::SIGKILL)
            .output()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", bin.join("initdb").display()));
        assert!(
            out.status.success(),
            "initdb failed ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        // A port found free can be taken before the postmaster binds it: try a few.
        let mut last_log = String::new();
        for _ in 0..3 {
            let port = free_port();
            let log_path = dir.path().join(format!("postgres-{port}.log"));
            let log = File::create(&log_path).unwrap();
            let mut postgres = Command::new(bin.join("postgres"));
            postgres.arg("-D").arg(&data).arg("-p").arg(port.to_string()).arg("-k").arg(dir.path());
            for setting in [
                "listen_addresses=127.0.0.1",
                "fsync=off",
                "synchronous_commit=off",
                "full_page_writes=off",
                "max_connections=200",
            ] {
                postgres.args(["-c", setting]);
            }
            postgres.stdin(Stdio::null()).stdout(log.try_clone().unwrap()).stderr(log);
            let mut child = as_owner(&mut postgres, owner, libc::SIGQUIT)
                .spawn()
                .unwrap_or_else(|e| panic!("cannot run {}: {e}", bin.join("postgres").display()));
            let admin_url = format!("postgres://radiance@127.0.0.1:{port}/postgres");
            match wait_ready(&admin_url, &mut child).await {
                Ok(()) => {
                    let cluster = Cluster { child, port, _dir: dir };
                    return Pg { admin_url, cluster: Some(cluster), made: Mutex::new(Vec::new()) };
                }
                Err(why) => {
                    stop(&mut child);
                    last_log = tail(&std::fs::read_to_string(&log_path).unwrap_or_default());
                    if !last_log.contains("could not bind") {
                        panic!("PostgreSQL did not start: {why}\n{last_log}");
                    }
                }
            }
        }
        panic!("PostgreSQL found no free port to listen on:\n{last_log}");
    }

    /// A new, empty database `t_<uuid>` on the server; its URL.
    pub async fn database(&self) -> String {
        let name = format!("t_{}", uuid::Uuid::now_v7().simple());
        let (client, connection) = tokio_postgres::connect(&self.admin_url, tokio_postgres::NoTls)
            .await
            .unwrap_or_else(|e| panic!("cannot connect to the test server: {e} ({:?})", std::error::Error::source(&e)));
        let driver = tokio::spawn(connection);
        client.batch_execute(&format!("CREATE DATABASE {name}")).await.unwrap();
        drop(client);
        let _ = driver.await;
        if self.cluster.is_none() {
            self.made.lock().unwrap().push(name.clone());
        }
        with_database(&self.admin_url, &name)
    }

    /// The port of the throwaway cluster (`None` on an existing server).
    pub fn port(&self) -> Option<u16> {
        self.cluster.as_ref().map(|c| c.port)
    }
}

impl Drop for Pg {
    fn drop(&mut self) {
        if let Some(c) = &mut self.cluster {
            stop(&mut c.child);
            return;
        }
        let made = std::mem::take(&mut *self.made.lock().unwrap_or_else(|e| e.into_inner()));
        if made.is_empty() {
            return;
        }
        // Drop may run inside a runtime: a thread of its own, and a bounded wait.
        let url = self.admin_url.clone();
        let (done, wait) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
            rt.block_on(async {
                if let Ok((client, connection)) = tokio_postgres::connect(&url, tokio_postgres::NoTls).await {
                    tokio::spawn(connection);
                    for name in made {
                        let _ = client.batch_execute(&format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")).await;
                    }
                }
            });
            let _ = done.send(());
        });
        let _ = wait.recv_timeout(Duration::from_secs(10));
    }
}

/// Immediate shutdown (SIGQUIT) of a postmaster, SIGKILL if it lingers.
fn stop(child: &mut Child) {
    let pid = child.id() as libc::pid_t;
    // SAFETY: a signal to our own child, which has not been reaped yet.
    unsafe { libc::kill(pid, libc::SIGQUIT) };
    let deadline = Instant::now() + Duration::from_secs(10);
    while Instant::now() < deadline {
        if !matches!(child.try_wait(), Ok(None)) {
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
}

/// Polls until a connection and `SELECT 1` succeed, the postmaster exits,
/// or [`READY_WITHIN`] passes.
async fn wait_ready(url: &str, child: &mut Child) -> Result<(), String> {
    let deadline = Instant::now() + READY_WITHIN;
    let mut last = String::new();
    while Instant::now() < deadline {
        if let Ok(Some(status)) = child.try_wait() {
            return Err(format!("the postmaster exited ({status})"));
        }
        match tokio_postgres::connect(url, tokio_postgres::NoTls).await {
            Ok((client, connection)) => {
                let driver = tokio::spawn(connection);
                let ok = client.simple_query("SELECT 1").await.is_ok();
                drop(client);
                let _ = driver.await;
                if ok {
                    return Ok(());
                }
            }
            Err(e) => last = format!("{e}: {:?}", std::error::Error::source(&e)),
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Err(format!("no connection within {READY_WITHIN:?} (last: {last})"))
}

/// Where `initdb` and `postgres` are (see the module comment), or what to
/// install.
pub fn bin_dir(env: Option<&OsStr>, path: Option<&OsStr>, lib_root: &Path) -> Result<PathBuf, String> {
    let has_both = |d: &Path| d.join("initdb").is_file() && d.join("postgres").is_file();
    if let Some(d) = env {
        let d = PathBuf::from(d);
        return if has_both(&d) {
            Ok(d)
        } else {
            Err(format!("RADIANCE_PG_BIN={} holds no initdb and postgres", d.display()))
        };
    }
    // On PATH it may be a link (/usr/local/bin/initdb): its target's folder
    // holds postgres too.
    let on_path = path.into_iter().flat_map(std::env::split_paths).map(|d| d.join("initdb")).find(|p| p.is_file());
    if let Some(dir) = on_path.and_then(|p| p.canonicalize().ok()).and_then(|p| p.parent().map(Path::to_path_buf))
        && has_both(&dir)
    {
        return Ok(dir);
    }
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir(lib_root)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| Some((e.file_name().to_str()?.parse().ok()?, e.path().join("bin"))))
        .filter(|(_, d): &(u32, PathBuf)| has_both(d))
        .collect();
    versions.sort();
    versions.pop().map(|(_, d)| d).ok_or_else(|| {
        format!(
            "these tests need PostgreSQL (initdb and postgres), found neither on PATH nor in {}/*/bin: install it \
             as scripts/setup does (Debian: echo 'create_main_cluster = false' >> \
             /etc/postgresql-common/createcluster.conf; apt-get install -y --no-install-recommends postgresql), \
             or set RADIANCE_PG_BIN to their folder, or RADIANCE_TEST_DATABASE_URL to a server",
            lib_root.display()
        )
    })
}

/// The uid and gid to run PostgreSQL as: `None` unless we are root, which
/// initdb and postgres refuse.
fn run_as() -> Option<(u32, u32)> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return None;
    }
    let user = std::env::var("RADIANCE_TEST_PG_USER").unwrap_or_else(|_| "postgres".into());
    let name = CString::new(user.clone()).unwrap();
    // SAFETY: a valid C string; the entry is read at once, before another
    // getpw* call could reuse its storage.
    let entry = unsafe { libc::getpwnam(name.as_ptr()) };
    if entry.is_null() {
        panic!(
            "running as root, and PostgreSQL refuses root: no user '{user}' to run it as (the Debian package \
             makes 'postgres'; or set RADIANCE_TEST_PG_USER)"
        );
    }
    // SAFETY: checked non-null above.
    Some(unsafe { ((*entry).pw_uid, (*entry).pw_gid) })
}

/// `cmd` run as `owner` (when set), receiving `signal` when the thread that
/// spawned it ends. The death signal is set after the uid change, which
/// clears it.
fn as_owner(cmd: &mut Command, owner: Option<(u32, u32)>, signal: libc::c_int) -> &mut Command {
    if let Some((uid, gid)) = owner {
        cmd.uid(uid).gid(gid);
    }
    // SAFETY: prctl is async-signal-safe; nothing is allocated.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, signal as libc::c_ulong) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        })
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// The last lines of a log, for a panic message.
fn tail(log: &str) -> String {
    let lines: Vec<&str> = log.lines().collect();
    lines[lines.len().saturating_sub(30)..].join("\n")
}

/// `url` naming database `name` instead of its own.
pub fn with_database(url: &str, name: &str) -> String {
    let (base, query) = url.split_once('?').map_or((url, None), |(b, q)| (b, Some(q)));
    let authority_end = base.find("://").map(|i| i + 3).unwrap_or(0);
    let path_start = base[authority_end..].find('/').map_or(base.len(), |i| authority_end + i);
    let mut out = format!("{}/{name}", &base[..path_start]);
    if let Some(q) = query {
        out.push('?');
        out.push_str(q);
    }
    out
}
