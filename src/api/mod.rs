//! The REST service: `app(state)` builds every route; [`Server::start`]
//! opens the stores, binds the router and serves it.
//!
//! One file per resource (`scenes` and their `thumbnails`, `jobs`, `models`,
//! `videos`, `demo`), one
//! error type (`error`), archive extraction (`archive`), `/healthz`,
//! `/readyz` and `/metrics` (`health`), the web app's embedded files
//! (`web`), the node's role (`role`), the shared stores and worker of
//! distributed mode (`deploy`) and the tower-http layers around it all
//! (`layers`). Handlers reach jobs, records and stored files only through
//! the stores (`crate::backend`: the job store and the artifact store; the
//! embedded pair runs the job scheduler beside the router). Handlers never
//! block the runtime: extraction, dataset validation and rendering run under
//! `spawn_blocking`, training on the scheduler's threads; the numeric work of
//! both on the global rayon pool.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::header::AUTHORIZATION;
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put};

use crate::backend::{Artifact, ArtifactStore, JobStore, embedded};
use crate::engine::front::Model;
use crate::jobs::SchedulerConfig;

pub mod archive;
pub mod camera_path;
pub mod crop;
pub mod demo;
pub mod deploy;
pub mod error;
pub mod health;
pub mod jobs;
pub mod layers;
pub mod limits;
pub mod mesh;
pub mod models;
pub mod role;
pub mod scenes;
pub mod site;
pub mod thumbnails;
pub mod transients;
pub mod videos;
pub mod web;

pub use deploy::Distributed;
pub use error::{ApiError, ApiResult, Code};
pub use role::Role;

/// Service settings.
#[derive(Clone, Debug)]
pub struct ServiceConfig {
    pub data_dir: PathBuf,
    /// Largest accepted upload body.
    pub max_upload_bytes: u64,
    /// Largest size an archive may unpack to.
    pub max_unpacked_bytes: u64,
    pub max_archive_entries: usize,
    /// Largest `width * height` of a render.
    pub max_render_pixels: u64,
    /// Renders running at once (others wait).
    pub max_concurrent_renders: usize,
    /// When set, every route but `/healthz` and `/readyz` needs `Authorization: Bearer KEY`.
    pub api_key: Option<String>,
    /// Free disk space a new job must leave, beyond its own output.
    pub min_free_disk_bytes: u64,
    /// Origins allowed to call the API from a browser page of their own
    /// (CORS); empty: none but the service's own page.
    pub cors_origins: Vec<String>,
    /// What this node does: the API, the jobs, or both (`all`, the only
    /// role of an embedded node).
    pub role: Role,
    /// The shared stores of distributed mode; `None`: the embedded stores
    /// in `data_dir`.
    pub distributed: Option<Distributed>,
    pub scheduler: SchedulerConfig,
}

impl ServiceConfig {
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        Self {
            data_dir: data_dir.into(),
            max_upload_bytes: 512 << 20,
            max_unpacked_bytes: 2 << 30,
            max_archive_entries: 100_000,
            max_render_pixels: 1 << 20,
            max_concurrent_renders: 2,
            api_key: None,
            min_free_disk_bytes: 1 << 30,
            cors_origins: Vec::new(),
            role: Role::All,
            distributed: None,
            scheduler: SchedulerConfig::default(),
        }
    }
}

/// Render counters for /metrics.
#[derive(Default)]
pub struct RenderStats {
    pub count: u64,
    pub seconds: f64,
}

/// Everything a handler needs.
pub struct AppInner {
    pub config: ServiceConfig,
    /// Jobs, and the records of scenes, models and videos.
    pub jobs: Arc<dyn JobStore>,
    /// Their bytes: datasets, checkpoints, videos.
    pub artifacts: Arc<dyn ArtifactStore>,
    pub renders: Mutex<RenderStats>,
    pub render_slots: tokio::sync::Semaphore,
    /// Recently used models, most recent first.
    pub model_cache: Mutex<Vec<CachedModel>>,
    /// Meshes made lately (`mesh`).
    pub meshes: mesh::MeshCache,
    /// What this node's worker counts (distributed mode; the embedded job
    /// store has its training counters, `JobStore::counters`).
    pub worker_stats: Option<Arc<crate::worker::WorkerStats>>,
}

/// A loaded model and the transient maps its checkpoint holds, valid while
/// its record's `updated_at` is unchanged.
#[derive(Clone)]
pub struct CachedModel {
    pub id: String,
    pub updated_at: u64,
    pub model: Arc<dyn Model>,
    pub transients: Option<Arc<crate::engine::front::TransientMaps>>,
    /// With the record's crop: what views of it draw (`Ok(None)`: a model
    /// whose views the crop leaves as they are), or why the crop cannot be
    /// used (it keeps none of the Gaussians).
    pub cropped: Option<Result<Option<Arc<dyn Model>>, String>>,
}

impl CachedModel {
    /// The model as views, videos and exports draw it: cropped when its
    /// record has a crop; a crop that cannot be used is a conflict.
    pub fn viewed(&self) -> ApiResult<Arc<dyn Model>> {
        match &self.cropped {
            None | Some(Ok(None)) => Ok(self.model.clone()),
            Some(Ok(Some(m))) => Ok(m.clone()),
            Some(Err(why)) => Err(ApiError::conflict(format!(
                "model '{}''s crop cannot be used ({why}): PUT another or DELETE it, or ask with crop=false",
                self.id
            ))),
        }
    }
}

pub type AppState = Arc<AppInner>;

/// Builds the router over a state.
pub fn app(state: AppState) -> Router {
    use layers::quick;
    let v1 = Router::new()
        // The body limit of uploads is tower-http's (`layers`), on every route.
        .route("/v1/scenes", post(scenes::create).layer(DefaultBodyLimit::disable()).merge(quick(get(scenes::list))))
        .route("/v1/scenes/{id}", quick(get(scenes::get_one).delete(scenes::delete)))
        .route("/v1/scenes/{id}/thumbnail", get(thumbnails::get))
        // The demo ray traces its scene on the first call: no `quick` timeout.
        .route("/v1/demo", post(demo::create))
        .route("/v1/jobs", quick(post(jobs::create).get(jobs::list)))
        .route("/v1/jobs/{id}", quick(get(jobs::get_one).delete(jobs::delete)))
        .route("/v1/jobs/{id}/cancel", quick(post(jobs::cancel)))
        .route("/v1/jobs/{id}/events", get(jobs::events))
        .route("/v1/models", quick(get(models::list)))
        .route("/v1/models/{id}", quick(get(models::get_one).delete(models::delete)))
        .route("/v1/models/{id}/render", get(models::render))
        .route("/v1/models/{id}/export", get(models::export))
        .route("/v1/models/{id}/mesh", get(mesh::get))
        .route("/v1/models/{id}/crop", put(crop::put).merge(quick(get(crop::get).delete(crop::delete))))
        .route("/v1/models/{id}/transients/{photo}", get(transients::get))
        .route("/v1/models/{id}/videos", quick(post(videos::create)))
        .route("/v1/videos/{id}", get(videos::get_one).merge(quick(delete(videos::delete))))
        .route("/metrics", quick(get(health::metrics)))
        .route_layer(middleware::from_fn_with_state(state.clone(), auth));
    // The page and its files need no key: the page asks for it.
    let web = Router::new().route("/", get(web::index)).route("/assets/{*name}", get(web::asset));
    let (max_body, cors) = (state.config.max_upload_bytes, state.config.cors_origins.clone());
    let routes = Router::new()
        .route("/healthz", get(health::healthz))
        .route("/readyz", get(health::readyz))
        .merge(web)
        .merge(v1)
        .fallback(not_found)
        .with_state(state);
    // Around the whole router rather than its routes: axum adds the `Allow`
    // header of a 405 as the answer leaves the route, after any route layer.
    layers::around(Router::new().fallback_service(routes), max_body, &cors)
}

/// The router of a `worker` node: health, readiness and metrics only (its
/// jobs come from the queue, not from requests).
pub fn worker_app(state: AppState) -> Router {
    let (max_body, cors) = (state.config.max_upload_bytes, state.config.cors_origins.clone());
    let metrics = Router::new()
        .route("/metrics", layers::quick(get(health::metrics)))
        .route_layer(middleware::from_fn_with_state(state.clone(), auth));
    let routes = Router::new()
        .route("/healthz", get(health::healthz))
        .route("/readyz", get(health::readyz))
        .merge(metrics)
        .fallback(not_found)
        .with_state(state);
    layers::around(Router::new().fallback_service(routes), max_body, &cors)
}

/// Removes the bytes behind a record just deleted. The delete has happened
/// (the record is gone, and the client is answered 204): bytes that could
/// not be removed stay in the object store, unreachable, and the log says
/// which.
async fn remove_artifact(s: &AppState, what: Artifact<'_>) {
    if let Err(e) = s.artifacts.remove(what).await {
        tracing::warn!(what = ?what, error = %e, "deleted the record, but not its bytes: they stay in the store, unused");
    }
}

async fn not_found(req: Request) -> ApiError {
    ApiError::new(Code::NotFound, format!("no route for {} {}", req.method(), req.uri().path()))
}

/// Bearer-token check, when an API key is configured. The 401 carries a
/// `WWW-Authenticate` challenge (see [`ApiError`]'s response).
async fn auth(State(s): State<AppState>, req: Request, next: Next) -> Response {
    if let Some(key) = &s.config.api_key {
        let given = req.headers().get(AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(bearer_token);
        if !given.is_some_and(|g| constant_time_eq(g.as_bytes(), key.as_bytes())) {
            return ApiError::new(Code::Unauthorized, "missing or wrong API key (Authorization: Bearer KEY)")
                .into_response();
        }
    }
    next.run(req).await
}

/// The token of an `Authorization: Bearer TOKEN` value. The scheme name is
/// case-insensitive (RFC 9110 section 11.1), so `bearer` and `BEARER` work too.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.split_once(' ')?;
    scheme.eq_ignore_ascii_case("bearer").then(|| token.trim_matches(' '))
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// A running service.
pub struct Server {
    pub addr: SocketAddr,
    pub state: AppState,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
    /// The worker of a distributed `worker` or `all` node.
    worker: Option<crate::worker::Worker>,
}

impl Server {
    /// Opens the stores, binds `addr` and serves in a background task.
    /// Embedded (no [`ServiceConfig::distributed`]): the data directory,
    /// and the job queue resumed; only role `all`. Distributed: PostgreSQL
    /// and the object store (see `deploy`), the full router on `api` and
    /// `all` nodes, health and metrics alone on `worker` nodes, and a
    /// worker claiming jobs on `worker` and `all` nodes.
    pub async fn start(config: ServiceConfig, addr: SocketAddr) -> std::io::Result<Server> {
        let (jobs, artifacts, worker): (Arc<dyn JobStore>, Arc<dyn ArtifactStore>, _) = match &config.distributed {
            None if config.role != Role::All => {
                return Err(std::io::Error::new(std::io::ErrorKind::Unsupported, role::needs_stores(config.role)));
            }
            None => {
                let (jobs, artifacts) = embedded::open(&config.data_dir, config.scheduler.clone())?;
                (Arc::new(jobs), Arc::new(artifacts), None)
            }
            Some(d) => {
                let opened = deploy::open(d, config.role, &config.data_dir, &config.scheduler).await?;
                (opened.jobs, opened.artifacts, opened.worker)
            }
        };
        let role = config.role;
        let state = Arc::new(AppInner {
            render_slots: tokio::sync::Semaphore::new(config.max_concurrent_renders.max(1)),
            config,
            jobs,
            artifacts,
            renders: Mutex::new(RenderStats::default()),
            model_cache: Mutex::new(Vec::new()),
            meshes: mesh::MeshCache::default(),
            worker_stats: worker.as_ref().map(crate::worker::Worker::stats),
        });
        let listener = tokio::net::TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let (stop, rx) = tokio::sync::oneshot::channel::<()>();
        let router = if role == Role::Worker { worker_app(state.clone()) } else { app(state.clone()) };
        let task = tokio::spawn(async move {
            axum::serve(listener, router)
                .with_graceful_shutdown(async move {
                    let _ = rx.await;
                })
                .await
        });
        tracing::info!(%addr, %role, "listening");
        Ok(Server { addr, state, stop, task, worker })
    }

    /// Stops accepting requests, lets running ones finish, stops the
    /// worker, then the job store (running jobs checkpoint and resume: at
    /// the next start, or on any worker).
    pub async fn shutdown(self) -> std::io::Result<()> {
        let _ = self.stop.send(());
        let served = self.task.await.map_err(std::io::Error::other)?;
        if let Some(w) = self.worker {
            w.shutdown().await;
        }
        self.state.jobs.shutdown().await;
        served
    }
}
