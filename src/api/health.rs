//! `GET /healthz` (alive), `GET /readyz` (the stores can serve) and
//! `GET /metrics` (Prometheus text format).

use std::fmt::Write;
use std::sync::atomic::Ordering;

use axum::Json;
use axum::extract::State;
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use serde_json::{Value, json};

use super::{ApiError, ApiResult, AppState, Code};
use crate::datadir::DiskUsage;
use crate::jobs::{Counters, Status};

/// Liveness, the version, and which optional uploads this server takes
/// (photo-only and video uploads need COLMAP, videos also ffmpeg).
pub async fn healthz(State(s): State<AppState>) -> Json<Value> {
    let poses = s.config.scheduler.poses.as_ref();
    Json(json!({
        "status": "ok",
        "version": env!("CARGO_PKG_VERSION"),
        "features": {
            "photo_uploads": poses.is_some(),
            "video_uploads": poses.is_some_and(|p| p.tools.ffmpeg.is_some()),
        },
    }))
}

/// Readiness: 200 while the job store and the artifact store can serve
/// (embedded: the job database answers a read, the data directory's folders
/// are there and a file can be made in `tmp/`); else 503 `unavailable`,
/// naming the store (the details go to the log, not to unauthenticated
/// callers).
pub async fn readyz(State(s): State<AppState>) -> ApiResult<Json<Value>> {
    if let Err(e) = s.jobs.ready().await {
        tracing::warn!(error = %e, "not ready: the job store");
        return Err(ApiError::new(Code::Unavailable, "not ready: the job store cannot serve (see the server log)"));
    }
    if let Err(e) = s.artifacts.ready().await {
        tracing::warn!(error = %e, "not ready: the artifact store");
        return Err(ApiError::new(
            Code::Unavailable,
            "not ready: the artifact store cannot serve (see the server log)",
        ));
    }
    Ok(Json(json!({ "status": "ready", "role": s.config.role.name() })))
}

pub async fn metrics(State(s): State<AppState>) -> ApiResult<impl IntoResponse> {
    let disk = s.artifacts.usage().await?;
    let stats = s.jobs.stats().await?;
    let (by_status, queue) = (stats.by_status, stats.queued);
    let (renders, render_secs) = {
        let r = s.renders.lock().unwrap_or_else(|e| e.into_inner());
        (r.count, r.seconds)
    };
    let mut out = String::new();
    let _ =
        writeln!(out, "# HELP radiance_node_info This node: its role and version.\n# TYPE radiance_node_info gauge");
    let (role, version) = (s.config.role.name(), env!("CARGO_PKG_VERSION"));
    // Distributed nodes also say which node they are (`--node-id`).
    let node = s.config.distributed.as_ref().map(|d| format!(",node=\"{}\"", d.node_id)).unwrap_or_default();
    let _ = writeln!(out, "radiance_node_info{{role=\"{role}\"{node},version=\"{version}\"}} 1");
    let _ = writeln!(out, "# HELP radiance_jobs Jobs by status.\n# TYPE radiance_jobs gauge");
    for st in Status::ALL {
        let _ = writeln!(out, "radiance_jobs{{status=\"{}\"}} {}", st.name(), by_status.get(&st).copied().unwrap_or(0));
    }
    let _ = writeln!(out, "# HELP radiance_queue_depth Jobs waiting to run.\n# TYPE radiance_queue_depth gauge");
    let _ = writeln!(out, "radiance_queue_depth {queue}");
    if let Some(c) = s.jobs.counters().or(s.worker_stats.as_deref().map(|w| &w.train)) {
        write_counters(&mut out, c);
    }
    if let Some(w) = &s.worker_stats {
        for (name, help, kind, v) in w.series() {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}\n{name} {v}");
        }
    }
    let _ = writeln!(out, "# HELP radiance_render_seconds Render latency.\n# TYPE radiance_render_seconds summary");
    let _ = writeln!(out, "radiance_render_seconds_sum {render_secs}\nradiance_render_seconds_count {renders}");
    write_disk(&mut out, &disk);
    Ok(([(CONTENT_TYPE, "text/plain; version=0.0.4")], out))
}

/// The training counters of the jobs this process runs.
fn write_counters(out: &mut String, c: &Counters) {
    let counters = [
        ("radiance_train_steps_total", "Training steps done.", c.train_steps.load(Ordering::Relaxed) as f64),
        ("radiance_train_rays_total", "Training rays processed.", c.train_rays.load(Ordering::Relaxed) as f64),
        (
            "radiance_train_seconds_total",
            "Seconds spent training (rays_total / seconds_total is the throughput).",
            c.train_micros.load(Ordering::Relaxed) as f64 * 1e-6,
        ),
    ];
    for (name, help, v) in counters {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
    }
}

/// `radiance_disk_bytes{kind}`: bytes under each folder of the data directory.
fn write_disk(out: &mut String, d: &DiskUsage) {
    let _ = writeln!(
        out,
        "# HELP radiance_disk_bytes Bytes of the files under each folder of the data directory.\n\
         # TYPE radiance_disk_bytes gauge"
    );
    for (kind, bytes) in [("scenes", d.scenes), ("models", d.models), ("videos", d.videos), ("tmp", d.tmp)] {
        let _ = writeln!(out, "radiance_disk_bytes{{kind=\"{kind}\"}} {bytes}");
    }
}
