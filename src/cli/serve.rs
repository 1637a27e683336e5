//! `radiance serve`: the REST service.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use super::Common;
use crate::api::{Distributed, Role, Server, ServiceConfig};
use crate::jobs::poses::PosesSetup;
use crate::jobs::{SchedulerConfig, default_memory_budget};
use crate::poses::Tools;

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// Address to listen on (port 0 picks a free port; the address is printed).
    #[arg(long, env = "RADIANCE_ADDR", default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Where scenes, models and the job store live.
    #[arg(long, env = "RADIANCE_DATA_DIR", default_value = "./radiance-data")]
    pub data_dir: PathBuf,
    /// Training jobs running at once; the others wait in order.
    #[arg(long, env = "RADIANCE_MAX_CONCURRENT_JOBS", default_value_t = 1)]
    pub max_concurrent_jobs: usize,
    /// Queued jobs beyond this are refused with 503.
    #[arg(long, env = "RADIANCE_MAX_QUEUED_JOBS", default_value_t = 100)]
    pub max_queued_jobs: usize,
    /// Seconds of training between checkpoints of a job.
    #[arg(long, env = "RADIANCE_CHECKPOINT_EVERY", default_value_t = 30.0)]
    pub checkpoint_every: f64,
    /// Largest upload, in MiB.
    #[arg(long, env = "RADIANCE_MAX_UPLOAD_MB", default_value_t = 512)]
    pub max_upload_mb: u64,
    /// Largest size an uploaded archive may unpack to, in MiB.
    #[arg(long, env = "RADIANCE_MAX_UNPACKED_MB", default_value_t = 2048)]
    pub max_unpacked_mb: u64,
    /// Largest render, in pixels (width * height).
    #[arg(long, env = "RADIANCE_MAX_RENDER_PIXELS", default_value_t = 1 << 20)]
    pub max_render_pixels: u64,
    /// Hours a model keeps its optimiser state after its training ended
    /// (only resuming training needs it: two thirds of the checkpoint);
    /// then the checkpoint is rewritten without it. 0: at once.
    #[arg(long, env = "RADIANCE_KEEP_TRAINING_STATE_HOURS", default_value_t = 24.0)]
    pub keep_training_state_hours: f64,
    /// Estimated peak memory of all running jobs together, in MiB (default:
    /// 80 % of the machine's memory); a job waits while starting it would
    /// pass this.
    #[arg(long, env = "RADIANCE_MEMORY_BUDGET_MB")]
    pub memory_budget_mb: Option<u64>,
    /// Estimated peak memory one job may have, in MiB (default: the memory
    /// budget); larger jobs are refused with 422.
    #[arg(long, env = "RADIANCE_MAX_JOB_MEMORY_MB")]
    pub max_job_memory_mb: Option<u64>,
    /// Free disk space, in MiB, that a new job's output must leave on the
    /// data directory's file system; jobs that would not are refused with 507.
    #[arg(long, env = "RADIANCE_MIN_FREE_DISK_MB", default_value_t = 1024)]
    pub min_free_disk_mb: u64,
    /// Require `Authorization: Bearer KEY` on every route but /healthz and /readyz.
    #[arg(long, env = "RADIANCE_API_KEY", hide_env_values = true)]
    pub api_key: Option<String>,
    /// The COLMAP binary for photo-only uploads (default: `colmap` on PATH);
    /// without it such uploads are refused and everything else works.
    #[arg(long, env = "RADIANCE_COLMAP")]
    pub colmap: Option<PathBuf>,
    /// Longest side of photos posed for photo-only uploads, in pixels.
    #[arg(long, env = "RADIANCE_POSES_MAX_SIZE", default_value_t = crate::poses::DEFAULT_MAX_SIZE)]
    pub poses_max_size: u32,
    /// Time limit of one pose estimation, in minutes.
    #[arg(long, env = "RADIANCE_POSES_TIME_LIMIT_MIN", default_value_t = 30.0)]
    pub poses_time_limit_min: f64,
    /// Let pages from this origin (`https://example.com`) call the API from
    /// a browser (CORS; repeatable, or comma-separated in the variable).
    /// Off by default: only the service's own page at `/` can.
    #[arg(long = "cors-origin", env = "RADIANCE_CORS_ORIGINS", value_delimiter = ',')]
    pub cors_origins: Vec<String>,
    /// What this node does: `all` serves the API and runs the jobs (over
    /// the data directory, or over the shared stores); `api` serves the API
    /// alone and `worker` runs the jobs alone, both over the shared stores.
    #[arg(long, env = "RADIANCE_ROLE", default_value = "all", value_parser = role_parser())]
    pub role: Role,
    /// The PostgreSQL database (`postgres://USER:PASSWORD@HOST/DB`) shared
    /// by the nodes of a distributed deployment (with --object-store).
    #[arg(long, env = "RADIANCE_DATABASE_URL", hide_env_values = true)]
    pub database_url: Option<String>,
    /// The object store (`s3://BUCKET/PREFIX` or `file:///PATH`) shared by
    /// the nodes of a distributed deployment (with --database-url).
    #[arg(long, env = "RADIANCE_OBJECT_STORE")]
    pub object_store: Option<String>,
    /// This node's id in job leases and logs (distributed mode; default:
    /// the host name and 8 random hex digits).
    #[arg(long, env = "RADIANCE_NODE_ID")]
    pub node_id: Option<String>,
    /// Seconds a worker's lease on a job lasts without a heartbeat
    /// (distributed mode): a worker that dies loses its job to another
    /// after about this long.
    #[arg(long, env = "RADIANCE_LEASE_SECONDS", default_value_t = 10.0)]
    pub lease_seconds: f64,
    /// Largest size of the local cache of scenes and checkpoints fetched
    /// from the object store, in MiB (distributed mode).
    #[arg(long, env = "RADIANCE_CACHE_MAX_MB", default_value_t = 4096)]
    pub cache_max_mb: u64,
    /// Connections to the database each node keeps (distributed mode).
    #[arg(long, env = "RADIANCE_DB_POOL_SIZE", default_value_t = 8)]
    pub db_pool_size: usize,
    /// Seconds start-up waits for the database and the object store to
    /// answer (distributed mode).
    #[arg(long, env = "RADIANCE_STARTUP_WAIT_SECONDS", default_value_t = 60.0)]
    pub startup_wait_seconds: f64,
    #[command(flatten)]
    pub common: Common,
}

/// The log on stderr: `RUST_LOG`'s filter (info by default), colour codes
/// only for a terminal (a log file or a pipe gets plain text).
fn init_logging() {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info,tower_http=warn".into()),
        )
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

/// Refuses a `--cors-origin` that is not an `http(s)://` origin.
fn check_cors_origins(origins: &[String]) -> anyhow::Result<()> {
    for o in origins {
        anyhow::ensure!(
            o.starts_with("http://") || o.starts_with("https://"),
            "--cors-origin {o}: expected an origin such as https://example.com"
        );
        anyhow::ensure!(axum::http::HeaderValue::from_str(o).is_ok(), "--cors-origin {o}: not a valid header value");
    }
    Ok(())
}

pub fn run(a: ServeArgs) -> anyhow::Result<()> {
    init_logging();
    let shared = deployment(a.role, a.database_url.as_deref(), a.object_store.as_deref())?;
    let distributed = shared.map(|(db, store)| distributed_settings(&a, db, store)).transpose()?;
    let api_key = api_key(a.api_key)?;
    let threads = a.common.init_threads()?;
    anyhow::ensure!(a.checkpoint_every.is_finite() && a.checkpoint_every > 0.0, "--checkpoint-every must be positive");
    anyhow::ensure!(a.max_concurrent_jobs > 0, "--max-concurrent-jobs must be at least 1");
    let keep_training_state = std::time::Duration::try_from_secs_f64(a.keep_training_state_hours * 3600.0)
        .map_err(|_| anyhow::anyhow!("--keep-training-state-hours must be a number of hours, 0 or more"))?;
    let mut config = ServiceConfig::new(&a.data_dir);
    config.max_upload_bytes = a.max_upload_mb << 20;
    config.max_unpacked_bytes = a.max_unpacked_mb << 20;
    config.max_render_pixels = a.max_render_pixels;
    config.api_key = api_key;
    check_cors_origins(&a.cors_origins)?;
    config.cors_origins = a.cors_origins;
    config.role = a.role;
    let budget = a.memory_budget_mb.map_or_else(default_memory_budget, |m| m << 20);
    let per_job = a.max_job_memory_mb.map_or(budget, |m| m << 20);
    anyhow::ensure!(budget > 0 && per_job > 0, "--memory-budget-mb and --max-job-memory-mb must be positive");
    anyhow::ensure!(
        per_job <= budget,
        "--max-job-memory-mb ({} MiB) is larger than --memory-budget-mb ({} MiB): such a job could never start",
        per_job >> 20,
        budget >> 20
    );
    config.min_free_disk_bytes = a.min_free_disk_mb << 20;
    anyhow::ensure!(a.poses_max_size >= 64, "--poses-max-size must be at least 64 pixels");
    let poses_time_limit = std::time::Duration::try_from_secs_f64(a.poses_time_limit_min * 60.0)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| anyhow::anyhow!("--poses-time-limit-min must be a positive number of minutes"))?;
    if distributed.is_some() {
        tracing::warn!("photo-only uploads are disabled in distributed mode: workers do not estimate poses yet");
    }
    let tools = if distributed.is_some() { None } else { pose_tools(a.colmap.as_deref()) };
    let poses = tools.map(|tools| PosesSetup { tools, max_size: a.poses_max_size, time_limit: poses_time_limit });
    config.distributed = distributed;
    config.scheduler = SchedulerConfig {
        max_concurrent: a.max_concurrent_jobs,
        max_queued: a.max_queued_jobs,
        checkpoint_every: a.checkpoint_every,
        keep_training_state,
        max_job_memory_bytes: per_job,
        memory_budget_bytes: budget,
        poses,
        ..SchedulerConfig::default()
    };
    let config_node = config.distributed.as_ref().map(|d| d.node_id.clone());
    // The runtime only moves bytes: the work runs on the rayon pool.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    rt.block_on(async move {
        let server = Server::start(config, a.addr)
            .await
            .with_context(|| format!("starting the service on {} with data in {}", a.addr, a.data_dir.display()))?;
        println!("listening on http://{}", server.addr);
        eprintln!("open http://{}/ in a browser for the web app", server.addr);
        tracing::info!(
            role = %a.role,
            node = config_node.as_deref().unwrap_or(""),
            data_dir = %a.data_dir.display(),
            threads,
            memory_budget_mib = budget >> 20,
            max_job_memory_mib = per_job >> 20,
            "radiance serve ready"
        );
        shutdown_signal().await;
        tracing::info!("shutting down: checkpointing running jobs");
        server.shutdown().await.context("shutting down")?;
        Ok(())
    })
}

/// `--role` takes the names of [`Role`] (listed in `--help`).
fn role_parser() -> impl clap::builder::TypedValueParser<Value = Role> {
    use clap::builder::TypedValueParser;
    clap::builder::PossibleValuesParser::new(Role::NAMES).try_map(|name| name.parse::<Role>())
}

/// Checks what the role and store flags ask for, and answers the shared
/// stores of distributed mode (the database URL and the object store), or
/// `None` for one embedded node (`--role all` and neither store). A
/// database URL is never quoted back: it may hold a password.
fn deployment<'a>(
    role: Role,
    database_url: Option<&'a str>,
    object_store: Option<&'a str>,
) -> anyhow::Result<Option<(&'a str, &'a str)>> {
    if let Some(url) = database_url
        && !(url.starts_with("postgres://") || url.starts_with("postgresql://"))
    {
        anyhow::bail!("--database-url / RADIANCE_DATABASE_URL: expected a postgres:// or postgresql:// URL");
    }
    if let Some(store) = object_store
        && !(store.starts_with("s3://") || store.starts_with("file://"))
    {
        anyhow::bail!("--object-store {store}: expected s3://BUCKET/PREFIX or file:///PATH");
    }
    match (role, database_url, object_store) {
        (Role::All, None, None) => Ok(None),
        (_, Some(_), None) | (_, None, Some(_)) => anyhow::bail!(
            "--database-url and --object-store go together: distributed mode needs both the shared job store \
             (PostgreSQL) and the shared artifact store; give both, or neither for one node over --data-dir"
        ),
        (role, None, None) => anyhow::bail!(
            "--role {role} needs the shared stores of distributed mode (--database-url and --object-store); \
             one node over its --data-dir runs with --role all (the default)"
        ),
        (_, Some(db), Some(store)) => Ok(Some((db, store))),
    }
}

/// The settings of distributed mode from the flags.
fn distributed_settings(a: &ServeArgs, database_url: &str, object_store: &str) -> anyhow::Result<Distributed> {
    let lease = std::time::Duration::try_from_secs_f64(a.lease_seconds)
        .ok()
        .filter(|l| *l >= std::time::Duration::from_secs(1) && *l <= std::time::Duration::from_secs(3600))
        .ok_or_else(|| anyhow::anyhow!("--lease-seconds must be between 1 and 3600"))?;
    let startup_wait = std::time::Duration::try_from_secs_f64(a.startup_wait_seconds)
        .map_err(|_| anyhow::anyhow!("--startup-wait-seconds must be a number of seconds, 0 or more"))?;
    anyhow::ensure!(a.db_pool_size > 0, "--db-pool-size must be at least 1");
    anyhow::ensure!(a.cache_max_mb > 0, "--cache-max-mb must be positive");
    let node_id = match &a.node_id {
        Some(id) => {
            anyhow::ensure!(
                !id.is_empty()
                    && id.len() <= 100
                    && id.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-')),
                "--node-id {id:?}: expected 1 to 100 letters, digits, '.', '_' or '-' (it names the node in \
                 leases, logs and metrics)"
            );
            id.clone()
        }
        None => default_node_id(),
    };
    Ok(Distributed {
        database_url: database_url.to_string(),
        object_store: object_store.to_string(),
        node_id,
        lease,
        cache_max_bytes: a.cache_max_mb << 20,
        db_pool_size: a.db_pool_size,
        startup_wait,
    })
}

/// `<host name>-<8 hex digits>`: unique among the nodes of a deployment
/// even when they share a host name (containers from one image).
fn default_node_id() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    let host = host.trim();
    let random = uuid::Uuid::now_v7().simple().to_string();
    format!("{}-{}", if host.is_empty() { "node" } else { host }, &random[random.len() - 8..])
}

/// COLMAP (and ffmpeg) for photo-only uploads, said plainly in the log
/// either way: a missing COLMAP disables those uploads only.
fn pose_tools(colmap: Option<&std::path::Path>) -> Option<Tools> {
    let colmap = match crate::poses::colmap::find(colmap) {
        Ok(c) => c,
        Err(e) => {
            tracing::warn!("photo-only uploads are disabled: {e}. Posed datasets upload and train as usual");
            return None;
        }
    };
    let ffmpeg = match crate::poses::video::find(None) {
        Ok(f) => Some(f),
        Err(e) => {
            tracing::warn!("video uploads are disabled: {e}");
            None
        }
    };
    tracing::info!(
        colmap = %colmap.path.display(),
        version = %colmap.version,
        videos = ffmpeg.is_some(),
        "photo-only uploads are enabled: their camera poses are estimated with COLMAP"
    );
    Some(Tools { colmap, ffmpeg })
}

/// The API key to require, if any. A key that is set but empty (as
/// `RADIANCE_API_KEY=` in a compose file with a missing secret gives) is
/// refused: serving without authentication is then never what was meant.
fn api_key(key: Option<String>) -> anyhow::Result<Option<String>> {
    match key {
        Some(k) if k.trim().is_empty() => anyhow::bail!(
            "RADIANCE_API_KEY / --api-key is set but empty: give a key, or unset it to serve without \
             authentication"
        ),
        other => Ok(other),
    }
}

/// Ctrl-C or SIGTERM.
async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The refusal of a flag combination.
    fn refusal(role: Role, db: Option<&str>, store: Option<&str>) -> String {
        deployment(role, db, store).expect_err("refused").to_string()
    }

    #[test]
    fn embedded_is_role_all_alone_and_distributed_needs_both_stores() {
        assert_eq!(deployment(Role::All, None, None).unwrap(), None);
        for role in [Role::Api, Role::Worker] {
            let e = refusal(role, None, None);
            assert!(e.starts_with(&format!("--role {role} needs the shared stores")), "{e}");
        }
        let db = "postgres://radiance:s3cret@db.example/radiance";
        for role in [Role::All, Role::Api, Role::Worker] {
            let e = refusal(role, Some(db), None);
            assert!(e.starts_with("--database-url and --object-store go together") && !e.contains("s3cret"), "{e}");
            let e = refusal(role, None, Some("s3://bucket/prefix"));
            assert!(e.starts_with("--database-url and --object-store go together"), "{e}");
            let both = deployment(role, Some(db), Some("file:///srv/radiance")).unwrap();
            assert_eq!(both, Some((db, "file:///srv/radiance")));
        }
    }

    #[test]
    fn node_ids_default_to_the_host_and_random_digits() {
        let (a, b) = (default_node_id(), default_node_id());
        assert_ne!(a, b);
        let (host, digits) = a.rsplit_once('-').unwrap();
        assert!(!host.is_empty() && digits.len() == 8 && digits.chars().all(|c| c.is_ascii_hexdigit()), "{a}");
    }

    #[test]
    fn store_urls_are_checked_and_a_password_is_never_quoted() {
        let e = refusal(Role::Api, Some("mysql://u:s3cret@h/db"), Some("s3://b"));
        assert!(e.contains("expected a postgres:// or postgresql:// URL") && !e.contains("s3cret"), "{e}");
        let e = refusal(Role::Api, Some("postgresql://h/db"), Some("ftp://b"));
        assert!(e.contains("--object-store ftp://b: expected s3://"), "{e}");
    }
}
