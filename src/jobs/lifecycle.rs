//! Deleting what the jobs made (a finished job's record, a model, a video)
//! and changing a model's crop volume.
//! Each check ("is anything queued or running that needs it?") and its
//! deletion happen under the scheduler's lock, so no job can be enqueued
//! on a model between the check and the removal (enqueueing checks that
//! the model exists under the same lock, and a job being enqueued counts
//! as queued). These deletions are of files, not of job records: no job
//! database write happens under the lock.

use super::{Job, JobSpec, SchedError, Scheduler, State};
use crate::datadir::write_json;
use crate::records::{CropBox, ModelInfo};
use crate::system::now_ms;

impl Scheduler {
    /// Removes a finished job's record: from the job database (outside the
    /// lock), then from memory, so that if the database fails the job is
    /// still listed. What it made (a model, a video) stays. A queued or
    /// running job must be canceled first.
    pub fn delete_job(&self, id: &str) -> Result<(), SchedError> {
        let rev = {
            let mut st = self.shared.lock();
            let Some(job) = st.jobs.get(id) else { return Err(SchedError::JobNotFound(id.into())) };
            if !job.status.is_final() {
                return Err(SchedError::JobNotFinal { id: id.into(), status: job.status.name() });
            }
            // Numbered like a record, so a final record still on its way to
            // the database cannot bring the job back.
            let job = job.clone();
            st.record(job).rev
        };
        self.shared.journal.remove(id, rev)?;
        self.shared.lock().jobs.remove(id);
        Ok(())
    }

    /// Removes a model (record, then checkpoint) unless a queued or running
    /// job writes or renders it. Videos made from it stay.
    pub fn delete_model(&self, id: &str) -> Result<(), SchedError> {
        // Retention rewrites checkpoints under `model_files`; the order
        // (`model_files`, then the scheduler's lock) is the same everywhere.
        let _files = self.shared.model_files.lock().unwrap_or_else(|e| e.into_inner());
        let st = self.shared.lock();
        let storage = &self.shared.storage;
        if storage.load_model(id)?.is_none() {
            return Err(SchedError::ModelNotFound(id.into()));
        }
        if let Some(j) = model_user(&st, id) {
            return Err(SchedError::ModelInUse { model: id.into(), job: j.id.clone(), status: j.status.name() });
        }
        storage.remove_model(id)?;
        Ok(())
    }

    /// Sets or removes a model's crop volume (`JobStore::set_crop`) unless a
    /// job that has not ended writes or renders the model. Under
    /// `model_files`, as retention's rewrite of the same record.
    pub fn set_crop(&self, id: &str, crop: Option<CropBox>) -> Result<ModelInfo, SchedError> {
        let _files = self.shared.model_files.lock().unwrap_or_else(|e| e.into_inner());
        let st = self.shared.lock();
        let storage = &self.shared.storage;
        let Some(mut info) = storage.load_model(id)? else { return Err(SchedError::ModelNotFound(id.into())) };
        if let Some(j) = model_user(&st, id) {
            return Err(SchedError::ModelInUse { model: id.into(), job: j.id.clone(), status: j.status.name() });
        }
        info.crop = crop;
        // Strictly later, so that a cache keyed on it sees the change.
        info.updated_at = now_ms().max(info.updated_at + 1);
        write_json(&storage.model_record(id), &info)?;
        Ok(info)
    }

    /// Removes a video (record, then file) unless its job has not ended.
    pub fn delete_video(&self, id: &str) -> Result<(), SchedError> {
        let st = self.shared.lock();
        let storage = &self.shared.storage;
        let Some(info) = storage.load_video(id)? else { return Err(SchedError::VideoNotFound(id.into())) };
        if let Some(j) = st.jobs.get(&info.job_id).filter(|j| !j.status.is_final()) {
            return Err(SchedError::VideoInUse { video: id.into(), job: j.id.clone(), status: j.status.name() });
        }
        storage.remove_video(id)?;
        Ok(())
    }
}

/// Whether `job` writes model `id` (a training or bake job) or reads it
/// (a video job, or a bake job of that model).
pub(crate) fn uses_model(job: &Job, id: &str) -> bool {
    let bakes = matches!(&job.spec, JobSpec::Bake(b) if b.source_model_id == id);
    writes_model(job, id) || job.model_id.as_deref() == Some(id) || bakes
}

/// Whether `job` is the training (or bake) job of model `id` (before its
/// first checkpoint the job's `model_id` is not set yet, but the id is
/// reserved).
pub(crate) fn writes_model(job: &Job, id: &str) -> bool {
    matches!(job.spec, JobSpec::Train(_) | JobSpec::Bake(_))
        && (job.reserved_model_id() == id || job.model_id.as_deref() == Some(id))
}

/// A queued, running or enqueuing job that writes or renders model `id`.
fn model_user<'a>(st: &'a State, id: &str) -> Option<&'a Job> {
    st.active().find(|j| uses_model(j, id))
}
