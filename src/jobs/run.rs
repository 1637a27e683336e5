//! The scheduler's thread: each tick starts the queued jobs that fit, runs
//! each on a thread of its own ([`run_body`]) and settles what they end in.

use super::*;

/// The scheduler thread: `tick` until shutdown, writing the records it
/// hands out after releasing the lock, and the retention sweep (without the
/// lock) at start-up, when a job ends and once a minute.
pub(super) fn scheduler_loop(shared: &Arc<Shared>) {
    let mut last_sweep: Option<Instant> = None;
    let mut st = shared.lock();
    while !st.shutting_down {
        let records = tick(shared, &mut st);
        if !records.is_empty() {
            drop(st);
            for r in &records {
                shared.persist_logged(r, "end");
                settle_scene(shared, &r.job);
            }
            st = shared.lock();
        }
        if retention::sweep_due(shared, last_sweep) {
            drop(st);
            retention::sweep(shared);
            last_sweep = Some(Instant::now());
            st = shared.lock();
        }
        st = shared.wake.wait_timeout(st, Duration::from_millis(500)).unwrap_or_else(|e| e.into_inner()).0;
    }
}

/// One round of scheduling, in order:
/// 1. forget the threads of jobs that have finished;
/// 2. while fewer than `max_concurrent` jobs run, take the oldest queued job,
///    mark it running, and start it on its own thread (which first persists
///    that), whose heavy work runs on the global rayon pool; a job that
///    cannot start is failed.
///
/// Returns the records of the jobs it failed, for the caller to write
/// once the lock is released.
fn tick(shared: &Arc<Shared>, st: &mut State) -> Vec<Record> {
    let mut failed = Vec::new();
    st.threads.retain(|t| !t.is_finished());
    if !shared.config.run_jobs {
        return failed;
    }
    while st.running.len() < shared.config.max_concurrent.max(1) {
        let Some(id) = st.queue.front().cloned() else { break };
        let Some(need) = st.jobs.get(&id).map(|j| j.memory_estimate_bytes) else {
            st.queue.pop_front();
            continue;
        };
        if need > shared.config.max_job_memory_bytes {
            // Accepted under a larger limit before a restart.
            st.queue.pop_front();
            let limit = shared.config.max_job_memory_bytes >> 20;
            let msg =
                format!("the job needs about {} MiB, more than the server now allows a job ({limit} MiB)", need >> 20);
            failed.extend(finish(shared, st, &id, Outcome::Failed(msg)));
            continue;
        }
        let used: u64 = st.running.keys().filter_map(|r| st.jobs.get(r)).map(|j| j.memory_estimate_bytes).sum();
        if !st.running.is_empty() && used + need > shared.config.memory_budget_bytes {
            break; // it waits, in order, until running jobs free enough memory
        }
        st.queue.pop_front();
        let Some(job) = st.jobs.get_mut(&id) else { continue };
        job.status = Status::Running;
        job.started_at = Some(now_ms());
        job.attempts += 1;
        job.error = None;
        let job = job.clone();
        let started = st.record(job);
        let cancel = Arc::new(AtomicBool::new(false));
        st.running.insert(id.clone(), Running { cancel: cancel.clone(), user_cancel: false });
        let s2 = shared.clone();
        let spawned =
            std::thread::Builder::new().name(format!("job-{id}")).spawn(move || run_job(&s2, started, cancel));
        match spawned {
            Ok(h) => st.threads.push(h),
            Err(e) => {
                st.running.remove(&id);
                failed.extend(finish(shared, st, &id, Outcome::Failed(format!("cannot start a thread: {e}"))));
            }
        }
    }
    failed
}

/// How a job run ended.
pub(crate) enum Outcome {
    Succeeded,
    Failed(String),
    /// Stopped by the cancel flag: canceled by the client, or interrupted by
    /// a shutdown (then it stays `running` on disk and resumes later).
    Stopped,
}

/// Runs `job`'s body over `host` until it ends or `cancel` is set: the one
/// place a job's kind chooses its body, for the embedded scheduler's
/// threads and a distributed worker's alike. A failure's message is what
/// clients read as the job's `error`.
pub(crate) fn run_body(host: &dyn JobHost, job: &Job, cancel: &AtomicBool) -> Outcome {
    let ended = match &job.spec {
        JobSpec::Train(spec) => train::run(host, job, spec, cancel),
        JobSpec::Video(spec) => video::run(host, job, spec, cancel),
        JobSpec::Poses(spec) => poses::run(host, job, spec, cancel),
        JobSpec::Bake(spec) => bake::run(host, job, spec, cancel),
    };
    match ended {
        Ok(outcome) => outcome,
        Err(JobError::Poses(PoseError::Cancelled)) => Outcome::Stopped,
        Err(e) => Outcome::Failed(e.to_string()),
    }
}

/// A job's thread: persists its start (`started`, handed out by `tick`),
/// runs it, records its end.
fn run_job(shared: &Arc<Shared>, started: Record, cancel: Arc<AtomicBool>) {
    shared.persist_logged(&started, "start");
    let job = started.job;
    let id = job.id.clone();
    tracing::info!(job = %id, kind = job.spec.name(), "job started");
    let host: &dyn JobHost = &**shared;
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run_body(host, &job, &cancel)))
        .unwrap_or_else(|_| Outcome::Failed("the job panicked (see the server log)".into()));
    // Recorded and its scene settled before the lock is released: a client
    // that sees the job's end also sees its scene's (and, before the thread
    // ends, since shutdown joins it and then closes the database).
    let mut st = shared.lock();
    if let Some(r) = finish(shared, &mut st, &id, outcome) {
        shared.persist_logged(&r, "end");
        settle_scene(shared, &r.job);
    }
    drop(st);
    shared.wake.notify_all();
}

/// After a pose-estimation job's final record: its scene, if the job did
/// not succeed, becomes `failed` (see `poses::settle`).
/// A video job's saved frames go with its end, too.
pub(super) fn settle_scene(shared: &Shared, job: &Job) {
    if let JobSpec::Poses(p) = &job.spec
        && job.status.is_final()
    {
        poses::settle(&shared.storage, &p.scene_id, Some(job));
    }
    if matches!(job.spec, JobSpec::Video(_)) && job.status.is_final() {
        let _ = std::fs::remove_dir_all(shared.storage.video_frames_dir(&job.id));
    }
}

/// Records the end of a run in memory, and returns the record to write:
/// the final state, or, when interrupted by a shutdown, the job queued again.
fn finish(shared: &Shared, st: &mut State, id: &str, outcome: Outcome) -> Option<Record> {
    let user_cancel = st.running.remove(id).is_some_and(|r| r.user_cancel);
    let job = st.jobs.get_mut(id)?;
    let status = match outcome {
        Outcome::Succeeded => Status::Succeeded,
        Outcome::Failed(e) => {
            job.error = Some(e);
            Status::Failed
        }
        Outcome::Stopped if user_cancel => Status::Canceled,
        Outcome::Stopped => {
            tracing::info!(job = %id, step = job.progress.step, "job interrupted by shutdown; it resumes at the next start");
            // Queued again on disk: a job found `running` at start-up was
            // cut short by the process dying, which counts as a crash.
            let mut interrupted = job.clone();
            interrupted.status = Status::Queued;
            return Some(st.record(interrupted));
        }
    };
    job.status = status;
    job.finished_at = Some(now_ms());
    shared.sweep_requested.store(true, Ordering::SeqCst);
    tracing::info!(job = %id, status = status.name(), error = job.error.as_deref().unwrap_or(""), "job finished");
    let job = job.clone();
    Some(st.record(job))
}
