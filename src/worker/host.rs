//! [`RemoteHost`]: the [`JobHost`] of a job a worker runs, over the shared
//! stores. Records come from PostgreSQL, files from the object store
//! through the local cache; what the job makes goes back to the object
//! store, and its record is published under the job's lease, so a worker
//! that lost the job publishes nothing.
//!
//! The job bodies run on std threads; each call here runs its async work on
//! the service's runtime (`Handle::block_on`, legal off the runtime's own
//! threads).
//!
//! A training job's session saves its checkpoint to a local scratch file
//! (`DATA/cache/jobs/<job>/model.ckpt`). At each save the file is uploaded
//! (content-addressed: `models/<id>/<sha256>.ckpt`) and then the model's
//! record is made to name it, fenced by the lease; the checkpoint it
//! replaces is deleted. A job resumed on another worker starts from the
//! checkpoint its model's record names, downloaded to that scratch file.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::Ctx;
use super::keeper::Run;
use crate::backend::pg::PgError;
use crate::backend::{ArtifactStore, NewJob};
use crate::datadir::{Local, ScenePart};
use crate::jobs::host::JobHost;
use crate::jobs::{Counters, Job, JobSpec, SchedulerConfig};
use crate::records::{ModelInfo, SceneInfo, VideoInfo};

/// The host of one running job (see the module comment).
pub struct RemoteHost {
    pub(super) ctx: Arc<Ctx>,
    pub(super) run: Arc<Run>,
}

impl RemoteHost {
    /// The job's scratch folder on this node.
    pub fn scratch(&self) -> PathBuf {
        self.ctx.scratch.join(&self.run.lease.job_id)
    }

    /// Refuses a write once the lease may be lost.
    fn check_lease(&self) -> io::Result<()> {
        if self.run.holds() {
            Ok(())
        } else {
            self.run.fence("the lease is not held: nothing is published");
            Err(lease_lost(&self.run.lease.job_id))
        }
    }

    /// `e`; a lost lease also stops the job.
    fn pg_error(&self, e: PgError, doing: &str) -> io::Error {
        if matches!(e, PgError::LeaseLost(_)) {
            self.run.fence("a fenced write was refused: the lease is lost");
        }
        io::Error::other(format!("{doing}: {e}"))
    }
}

fn lease_lost(job: &str) -> io::Error {
    io::Error::other(format!("the lease on job '{job}' is lost: another worker may run it now"))
}

impl JobHost for RemoteHost {
    fn config(&self) -> &SchedulerConfig {
        &self.ctx.config
    }

    fn counters(&self) -> &Counters {
        &self.ctx.stats.train
    }

    /// The job's progress in memory; the next heartbeat writes it.
    fn set_progress(&self, job_id: &str, f: &mut dyn FnMut(&mut Job)) {
        let mut job = self.run.job();
        if job.id == job_id {
            f(&mut job);
        }
    }

    fn scene(&self, id: &str) -> io::Result<Option<SceneInfo>> {
        self.ctx.rt.block_on(self.ctx.queue.scene(id)).map_err(|e| self.pg_error(e, "reading the scene"))
    }

    fn model(&self, id: &str) -> io::Result<Option<ModelInfo>> {
        self.ctx.rt.block_on(self.ctx.queue.model(id)).map_err(|e| self.pg_error(e, "reading the model"))
    }

    /// The scene's tar, unpacked once into the local cache (pinned while
    /// the job holds it).
    fn scene_dir(&self, scene: &SceneInfo, part: ScenePart) -> io::Result<Local> {
        self.ctx.rt.block_on(self.ctx.artifacts.scene_files(scene, part))
    }

    /// A fresh scratch file, holding the model's published checkpoint when
    /// there is one (the job was started before, maybe on another worker):
    /// the session resumes from it.
    fn job_checkpoint(&self, _job: &Job, model_id: &str) -> io::Result<PathBuf> {
        let dir = self.scratch();
        if dir.exists() {
            std::fs::remove_dir_all(&dir)?;
        }
        std::fs::create_dir_all(&dir)?;
        let ckpt = dir.join("model.ckpt");
        let sha = self
            .ctx
            .rt
            .block_on(self.ctx.queue.checkpoint_sha256(model_id))
            .map_err(|e| self.pg_error(e, "reading the model's checkpoint"))?;
        if let Some(sha) = sha {
            self.ctx
                .rt
                .block_on(self.ctx.artifacts.fetch_checkpoint(model_id, &sha, &ckpt))
                .map_err(|e| io::Error::new(e.kind(), format!("fetching checkpoint {sha} of {model_id}: {e}")))?;
            tracing::info!(job = %self.run.lease.job_id, worker = %self.ctx.node, model = model_id, sha256 = %sha,
                "fetched the job's last checkpoint to resume from");
        }
        Ok(ckpt)
    }

    /// Uploads the checkpoint, then points the model's record at it under
    /// the lease, then deletes the one it replaced.
    fn publish_model(&self, _job: &Job, info: &ModelInfo, ckpt: &Path) -> io::Result<()> {
        self.check_lease()?;
        let (ctx, run) = (&self.ctx, &self.run);
        let stored = ctx.rt.block_on(ctx.artifacts.put_checkpoint(&info.id, ckpt))?;
        self.check_lease()?;
        let replaced = ctx
            .rt
            .block_on(ctx.queue.publish_model(&run.lease, info, &stored.sha256))
            .map_err(|e| self.pg_error(e, "publishing the model"))?;
        tracing::info!(job = %run.lease.job_id, worker = %ctx.node, model = %info.id, step = info.steps,
            sha256 = %stored.sha256, bytes = stored.size, "checkpoint stored and published");
        if let Some(old) = replaced
            && let Err(e) = ctx.rt.block_on(ctx.artifacts.delete_checkpoint(&info.id, &old))
        {
            tracing::warn!(model = %info.id, sha256 = %old, error = %e, "cannot delete a replaced checkpoint");
        }
        Ok(())
    }

    fn model_checkpoint(&self, info: &ModelInfo) -> io::Result<Local> {
        self.ctx.rt.block_on(self.ctx.artifacts.checkpoint(info))
    }

    /// The bytes (one atomic put), then the record under the lease.
    fn publish_video(&self, _job: &Job, info: &VideoInfo, bytes: &[u8]) -> io::Result<()> {
        self.check_lease()?;
        let ctx = &self.ctx;
        ctx.rt.block_on(ctx.artifacts.put_video(&info.id, bytes.to_vec()))?;
        self.check_lease()?;
        ctx.rt
            .block_on(ctx.queue.publish_video(&self.run.lease, info))
            .map_err(|e| self.pg_error(e, "publishing the video"))
    }

    /// Workers claim no pose estimations (they claim as having no COLMAP):
    /// the fenced publish of a posed scene is not built.
    fn posing_workdir(&self, _job: &Job, _scene: &SceneInfo) -> io::Result<PathBuf> {
        Err(io::Error::new(io::ErrorKind::Unsupported, "pose estimation does not run on workers yet"))
    }

    fn publish_posed_scene(&self, _job: &Job, _ready: &SceneInfo, _workdir: &Path) -> io::Result<()> {
        Err(io::Error::new(io::ErrorKind::Unsupported, "pose estimation does not run on workers yet"))
    }

    /// Through the queue; an id already taken is the job this one enqueued
    /// in a run before.
    fn enqueue(&self, id: String, spec: JobSpec, memory_estimate: u64) -> Result<(), String> {
        if self.ctx.rt.block_on(self.ctx.queue.get(&id)).map_err(|e| e.to_string())?.is_some() {
            return Ok(());
        }
        let new = NewJob { id: Some(id), spec, model_id: None, memory_estimate };
        self.ctx.rt.block_on(self.ctx.queue.enqueue(new)).map(|_| ()).map_err(|e| e.to_string())
    }
}
