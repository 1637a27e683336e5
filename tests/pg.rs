//! The PostgreSQL job queue (`radiance::backend::pg`) against a real server:
//! a throwaway cluster per test (`common::pg`). Migrations, claims under
//! concurrency, leases, crash counting, fencing, cancel and notifications,
//! and jobs that read back as the embedded queue shows them.

mod common;

use std::collections::HashSet;
use std::time::{Duration, Instant, SystemTime};

use common::pg::{Pg, bin_dir, with_database};
use radiance::backend::NewJob;
use radiance::backend::pg::migrate::{self, MIGRATIONS, Migration};
use radiance::backend::pg::{
    Admission, Database, Heartbeat, Lease, Listener, Notice, PgError, PgQueue, QueueConfig, RunEnd, RunState,
};
use radiance::datadir::{DataDir, new_id, now_ms, write_json};
use radiance::engine::dataset::{Dataset, LoadOptions};
use radiance::engine::models::config::ModelConfig;
use radiance::jobs::{
    Job, JobBudget, JobProgress, JobSpec, PosesSpec, SchedError, Scheduler, SchedulerConfig, Status, TrainSpec,
};
use radiance::records::{ModelInfo, SceneInfo, ScenePoses, SceneStatus};
use serde_json::Value;

/// A migrated database on a cluster of its own, and the queue over it.
/// Fields drop in order: the pool before the server.
struct Db {
    queue: PgQueue,
    db: Database,
    _pg: Pg,
}

async fn setup(max_queued: usize) -> Db {
    let pg = Pg::start().await;
    let db = Database::parse(&pg.database().await).unwrap();
    within(30, migrate::migrate(&db)).await.unwrap();
    let pool = db.pool(12).await.unwrap();
    Db { queue: PgQueue::new(pool, QueueConfig { max_queued }), db, _pg: pg }
}

impl Db {
    /// A connection of the test's own, for checks in SQL.
    async fn sql(&self) -> tokio_postgres::Client {
        self.db.connect().await.unwrap()
    }

    async fn ready_scene(&self) -> SceneInfo {
        let scene = ready_scene();
        assert!(self.queue.insert_scene(&scene, None).await.unwrap().is_none());
        scene
    }

    async fn enqueue(&self, spec: JobSpec, memory: u64) -> Job {
        self.queue.enqueue(new_job(None, spec, memory)).await.unwrap()
    }

    async fn job(&self, id: &str) -> Job {
        self.queue.get(id).await.unwrap().unwrap_or_else(|| panic!("no job {id}"))
    }

    /// `(attempt, worker, outcome)` of each run of a job, in order.
    async fn runs(&self, id: &str) -> Vec<(i32, String, Option<String>)> {
        let rows = self
            .sql()
            .await
            .query("SELECT attempt, worker_id, outcome FROM job_runs WHERE job_id = $1 ORDER BY attempt", &[&id])
            .await
            .unwrap();
        rows.iter().map(|r| (r.get(0), r.get(1), r.get(2))).collect()
    }

    /// Reclaims until something is taken back (bounded: leases here are short).
    async fn reclaim_one(&self) -> radiance::backend::pg::Reclaimed {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            let mut got = self.queue.reclaim().await.unwrap();
            if let Some(r) = got.pop() {
                assert!(got.is_empty(), "one expired lease at a time here");
                return r;
            }
            assert!(Instant::now() < deadline, "no lease expired within 10 s");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

/// Awaits `f` for at most `secs`, failing the test past that.
async fn within<F: std::future::Future>(secs: u64, f: F) -> F::Output {
    tokio::time::timeout(Duration::from_secs(secs), f).await.unwrap_or_else(|_| panic!("not done within {secs} s"))
}

/// The record of a small generated scene, as an upload stores it.
fn ready_scene() -> SceneInfo {
    let dir = tempfile::tempdir().unwrap();
    common::scene_dir(dir.path());
    let ds = Dataset::load(dir.path(), &LoadOptions::default()).unwrap();
    SceneInfo::from_dataset(&new_id("scn"), &ds, 1234, "data".into())
}

/// A scene uploaded as photos only, posed by job `job_id`.
fn posing_scene(job_id: &str) -> SceneInfo {
    let mut s = ready_scene();
    s.status = SceneStatus::Posing;
    s.poses = Some(ScenePoses { job_id: job_id.into(), source: "photos".into(), photos: 3, report: None });
    s
}

fn train(scene: &str) -> JobSpec {
    JobSpec::Train(Box::new(TrainSpec {
        scene_id: scene.into(),
        model: "nerf-tiny".into(),
        config: ModelConfig::preset("nerf-tiny").unwrap(),
        budget: JobBudget { steps: Some(10), ..JobBudget::default() },
        seed: 7,
        batch_rays: 64,
        masks: Default::default(),
        model_reason: None,
        bake: None,
        drop_transients: false,
    }))
}

fn poses(scene: &str) -> JobSpec {
    JobSpec::Poses(PosesSpec { scene_id: scene.into() })
}

fn new_job(id: Option<String>, spec: JobSpec, memory: u64) -> NewJob {
    NewJob { id, spec, model_id: None, memory_estimate: memory }
}

/// A worker with room for anything, alone.
fn idle(colmap: bool) -> Admission {
    Admission {
        max_concurrent: 4,
        max_job_memory_bytes: u64::MAX,
        memory_budget_bytes: u64::MAX,
        running_jobs: 0,
        running_bytes: 0,
        colmap,
    }
}

const LONG: Duration = Duration::from_secs(60);
const SHORT: Duration = Duration::from_millis(200);

fn model_of(job: &Job, scene: &SceneInfo, steps: u64) -> ModelInfo {
    ModelInfo {
        id: job.reserved_model_id(),
        scene_id: scene.id.clone(),
        job_id: job.id.clone(),
        model: "nerf-tiny".into(),
        model_reason: None,
        config: serde_json::to_value(ModelConfig::preset("nerf-tiny").unwrap()).unwrap(),
        steps,
        training_seconds: 1.5,
        test_psnr: None,
        test_views: 0,
        size_bytes: 4096,
        created_at: now_ms(),
        updated_at: now_ms(),
        complete: false,
        training_state: true,
        view: scene.view.clone(),
        poses: None,
        gaussians: None,
        transients: None,
        crop: None,
    }
}

/// A `job_runs` row as [`Db::runs`] reads it.
fn run(attempt: i32, worker: &str, outcome: &str) -> (i32, String, Option<String>) {
    (attempt, worker.into(), Some(outcome.into()))
}

/// A well-formed sha256 (64 hex digits) made of one byte.
fn sha(n: u8) -> String {
    format!("{n:02x}").repeat(32)
}

// ---- migrations ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn migrations_apply_once_when_four_nodes_start_together() {
    let pg = Pg::start().await;
    let db = Database::parse(&pg.database().await).unwrap();
    let starts: Vec<_> = (0..4)
        .map(|_| {
            let db = db.clone();
            tokio::spawn(async move { migrate::migrate(&db).await })
        })
        .collect();
    let mut applied = Vec::new();
    for s in starts {
        applied.push(within(30, s).await.unwrap().unwrap());
    }
    let all: Vec<i32> = MIGRATIONS.iter().map(|m| m.version).collect();
    assert_eq!(applied.iter().filter(|a| **a == all).count(), 1, "one node applied them: {applied:?}");
    assert_eq!(applied.iter().filter(|a| a.is_empty()).count(), 3, "the others found them applied: {applied:?}");
    let client = db.connect().await.unwrap();
    let rows =
        client.query("SELECT version, name, sha256 FROM radiance_migrations ORDER BY version", &[]).await.unwrap();
    let recorded: Vec<(i32, String, String)> = rows.iter().map(|r| (r.get(0), r.get(1), r.get(2))).collect();
    let ours: Vec<(i32, String, String)> = MIGRATIONS.iter().map(|m| (m.version, m.name.into(), m.sha256())).collect();
    assert_eq!(recorded, ours);
    assert_eq!(within(30, migrate::migrate(&db)).await.unwrap(), Vec::<i32>::new(), "a later start applies nothing");
    // The schema is there: the trigger's function, the tables the queue uses.
    let tables: i64 = client
        .query_one(
            "SELECT count(*) FROM information_schema.tables WHERE table_name IN \
             ('scenes','jobs','job_runs','models','videos','workers','maintenance')",
            &[],
        )
        .await
        .unwrap()
        .get(0);
    assert_eq!(tables, 7);
}

#[tokio::test]
async fn a_changed_or_newer_schema_is_refused() {
    let pg = Pg::start().await;
    let db = Database::parse(&pg.database().await).unwrap();
    within(30, migrate::migrate(&db)).await.unwrap();
    let client = db.connect().await.unwrap();
    let real = MIGRATIONS[0].sha256();
    client.execute("UPDATE radiance_migrations SET sha256 = $1 WHERE version = 1", &[&sha(0xab)]).await.unwrap();
    let e = within(30, migrate::migrate(&db)).await.expect_err("a changed migration").to_string();
    assert!(e.starts_with("migration 1 (init) was changed after it was applied"), "{e}");
    client.execute("UPDATE radiance_migrations SET sha256 = $1 WHERE version = 1", &[&real]).await.unwrap();
    let newer = MIGRATIONS.len() as i32 + 1;
    client
        .execute(
            "INSERT INTO radiance_migrations (version, name, sha256) VALUES ($1, 'future', $2)",
            &[&newer, &sha(0xcd)],
        )
        .await
        .unwrap();
    let e = within(30, migrate::migrate(&db)).await.expect_err("a newer schema").to_string();
    assert!(e.starts_with("the database schema is newer than this binary: upgrade it"), "{e}");
    assert!(e.contains(&format!("migration {newer} (future)")), "{e}");
    // Each refusal released the lock: once the database is as we know it, a start goes through.
    client.execute("DELETE FROM radiance_migrations WHERE version = $1", &[&newer]).await.unwrap();
    assert_eq!(within(30, migrate::migrate(&db)).await.unwrap(), Vec::<i32>::new());
}

#[tokio::test]
async fn a_failing_migration_leaves_the_ones_before_it_and_nothing_of_itself() {
    let pg = Pg::start().await;
    let db = Database::parse(&pg.database().await).unwrap();
    let good = Migration { version: 1, name: "good", sql: "CREATE TABLE first_table (x int);" };
    let bad = Migration {
        version: 2,
        name: "bad",
        sql: "CREATE TABLE second_table (x int); INSERT INTO second_table VALUES (1); SELECT no_such_function();",
    };
    let e = within(30, migrate::apply(&db, &[good, bad])).await.expect_err("migration 2 fails").to_string();
    assert!(e.starts_with("migration 2 (bad) failed: "), "{e}");
    assert!(e.contains("no_such_function"), "the server's reason: {e}");
    let client = db.connect().await.unwrap();
    let exists = |t: &'static str| {
        let client = &client;
        async move { client.query_one("SELECT to_regclass($1) IS NOT NULL", &[&t]).await.unwrap().get::<_, bool>(0) }
    };
    assert!(exists("first_table").await);
    assert!(!exists("second_table").await, "a failed migration leaves nothing");
    let versions: Vec<i32> =
        client.query("SELECT version FROM radiance_migrations", &[]).await.unwrap().iter().map(|r| r.get(0)).collect();
    assert_eq!(versions, [1]);
    // Fixed, it applies on the next start, alone.
    let fixed = Migration { version: 2, name: "bad", sql: "CREATE TABLE second_table (x int);" };
    assert_eq!(within(30, migrate::apply(&db, &[good, fixed])).await.unwrap(), [2]);
    let skipped = Migration { version: 3, ..good };
    assert!(matches!(migrate::apply(&db, &[good, skipped]).await, Err(PgError::Invalid(_))), "versions in order");
}

// ---- enqueue and claim ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn eight_workers_claim_two_thousand_jobs_each_exactly_once() {
    const JOBS: usize = 2000;
    let t = setup(JOBS).await;
    let scene = t.ready_scene().await;
    let enqueuers: Vec<_> = (0..4)
        .map(|_| {
            let (queue, scene) = (t.queue.clone(), scene.id.clone());
            tokio::spawn(async move {
                for _ in 0..JOBS / 4 {
                    queue.enqueue(new_job(None, train(&scene), 1)).await.unwrap();
                }
            })
        })
        .collect();
    for e in enqueuers {
        within(60, e).await.unwrap();
    }
    let full = t.queue.enqueue(new_job(None, train(&scene.id), 1)).await;
    assert!(matches!(full, Err(PgError::Refused(SchedError::QueueFull(n))) if n == JOBS), "{full:?}");
    let workers: Vec<_> = (0..8)
        .map(|w| {
            let queue = t.queue.clone();
            tokio::spawn(async move {
                let worker = format!("worker-{w}");
                let mut claimed = Vec::new();
                while let Some(c) = queue.claim(&worker, &idle(false), LONG).await.unwrap() {
                    assert_eq!((c.job.status, c.job.attempts, c.lease.attempt), (Status::Running, 1, 1));
                    assert_eq!(c.lease.worker, worker);
                    let done = queue.finish(&c.lease, RunEnd::Succeeded, &RunState::default()).await.unwrap();
                    assert_eq!(done.status, Status::Succeeded);
                    claimed.push((c.job.seq, c.job.id));
                }
                claimed
            })
        })
        .collect();
    let mut all = Vec::new();
    for w in workers {
        let claimed = within(120, w).await.unwrap();
        // A worker always takes the oldest job left: its claims follow seq.
        assert!(claimed.windows(2).all(|p| p[0].0 < p[1].0), "in seq order");
        all.extend(claimed);
    }
    let ids: HashSet<&String> = all.iter().map(|(_, id)| id).collect();
    assert_eq!((all.len(), ids.len()), (JOBS, JOBS), "every job claimed, none twice");
    let row = t
        .sql()
        .await
        .query_one(
            "SELECT count(*), count(DISTINCT job_id), count(*) FILTER (WHERE attempt = 1 AND outcome = 'succeeded'), \
             (SELECT count(*) FROM jobs WHERE status = 'succeeded' AND attempts = 1) FROM job_runs",
            &[],
        )
        .await
        .unwrap();
    let counts: [i64; 4] = [row.get(0), row.get(1), row.get(2), row.get(3)];
    assert_eq!(counts, [JOBS as i64; 4], "one run per job, each succeeded");
}

#[tokio::test]
async fn claims_follow_seq_and_an_interrupted_job_keeps_its_place() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let mut queued = Vec::new();
    for _ in 0..4 {
        queued.push(t.enqueue(train(&scene.id), 1).await);
    }
    assert!(queued.windows(2).all(|p| p[0].seq < p[1].seq), "seq follows enqueue order");
    let listed: Vec<String> = t.queue.list(Some(Status::Queued)).await.unwrap().into_iter().map(|j| j.id).collect();
    assert_eq!(listed, queued.iter().map(|j| j.id.clone()).collect::<Vec<_>>());
    let first = t.queue.claim("w", &idle(false), LONG).await.unwrap().unwrap();
    assert_eq!(first.job.id, queued[0].id);
    // The worker stops (a shutdown, no cancel asked): queued again, not a crash.
    let state = RunState { progress: JobProgress { step: 3, ..JobProgress::default() }, ..RunState::default() };
    let back = t.queue.finish(&first.lease, RunEnd::Stopped, &state).await.unwrap();
    assert_eq!((back.status, back.crashes, back.finished_at, back.progress.step), (Status::Queued, 0, None, 3));
    assert_eq!(t.runs(&queued[0].id).await, [run(1, "w", "interrupted")]);
    let mut order = Vec::new();
    while let Some(c) = t.queue.claim("w", &idle(false), LONG).await.unwrap() {
        order.push((c.job.id, c.job.attempts));
    }
    let expected: Vec<(String, u32)> =
        queued.iter().enumerate().map(|(i, j)| (j.id.clone(), if i == 0 { 2 } else { 1 })).collect();
    assert_eq!(order, expected, "the interrupted job first (its seq), then the rest in order");
}

#[tokio::test]
async fn workers_take_only_what_fits_them() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let big = t.enqueue(train(&scene.id), 600).await;
    let small = t.enqueue(train(&scene.id), 100).await;
    let limits = |running_jobs, running_bytes, max_job| Admission {
        max_concurrent: 2,
        max_job_memory_bytes: max_job,
        memory_budget_bytes: 1000,
        running_jobs,
        running_bytes,
        colmap: false,
    };
    // 500 of 1000 in use: the oldest (600) does not fit, and the small one behind it waits too.
    assert!(t.queue.claim("w", &limits(1, 500, 1000), LONG).await.unwrap().is_none(), "head-of-line waiting");
    assert!(t.queue.claim("w", &limits(2, 0, 1000), LONG).await.unwrap().is_none(), "at max_concurrent");
    // A worker whose jobs may be 200 at most leaves the big one for another.
    let c = t.queue.claim("small-worker", &limits(0, 0, 200), LONG).await.unwrap().unwrap();
    assert_eq!(c.job.id, small.id, "oversized jobs are skipped, not failed");
    assert!(t.queue.claim("small-worker", &limits(1, 100, 200), LONG).await.unwrap().is_none());
    assert_eq!(t.job(&big.id).await.status, Status::Queued);
    // Alone, a worker takes any job within its per-job limit, even past its budget.
    let alone = Admission { memory_budget_bytes: 10, ..limits(0, 0, 1000) };
    assert_eq!(t.queue.claim("big-worker", &alone, LONG).await.unwrap().unwrap().job.id, big.id);
    // Pose estimations go only to workers with COLMAP.
    let photos = posing_scene("job_later");
    t.queue.insert_scene(&photos, None).await.unwrap();
    let pose = t.enqueue(poses(&photos.id), 1).await;
    let after = t.enqueue(train(&scene.id), 1).await;
    let c = t.queue.claim("no-colmap", &idle(false), LONG).await.unwrap().unwrap();
    assert_eq!(c.job.id, after.id, "the poses job is passed over");
    assert!(t.queue.claim("no-colmap", &idle(false), LONG).await.unwrap().is_none());
    assert_eq!(t.queue.claim("colmap", &idle(true), LONG).await.unwrap().unwrap().job.id, pose.id);
}

#[tokio::test]
async fn enqueue_refuses_what_the_embedded_queue_refuses() {
    let t = setup(2).await;
    let scene = t.ready_scene().await;
    let refused = |r: Result<Job, PgError>| match r {
        Err(PgError::Refused(e)) => e,
        other => panic!("expected a refusal, got {other:?}"),
    };
    let missing = refused(t.queue.enqueue(new_job(None, train("scn_missing"), 1)).await);
    assert!(matches!(&missing, SchedError::SceneNotFound(s) if s == "scn_missing"), "{missing}");
    let photos = posing_scene("job_x");
    t.queue.insert_scene(&photos, None).await.unwrap();
    let posing = refused(t.queue.enqueue(new_job(None, train(&photos.id), 1)).await);
    assert_eq!(
        posing.to_string(),
        format!(
            "scene '{}' is posing (its poses are being estimated): only a ready scene can be trained on",
            photos.id
        )
    );
    let missing = refused(t.queue.enqueue(new_job(None, poses("scn_missing"), 1)).await);
    assert!(matches!(missing, SchedError::SceneNotFound(_)));
    let video = JobSpec::Video(serde_json::from_value(serde_json::json!({
        "frames": 4, "fps": 4, "width": 16, "height": 16, "elevation": 20.0, "radius": 3.0, "fov": 40.0, "format": "gif"
    }))
    .unwrap());
    let no_model = NewJob { model_id: Some("mdl_missing".into()), ..new_job(None, video, 1) };
    assert!(matches!(refused(t.queue.enqueue(no_model).await), SchedError::ModelNotFound(m) if m == "mdl_missing"));
    let id = new_id("job");
    t.queue.enqueue(new_job(Some(id.clone()), train(&scene.id), 1)).await.unwrap();
    let taken = refused(t.queue.enqueue(new_job(Some(id.clone()), train(&scene.id), 1)).await);
    assert_eq!(taken.to_string(), format!("job id '{id}' is taken"));
    t.enqueue(train(&scene.id), 1).await;
    assert!(matches!(refused(t.queue.enqueue(new_job(None, train(&scene.id), 1)).await), SchedError::QueueFull(2)));
    let bad = t.queue.enqueue(new_job(Some("Job/../x".into()), train(&scene.id), 1)).await;
    assert!(matches!(bad, Err(PgError::Invalid(_))), "{bad:?}");
    // Nothing refused was stored.
    assert_eq!(t.queue.list(None).await.unwrap().len(), 2);
}

// ---- leases ----

#[tokio::test]
async fn an_expired_lease_is_reclaimed_with_crash_counting() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let job = t.enqueue(train(&scene.id), 1).await;
    // Lost without saving: one crash, queued again.
    let first = t.queue.claim("w1", &idle(false), SHORT).await.unwrap().unwrap();
    // Seconds from now to the expiry: at most the lease, and not long past.
    let expiry = match first.lease.expires_at.duration_since(SystemTime::now()) {
        Ok(ahead) => ahead.as_secs_f64(),
        Err(behind) => -behind.duration().as_secs_f64(),
    };
    assert!((-5.0..=SHORT.as_secs_f64()).contains(&expiry), "expiry by the database clock, in {expiry} s");
    let r = t.reclaim_one().await;
    assert_eq!((r.job.id.as_str(), r.worker.as_str(), r.attempt), (job.id.as_str(), "w1", 1));
    assert_eq!((r.job.status, r.job.crashes, r.job.finished_at), (Status::Queued, 1, None));
    // Lost after saving a checkpoint: progress was made, so back to one crash.
    let second = t.queue.claim("w2", &idle(false), SHORT).await.unwrap().unwrap();
    assert_eq!((second.job.id.as_str(), second.lease.attempt), (job.id.as_str(), 2));
    let model = model_of(&second.job, &scene, 5);
    assert_eq!(t.queue.publish_model(&second.lease, &model, &sha(1)).await.unwrap(), None);
    let r = t.reclaim_one().await;
    assert_eq!((r.job.status, r.job.crashes, r.worker.as_str()), (Status::Queued, 1, "w2"));
    assert_eq!(r.job.model_id.as_deref(), Some(model.id.as_str()), "the saved model stays the job's");
    // Lost again without saving: the second crash in a row fails it.
    t.queue.claim("w3", &idle(false), SHORT).await.unwrap().unwrap();
    let r = t.reclaim_one().await;
    assert_eq!((r.job.status, r.job.crashes, r.attempt), (Status::Failed, 2, 3));
    assert!(r.job.finished_at.is_some());
    assert!(r.job.error.as_deref().unwrap().contains("died 2 times in a row"), "{:?}", r.job.error);
    assert_eq!(t.runs(&job.id).await, [run(1, "w1", "lost"), run(2, "w2", "lost"), run(3, "w3", "lost")]);
    assert!(t.queue.claim("w4", &idle(false), LONG).await.unwrap().is_none(), "a failed job is not run again");
    assert!(t.queue.reclaim().await.unwrap().is_empty());

    // A pose estimation failed by crashes fails its scene, saying why.
    let id = new_id("job");
    let photos = posing_scene(&id);
    t.queue.insert_scene(&photos, Some(new_job(Some(id.clone()), poses(&photos.id), 1))).await.unwrap();
    for _ in 0..2 {
        t.queue.claim("w5", &idle(true), SHORT).await.unwrap().unwrap();
        t.reclaim_one().await;
    }
    assert_eq!(t.job(&id).await.status, Status::Failed);
    let settled = t.queue.scene(&photos.id).await.unwrap().unwrap();
    assert_eq!(settled.status, SceneStatus::Failed);
    assert!(settled.error.as_deref().unwrap().starts_with("pose estimation failed: the worker running this job died"));
}

#[tokio::test]
async fn heartbeats_keep_a_lease_and_write_progress() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let job = t.enqueue(train(&scene.id), 1).await;
    // 3 s: a stall of this thread between a heartbeat and the reclaim after
    // it would have to outlast it.
    let c = t.queue.claim("w", &idle(false), Duration::from_secs(3)).await.unwrap().unwrap();
    let mut state = RunState::default();
    let sql = t.sql().await;
    let mut expiry = c.lease.expires_at;
    // Three lease lengths, renewed every 750 ms: never reclaimed, and each
    // heartbeat moves the expiry on (by the database clock).
    for step in 1..=12u64 {
        state.progress =
            JobProgress { step, total_steps: Some(100), loss: 0.5 / step as f64, ..JobProgress::default() };
        state.model_id = (step == 4).then(|| job.reserved_model_id());
        let hb = t.queue.heartbeat(&c.lease, &state).await.unwrap();
        assert_eq!(hb, Heartbeat::Renewed { cancel_requested: false });
        assert!(t.queue.reclaim().await.unwrap().is_empty(), "renewed at step {step}");
        let row = sql.query_one("SELECT lease_expires_at FROM jobs WHERE id = $1", &[&job.id]).await.unwrap();
        let renewed: SystemTime = row.get(0);
        assert!(renewed > expiry, "step {step}: the expiry did not move on from {expiry:?} ({renewed:?})");
        expiry = renewed;
        tokio::time::sleep(Duration::from_millis(750)).await;
    }
    let now = t.job(&job.id).await;
    assert_eq!(serde_json::to_value(&now.progress).unwrap(), serde_json::to_value(&state.progress).unwrap());
    assert_eq!(now.model_id, Some(job.reserved_model_id()), "set once, kept by heartbeats without one");
    // Heartbeats stop: the lease runs out and the job is taken back.
    let r = t.reclaim_one().await;
    assert_eq!((r.job.id, r.job.status, r.job.progress.step), (job.id, Status::Queued, 12));
}

#[tokio::test]
async fn a_stale_lease_can_neither_heartbeat_nor_finish_nor_publish() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let job = t.enqueue(train(&scene.id), 1).await;
    let old = t.queue.claim("w1", &idle(false), SHORT).await.unwrap().unwrap().lease;
    t.reclaim_one().await;
    let new = t.queue.claim("w2", &idle(false), LONG).await.unwrap().unwrap().lease;
    assert_ne!(old.token, new.token);
    let stale = RunState { progress: JobProgress { step: 999, ..JobProgress::default() }, ..RunState::default() };
    let forged = Lease { token: uuid::Uuid::now_v7(), ..new.clone() };
    for lease in [&old, &forged] {
        assert_eq!(t.queue.heartbeat(lease, &stale).await.unwrap(), Heartbeat::Lost);
        let e = t.queue.finish(lease, RunEnd::Succeeded, &stale).await.expect_err("fenced");
        assert!(matches!(&e, PgError::LeaseLost(id) if *id == job.id), "{e}");
        let e = t.queue.publish_model(lease, &model_of(&job, &scene, 1), &sha(9)).await.expect_err("fenced");
        assert!(matches!(e, PgError::LeaseLost(_)), "{e}");
    }
    let now = t.job(&job.id).await;
    assert_eq!((now.status, now.progress.step, now.model_id), (Status::Running, 0, None), "nothing stale written");
    let models: i64 = t.sql().await.query_one("SELECT count(*) FROM models", &[]).await.unwrap().get(0);
    assert_eq!(models, 0);
    // The holder of the lease still can.
    assert_eq!(
        t.queue.heartbeat(&new, &RunState::default()).await.unwrap(),
        Heartbeat::Renewed { cancel_requested: false }
    );
    let model = model_of(&job, &scene, 3);
    assert_eq!(t.queue.publish_model(&new, &model, &sha(2)).await.unwrap(), None);
    assert_eq!(t.queue.publish_model(&new, &model, &sha(3)).await.unwrap(), Some(sha(2)), "the object replaced");
    assert_eq!(t.queue.publish_model(&new, &model, &sha(3)).await.unwrap(), None, "the same object: nothing to delete");
    let done = t.queue.finish(&new, RunEnd::Succeeded, &RunState::default()).await.unwrap();
    assert_eq!((done.status, done.model_id), (Status::Succeeded, Some(model.id)));
    assert!(matches!(t.queue.finish(&new, RunEnd::Succeeded, &RunState::default()).await, Err(PgError::LeaseLost(_))));
    assert_eq!(t.runs(&job.id).await, [run(1, "w1", "lost"), run(2, "w2", "succeeded")]);
}

#[tokio::test]
async fn a_video_is_published_under_its_lease_and_a_models_checkpoint_reads_back() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let trainer = t.enqueue(train(&scene.id), 1).await;
    let lease = t.queue.claim("w1", &idle(false), LONG).await.unwrap().unwrap().lease;
    let model = model_of(&trainer, &scene, 3);
    assert_eq!(t.queue.checkpoint_sha256(&model.id).await.unwrap(), None, "no record yet");
    t.queue.publish_model(&lease, &model, &sha(4)).await.unwrap();
    assert_eq!(t.queue.checkpoint_sha256(&model.id).await.unwrap(), Some(sha(4)), "what a resumed job fetches");
    t.queue.finish(&lease, RunEnd::Succeeded, &RunState::default()).await.unwrap();

    let spec: JobSpec = serde_json::from_value(serde_json::json!({
        "kind": "video", "frames": 2, "fps": 2, "width": 16, "height": 16, "elevation": 20.0, "radius": 3.0,
        "fov": 40.0, "format": "gif"
    }))
    .unwrap();
    let new = NewJob { model_id: Some(model.id.clone()), ..new_job(None, spec, 1) };
    let job = t.queue.enqueue(new).await.unwrap();
    let old = t.queue.claim("w1", &idle(false), SHORT).await.unwrap().unwrap().lease;
    t.reclaim_one().await;
    let lease = t.queue.claim("w2", &idle(false), LONG).await.unwrap().unwrap().lease;
    let video = radiance::records::VideoInfo {
        id: job.reserved_video_id(),
        model_id: model.id.clone(),
        job_id: job.id.clone(),
        format: radiance::media::video::VideoFormat::Gif,
        frames: 2,
        fps: 2,
        width: 16,
        height: 16,
        size_bytes: 10,
        created_at: now_ms(),
    };
    // The worker that lost the job publishes nothing; a video record for
    // another job is refused.
    let e = t.queue.publish_video(&old, &video).await.expect_err("fenced");
    assert!(matches!(e, PgError::LeaseLost(_)), "{e}");
    assert_eq!(t.queue.video(&video.id).await.unwrap().map(|v| v.id), None);
    let other = radiance::records::VideoInfo { job_id: trainer.id.clone(), ..video.clone() };
    let e = t.queue.publish_video(&lease, &other).await.expect_err("not this job's video");
    assert!(e.to_string().contains("does not make video"), "{e}");
    // The holder does: the record and the job's video_id together.
    t.queue.publish_video(&lease, &video).await.unwrap();
    assert_eq!(t.queue.video(&video.id).await.unwrap().map(|v| v.size_bytes), Some(10));
    assert_eq!(t.job(&job.id).await.video_id, Some(video.id.clone()));
    let done = t.queue.finish(&lease, RunEnd::Succeeded, &RunState::default()).await.unwrap();
    assert_eq!((done.status, done.video_id), (Status::Succeeded, Some(video.id)));
}

// ---- cancel and notifications ----

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_reaches_queued_and_running_jobs() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let mut listener = Listener::start(&t.db).await.unwrap();
    // Queued: canceled at once, never claimed.
    let queued = t.enqueue(train(&scene.id), 1).await;
    let canceled = t.queue.cancel(&queued.id).await.unwrap();
    assert_eq!(canceled.status, Status::Canceled);
    assert!(canceled.finished_at.is_some());
    assert!(t.queue.claim("w", &idle(false), LONG).await.unwrap().is_none());
    let again = t.queue.cancel(&queued.id).await;
    assert!(matches!(again, Err(PgError::Refused(SchedError::AlreadyFinal { status: "canceled", .. }))), "{again:?}");
    let unknown = t.queue.cancel("job_missing").await;
    assert!(matches!(unknown, Err(PgError::Refused(SchedError::JobNotFound(_)))), "{unknown:?}");
    // Running: the answer is the running job; the worker hears it from NOTIFY and from its heartbeat.
    let running = t.enqueue(train(&scene.id), 1).await;
    let c = t.queue.claim("w", &idle(false), LONG).await.unwrap().unwrap();
    assert_eq!(c.job.id, running.id);
    let asked = t.queue.cancel(&running.id).await.unwrap();
    assert_eq!(asked.status, Status::Running);
    let notice = within(5, async {
        loop {
            match listener.recv().await.expect("the listener is connected") {
                Notice::Cancel(id) => break id,
                _ => continue,
            }
        }
    })
    .await;
    assert_eq!(notice, running.id);
    assert_eq!(
        t.queue.heartbeat(&c.lease, &RunState::default()).await.unwrap(),
        Heartbeat::Renewed { cancel_requested: true }
    );
    let ended = t.queue.finish(&c.lease, RunEnd::Stopped, &RunState::default()).await.unwrap();
    assert_eq!(ended.status, Status::Canceled);
    assert_eq!(t.runs(&running.id).await, [run(1, "w", "canceled")]);
    // A queued pose estimation canceled fails its scene, as the embedded queue does.
    let id = new_id("job");
    let photos = posing_scene(&id);
    t.queue.insert_scene(&photos, Some(new_job(Some(id.clone()), poses(&photos.id), 1))).await.unwrap();
    t.queue.cancel(&id).await.unwrap();
    let settled = t.queue.scene(&photos.id).await.unwrap().unwrap();
    assert_eq!((settled.status, settled.error.as_deref()), (SceneStatus::Failed, Some("pose estimation was canceled")));
}

#[tokio::test]
async fn notify_wakes_a_listener_on_enqueue() {
    let t = setup(100).await;
    let scene = t.ready_scene().await;
    let mut listener = Listener::start(&t.db).await.unwrap();
    let job = t.enqueue(train(&scene.id), 1).await;
    // Only the NOTIFY can deliver it (a listener has no fallback): within
    // 10 s of the commit, room for a starved test thread.
    let notice = within(10, listener.recv()).await.expect("the listener is connected");
    assert_eq!(notice, Notice::Queued(job.id.clone()));
    // A claim is a change; a job queued again wakes idle workers again.
    let c = t.queue.claim("w", &idle(false), LONG).await.unwrap().unwrap();
    assert_eq!(within(5, listener.recv()).await, Some(Notice::Changed(job.id.clone())));
    t.queue.finish(&c.lease, RunEnd::Stopped, &RunState::default()).await.unwrap();
    assert_eq!(within(5, listener.recv()).await, Some(Notice::Queued(job.id)));
}

// ---- the records clients see ----

/// A job's JSON without what differs between two stores by design: `seq`
/// (each counts its own) and the times (each reads its own clock).
fn comparable(job: &Job) -> Value {
    let mut v = serde_json::to_value(job).unwrap();
    for k in ["seq", "created_at", "started_at", "finished_at"] {
        v[k] = Value::Null;
    }
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_and_scenes_read_back_as_the_embedded_queue_shows_them() {
    let t = setup(100).await;
    let data = tempfile::tempdir().unwrap();
    let storage = DataDir::open(data.path()).unwrap();
    let scene = ready_scene();
    let job_id = new_id("job");
    let photos = posing_scene(&job_id);
    let store_scene = |s: &SceneInfo| {
        std::fs::create_dir_all(storage.scene_dir(&s.id)).unwrap();
        write_json(&storage.scene_record(&s.id), s).unwrap();
    };
    store_scene(&scene);
    let sched =
        Scheduler::open(storage.clone(), SchedulerConfig { run_jobs: false, ..SchedulerConfig::default() }).unwrap();
    // A training job.
    let id = new_id("job");
    let embedded = sched.enqueue_as(id.clone(), train(&scene.id), None, 123_456).unwrap();
    t.queue.insert_scene(&scene, None).await.unwrap();
    let pg = t.queue.enqueue(new_job(Some(id.clone()), train(&scene.id), 123_456)).await.unwrap();
    assert_eq!(comparable(&pg), comparable(&embedded));
    assert!(pg.created_at.abs_diff(now_ms()) < 60_000, "milliseconds by the database clock: {}", pg.created_at);
    let listed = t.queue.list(None).await.unwrap();
    assert_eq!(serde_json::to_value(&listed).unwrap(), serde_json::to_value([&pg]).unwrap());
    // A pose estimation stored with its scene, then canceled: the job and
    // the scene's record end as the embedded queue leaves them.
    // Stored as an upload stores it, then its job queued (a posing scene
    // without its job at start-up would be failed by `Scheduler::open`).
    store_scene(&photos);
    let embedded = sched
        .enqueue_as(job_id.clone(), poses(&photos.id), None, radiance::jobs::poses::MEMORY_ESTIMATE_BYTES)
        .unwrap();
    let new = new_job(Some(job_id.clone()), poses(&photos.id), radiance::jobs::poses::MEMORY_ESTIMATE_BYTES);
    let pg = t.queue.insert_scene(&photos, Some(new)).await.unwrap().unwrap();
    assert_eq!(comparable(&pg), comparable(&embedded));
    let scene_json = |s: &SceneInfo| serde_json::to_value(s).unwrap();
    assert_eq!(scene_json(&t.queue.scene(&photos.id).await.unwrap().unwrap()), scene_json(&photos));
    let embedded = sched.cancel(&job_id).unwrap();
    let pg = t.queue.cancel(&job_id).await.unwrap();
    assert_eq!(comparable(&pg), comparable(&embedded));
    assert_eq!(
        scene_json(&t.queue.scene(&photos.id).await.unwrap().unwrap()),
        scene_json(&storage.load_scene(&photos.id).unwrap().unwrap()),
        "the failed scene"
    );
    sched.shutdown();
    // Progress as a worker reports it reads back field for field, optional ones included.
    let c = t.queue.claim("w", &idle(false), LONG).await.unwrap().unwrap();
    let progress = JobProgress {
        step: 7,
        total_steps: Some(10),
        loss: 0.125,
        train_psnr: 18.5,
        elapsed: 2.25,
        eta: Some(1.5),
        test_psnr: Some(21.75),
        test_psnr_step: Some(5),
        rays_per_second: 1e5,
        diverged_steps: 1,
        rollbacks: 2,
        stage: Some("training".into()),
        gaussians: None,
    };
    let state = RunState { progress, model_id: Some(c.job.reserved_model_id()), video_id: None };
    t.queue.heartbeat(&c.lease, &state).await.unwrap();
    let read = t.job(&id).await;
    assert_eq!(serde_json::to_value(&read.progress).unwrap(), serde_json::to_value(&state.progress).unwrap());
    let json = serde_json::to_value(&read).unwrap();
    let back: Job = serde_json::from_value(json.clone()).unwrap();
    assert_eq!(serde_json::to_value(&back).unwrap(), json, "the JSON is a Job's");
}

// ---- the harness ----

#[test]
fn the_harness_fails_with_what_to_install_when_postgresql_is_missing() {
    let empty = tempfile::tempdir().unwrap();
    let e = bin_dir(None, Some(empty.path().as_os_str()), empty.path()).unwrap_err();
    assert!(e.contains("apt-get install -y --no-install-recommends postgresql"), "{e}");
    assert!(bin_dir(Some(empty.path().as_os_str()), None, empty.path()).unwrap_err().contains("RADIANCE_PG_BIN"));
    // Found in the highest version's folder.
    for v in ["9", "15", "13"] {
        let bin = empty.path().join(v).join("bin");
        std::fs::create_dir_all(&bin).unwrap();
        for f in ["initdb", "postgres"] {
            std::fs::write(bin.join(f), "").unwrap();
        }
    }
    assert_eq!(bin_dir(None, None, empty.path()).unwrap(), empty.path().join("15").join("bin"));
    assert_eq!(
        with_database("postgres://u:p@h:1/postgres?sslmode=disable", "t_1"),
        "postgres://u:p@h:1/t_1?sslmode=disable"
    );
    assert_eq!(with_database("postgres://u@h", "t_2"), "postgres://u@h/t_2");
}

// ---- measurement (run by hand: the "Scaling out" figures of docs/benchmarks.md) ----

/// Jobs claimed and finished per second through the queue's SQL, with 1, 2
/// and 4 claimers: the queue's ceiling, whatever the jobs do. Each count
/// runs on a fresh database of 5 000 queued jobs; every job must be claimed
/// exactly once. `cargo test --release --test pg claims_per_second --
/// --ignored --nocapture`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement, run by hand"]
async fn claims_per_second() {
    const JOBS: usize = 5000;
    let mut table = Vec::new();
    for claimers in [1usize, 2, 4] {
        let t = setup(JOBS).await;
        let scene = t.ready_scene().await;
        for _ in 0..JOBS {
            t.queue.enqueue(new_job(None, train(&scene.id), 1)).await.unwrap();
        }
        let started = Instant::now();
        let tasks: Vec<_> = (0..claimers)
            .map(|w| {
                let queue = t.queue.clone();
                tokio::spawn(async move {
                    let worker = format!("worker-{w}");
                    let mut n = 0usize;
                    while let Some(c) = queue.claim(&worker, &idle(false), LONG).await.unwrap() {
                        queue.finish(&c.lease, RunEnd::Succeeded, &RunState::default()).await.unwrap();
                        n += 1;
                    }
                    n
                })
            })
            .collect();
        let mut claimed = 0;
        for task in tasks {
            claimed += within(600, task).await.unwrap();
        }
        let secs = started.elapsed().as_secs_f64();
        assert_eq!(claimed, JOBS, "every job claimed once");
        let runs: i64 =
            t.sql().await.query_one("SELECT count(DISTINCT job_id) FROM job_runs", &[]).await.unwrap().get(0);
        assert_eq!(runs, JOBS as i64);
        table.push(format!("| {claimers} | {JOBS} | {secs:.2} s | {:.0} |", JOBS as f64 / secs));
    }
    println!("| claimers | jobs | time | claims/s (claim + finish) |\n| --- | --- | --- | --- |");
    for row in table {
        println!("{row}");
    }
}
