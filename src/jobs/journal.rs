//! The job database as the scheduler uses it: opened once at start-up, held
//! until shutdown, and written outside the scheduler's lock.
//!
//! Request handlers wait on the scheduler's lock (`get`, `list`, the SSE
//! poll), so no database write happens while it is held: a change is made
//! in memory under the lock, which also hands out a [`Record`] (a copy of
//! the job and a revision, numbered in the order the changes were made),
//! and the record is written after the lock is released. Two writes of one
//! job can then commit in either order (a job's start, written by its own
//! thread, and its end); the journal skips a record older than one already
//! committed for that job, so the newer state is what stays on disk.
//!
//! What is durable is what it was before: a job is answered as queued only
//! once its enqueued record has committed, a final state is written before
//! the job's thread ends (shutdown waits for it), and a crash between a
//! change and its write leaves the previous state, which start-up handles
//! as it always has (a job found queued or running runs again).

use std::collections::HashMap;
use std::io;
use std::sync::{Mutex, MutexGuard};

use super::Job;
use crate::datadir::{DataDir, JobDb};

/// A job record to write, and its revision (see the module comment).
pub(crate) struct Record {
    pub rev: u64,
    pub job: Job,
}

pub(crate) struct Journal {
    inner: Mutex<Inner>,
    /// Test hook: the next write waits here (see [`WriteGate`]).
    #[cfg(test)]
    pub(crate) gate: Mutex<Option<WriteGate>>,
}

struct Inner {
    /// `None` once closed at shutdown.
    db: Option<JobDb>,
    /// The revision last committed (or removed) per job id.
    committed: HashMap<String, u64>,
}

impl Journal {
    /// Opens the database and reads every record.
    pub fn open(storage: &DataDir) -> io::Result<(Self, Vec<Job>)> {
        let db = storage.open_jobs()?;
        let jobs = db.list()?;
        let inner = Inner { db: Some(db), committed: HashMap::new() };
        #[cfg(test)]
        let journal = Self { inner: Mutex::new(inner), gate: Mutex::new(None) };
        #[cfg(not(test))]
        let journal = Self { inner: Mutex::new(inner) };
        Ok((journal, jobs))
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes a record (one committed transaction), unless a newer one of
    /// the same job has committed already.
    pub fn put(&self, record: &Record) -> io::Result<()> {
        #[cfg(test)]
        self.wait_at_gate();
        let mut inner = self.lock();
        let id = record.job.id.as_str();
        if inner.committed.get(id).is_some_and(|&rev| rev > record.rev) {
            return Ok(());
        }
        inner.db()?.put(id, &record.job)?;
        inner.committed.insert(id.to_string(), record.rev);
        Ok(())
    }

    /// Removes a job's record; a record of it older than `rev` that comes
    /// later is skipped rather than bringing it back.
    pub fn remove(&self, id: &str, rev: u64) -> io::Result<bool> {
        let mut inner = self.lock();
        let removed = inner.db()?.remove(id)?;
        inner.committed.insert(id.to_string(), rev);
        Ok(removed)
    }

    /// Whether the database is open and answers a read.
    pub fn check(&self) -> io::Result<()> {
        self.lock().db()?.check()
    }

    /// Closes the database (at shutdown, after every job thread has ended),
    /// so the next start, or a tool, can open it.
    pub fn close(&self) {
        self.lock().db = None;
    }

    #[cfg(test)]
    fn wait_at_gate(&self) {
        let gate = self.gate.lock().unwrap_or_else(|e| e.into_inner()).take();
        if let Some(g) = gate {
            let _ = g.entered.send(());
            let _ = g.release.recv();
        }
    }
}

impl Inner {
    fn db(&self) -> io::Result<&JobDb> {
        self.db.as_ref().ok_or_else(|| io::Error::other("job database: closed (the scheduler has stopped)"))
    }
}

/// Holds the next write before it starts: it signals `entered`, then waits
/// for `release` (or for the sender to be dropped).
#[cfg(test)]
pub(crate) struct WriteGate {
    pub entered: std::sync::mpsc::Sender<()>,
    pub release: std::sync::mpsc::Receiver<()>,
}

#[cfg(test)]
pub(super) mod tests {
    use std::sync::mpsc;
    use std::time::Duration;

    use super::*;
    use crate::datadir::write_json;
    use crate::engine::front::ModelConfig;
    use crate::jobs::{JobBudget, JobSpec, Scheduler, SchedulerConfig, Status, TrainSpec};

    /// A data directory with the record of scene `scn_a` (enough to enqueue
    /// a training job on it) and a scheduler that does not start jobs.
    fn scheduler(dir: &std::path::Path) -> Scheduler {
        let storage = DataDir::open(dir).unwrap();
        let scene = crate::records::sample_scene("scn_a");
        std::fs::create_dir_all(storage.scene_dir("scn_a")).unwrap();
        write_json(&storage.scene_record("scn_a"), &scene).unwrap();
        Scheduler::open(storage, SchedulerConfig { run_jobs: false, ..Default::default() }).unwrap()
    }

    /// A one-step training job of the tiny classic model (also the
    /// retention tests').
    pub(in crate::jobs) fn train_spec() -> JobSpec {
        JobSpec::Train(Box::new(TrainSpec {
            scene_id: "scn_a".into(),
            model: "nerf-tiny".into(),
            config: ModelConfig::preset("nerf-tiny").unwrap(),
            budget: JobBudget { steps: Some(1), ..Default::default() },
            seed: 0,
            batch_rays: 64,
            masks: Default::default(),
            model_reason: None,
            bake: None,
            drop_transients: false,
        }))
    }

    /// Runs `f` on another thread and waits for it at most `secs`: a read
    /// that blocked on the scheduler's lock would fail the test, not hang it.
    fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> Option<T> {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || tx.send(f()));
        rx.recv_timeout(Duration::from_secs(secs)).ok()
    }

    #[test]
    fn requests_are_answered_while_a_job_record_is_being_written() {
        let dir = tempfile::tempdir().unwrap();
        let sched = scheduler(dir.path());
        let queued = sched.enqueue(train_spec(), None, 0).unwrap();
        let (entered_tx, entered) = mpsc::channel();
        let (release, release_rx) = mpsc::channel();
        *sched.shared.journal.gate.lock().unwrap() = Some(WriteGate { entered: entered_tx, release: release_rx });

        // The cancel's write of the canceled record is held mid-way...
        let s2 = sched.clone();
        let id = queued.id.clone();
        let cancel = std::thread::spawn(move || s2.cancel(&id));
        entered.recv_timeout(Duration::from_secs(30)).expect("the cancel reaches its write");
        // ... and reads (what GET /v1/jobs/{id}, the list and the SSE poll
        // do) and another enqueue still answer.
        let (s3, id) = (sched.clone(), queued.id.clone());
        let seen = within(30, move || (s3.get(&id), s3.list(None).len(), s3.enqueue(train_spec(), None, 0).is_ok()));
        let (job, listed, enqueued) = seen.expect("answered while the write is held");
        assert_eq!(job.map(|j| j.status), Some(Status::Canceled));
        assert_eq!((listed, enqueued), (1, true));

        release.send(()).unwrap();
        assert_eq!(cancel.join().unwrap().unwrap().status, Status::Canceled);
        sched.shutdown();
        let storage = DataDir::open(dir.path()).unwrap();
        let on_disk: Job = storage.get_job(&queued.id).unwrap().unwrap();
        assert_eq!(on_disk.status, Status::Canceled);
        assert_eq!(storage.open_jobs().unwrap().list::<Job>().unwrap().len(), 2);
    }

    #[test]
    fn an_older_record_never_replaces_a_newer_one() {
        let dir = tempfile::tempdir().unwrap();
        let sched = scheduler(dir.path());
        let job = sched.enqueue(train_spec(), None, 0).unwrap();
        sched.shutdown();
        let storage = DataDir::open(dir.path()).unwrap();
        let (journal, loaded) = Journal::open(&storage).unwrap();
        assert_eq!(loaded.len(), 1);
        let status_on_disk = |journal: &Journal| {
            let db = journal.lock();
            db.db().unwrap().get::<Job>(&job.id).unwrap().map(|j| j.status)
        };
        let with = |status| Job { status, ..job.clone() };
        // The end of a run (revision 3) commits before its start (2).
        journal.put(&Record { rev: 3, job: with(Status::Succeeded) }).unwrap();
        journal.put(&Record { rev: 2, job: with(Status::Running) }).unwrap();
        assert_eq!(status_on_disk(&journal), Some(Status::Succeeded));
        // Deleted (4): a late final record (3) does not bring it back.
        assert!(journal.remove(&job.id, 4).unwrap());
        journal.put(&Record { rev: 3, job: with(Status::Succeeded) }).unwrap();
        assert_eq!(status_on_disk(&journal), None);
        // Once closed, writes fail rather than vanish.
        journal.close();
        assert!(journal.put(&Record { rev: 5, job: with(Status::Failed) }).is_err());
    }
}
