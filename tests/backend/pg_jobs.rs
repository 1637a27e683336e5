//! What the PostgreSQL job store does beyond the contract, checked with the
//! test playing the worker through its `PgQueue` (no worker is built yet):
//! a running job's cancel reaches the worker's heartbeat, followers of a
//! job are woken by its NOTIFY well before the fallback (also once the
//! change feed has connected again after losing its connection), the records of
//! models and videos stay while jobs need them, and readiness needs the
//! schema and an answer within a second.

use std::time::{Duration, Instant};

use radiance::backend::pg::migrate;
use radiance::backend::pg::{
    Admission, CHANGE_FALLBACK, Claimed, Heartbeat, PgJobStore, PgStoreConfig, READY_WITHIN, RunEnd, RunState,
};
use radiance::backend::{JobStore, NewJob};
use radiance::datadir::{new_id, now_ms};
use radiance::engine::dataset::{Dataset, LoadOptions};
use radiance::engine::models::config::ModelConfig;
use radiance::jobs::{Job, JobProgress, SchedError, Status};
use radiance::records::{ModelInfo, SceneInfo};

use crate::contract::{new_job, train, video};
use crate::pg::open_pg;

const LEASE: Duration = Duration::from_secs(60);

/// A worker with room for anything.
fn idle() -> Admission {
    Admission {
        max_concurrent: 4,
        max_job_memory_bytes: u64::MAX,
        memory_budget_bytes: u64::MAX,
        running_jobs: 0,
        running_bytes: 0,
        colmap: true,
    }
}

/// A ready scene's record (its files are not needed here).
async fn ready_scene(store: &PgJobStore) -> SceneInfo {
    let dir = tempfile::tempdir().unwrap();
    crate::common::scene_dir(dir.path());
    let ds = Dataset::load(dir.path(), &LoadOptions::default()).unwrap();
    let scene = SceneInfo::from_dataset(&new_id("scn"), &ds, 1234, "data".into());
    assert!(store.insert_scene(scene.clone(), None).await.unwrap().is_none());
    scene
}

/// Enqueues a training job on `scene` and claims it as worker `w`.
async fn running_job(store: &PgJobStore, scene: &SceneInfo) -> Claimed {
    let job = store.enqueue(new_job(train(&scene.id, 100, 1), 1)).await.unwrap();
    let claimed = store.queue().claim("w", &idle(), LEASE).await.unwrap().expect("the queued job is claimed");
    assert_eq!(claimed.job.id, job.id);
    claimed
}

fn progress(step: u64) -> RunState {
    RunState { progress: JobProgress { step, total_steps: Some(100), ..JobProgress::default() }, ..RunState::default() }
}

fn model_of(job: &Job, scene: &SceneInfo) -> ModelInfo {
    ModelInfo {
        id: job.reserved_model_id(),
        scene_id: scene.id.clone(),
        job_id: job.id.clone(),
        model: "nerf-tiny".into(),
        model_reason: None,
        config: serde_json::to_value(ModelConfig::preset("nerf-tiny").unwrap()).unwrap(),
        steps: 10,
        training_seconds: 1.0,
        test_psnr: None,
        test_views: 0,
        size_bytes: 4096,
        created_at: now_ms(),
        updated_at: now_ms(),
        complete: true,
        training_state: true,
        view: scene.view.clone(),
        poses: None,
        gaussians: None,
        transients: None,
        crop: None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_jobs_cancel_reaches_its_workers_heartbeat() {
    let (store, _db, _pg) = open_pg(100).await;
    let scene = ready_scene(&store).await;
    let c = running_job(&store, &scene).await;
    assert_eq!(
        store.queue().heartbeat(&c.lease, &progress(3)).await.unwrap(),
        Heartbeat::Renewed { cancel_requested: false }
    );
    // Asked, answered while still running, and the job still reads running.
    let asked = store.cancel(&c.job.id).await.unwrap();
    assert_eq!((asked.status, asked.progress.step), (Status::Running, 3));
    assert_eq!(store.get_job(&c.job.id).await.unwrap().unwrap().status, Status::Running);
    match store.delete_job(&c.job.id).await {
        Err(SchedError::JobNotFinal { status, .. }) => assert_eq!(status, "running"),
        other => panic!("deleting a running job: {other:?}"),
    }
    // The worker's next heartbeat reads the request, and its stop is recorded as a cancel.
    assert_eq!(
        store.queue().heartbeat(&c.lease, &progress(4)).await.unwrap(),
        Heartbeat::Renewed { cancel_requested: true }
    );
    let ended = store.queue().finish(&c.lease, RunEnd::Stopped, &progress(4)).await.unwrap();
    assert_eq!(ended.status, Status::Canceled);
    let read = store.get_job(&c.job.id).await.unwrap().unwrap();
    assert_eq!((read.status, read.progress.step, read.error), (Status::Canceled, 4, None));
    assert!(read.finished_at.is_some_and(|t| t >= read.created_at));
    assert!(matches!(store.cancel(&c.job.id).await, Err(SchedError::AlreadyFinal { status: "canceled", .. })));
    let stats = store.stats().await.unwrap();
    assert_eq!((stats.queued, stats.by_status.get(&Status::Canceled).copied()), (0, Some(1)));
    assert!(store.counters().is_none(), "no jobs run in this process");
    // Finished: it can go, once.
    store.delete_job(&c.job.id).await.unwrap();
    assert!(store.get_job(&c.job.id).await.unwrap().is_none());
    assert!(matches!(store.delete_job(&c.job.id).await, Err(SchedError::JobNotFound(_))));
    store.shutdown().await;
}

/// A follower's fallback long enough that one woken within
/// [`NOTICE_WITHIN`] was woken by a notice, however slow the machine.
const LONG_FALLBACK: Duration = Duration::from_secs(30);
const NOTICE_WITHIN: Duration = Duration::from_secs(10);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn followers_wake_on_their_jobs_notify_well_before_the_fallback() {
    let (store, db, _pg) = open_pg(100).await;
    let scene = ready_scene(&store).await;
    let c = running_job(&store, &scene).await;
    // Followers on a second store of the database, with the long fallback.
    let config = PgStoreConfig { pool_size: 2, ..PgStoreConfig::default() };
    let follower = PgJobStore::open(&db, config).await.unwrap().with_change_fallback(LONG_FALLBACK);
    // Each heartbeat is a change of the job: its follower wakes at once.
    for step in 1..=5 {
        let hint = follower.job_changed(&c.job.id);
        store.queue().heartbeat(&c.lease, &progress(step)).await.unwrap();
        tokio::time::timeout(NOTICE_WITHIN, hint).await.unwrap_or_else(|_| panic!("no notice woke it (step {step})"));
        assert_eq!(follower.get_job(&c.job.id).await.unwrap().unwrap().progress.step, step);
    }
    // Another job's change does not wake it: still waiting once a notice
    // sent after that change has reached the store's followers.
    let mut hint = follower.job_changed(&c.job.id);
    let other = store.enqueue(new_job(train(&scene.id, 100, 2), 1)).await.unwrap();
    let later = follower.job_changed(&other.id);
    store.cancel(&other.id).await.unwrap();
    tokio::time::timeout(NOTICE_WITHIN, later).await.expect("the other job's notices arrive");
    assert!(tokio::time::timeout(Duration::ZERO, &mut hint).await.is_err(), "woken by another job's change");
    drop(hint);
    follower.shutdown().await;
    // With the default fallback, another job's change leaves it to the
    // fallback, after about a second (the upper bound only says bounded).
    let hint = store.job_changed(&c.job.id);
    let t0 = Instant::now();
    store.enqueue(new_job(train(&scene.id, 100, 3), 1)).await.unwrap();
    hint.await;
    let waited = t0.elapsed();
    assert!(
        waited >= CHANGE_FALLBACK - Duration::from_millis(50) && waited < CHANGE_FALLBACK + Duration::from_secs(10),
        "resolved after {waited:?}"
    );
    // After shutdown the hint still resolves (bounded), by the fallback.
    store.shutdown().await;
    let t0 = Instant::now();
    tokio::time::timeout(Duration::from_secs(15), store.job_changed(&c.job.id)).await.expect("bounded");
    assert!(t0.elapsed() >= CHANGE_FALLBACK - Duration::from_millis(50));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_change_feed_listens_again_after_its_connection_is_killed() {
    let (store, db, _pg) = open_pg(100).await;
    let scene = ready_scene(&store).await;
    let c = running_job(&store, &scene).await;
    let sql = db.connect().await.unwrap();
    let listening = "SELECT pid FROM pg_stat_activity WHERE query LIKE 'LISTEN %' AND pid <> pg_backend_pid()";
    let pids: Vec<i32> = sql.query(listening, &[]).await.unwrap().iter().map(|r| r.get(0)).collect();
    assert_eq!(pids.len(), 1, "one listener per store: {pids:?}");
    sql.execute("SELECT pg_terminate_backend($1)", &[&pids[0]]).await.unwrap();
    let killed = Instant::now();
    while sql.query_opt("SELECT 1 FROM pg_stat_activity WHERE pid = $1", &[&pids[0]]).await.unwrap().is_some() {
        assert!(killed.elapsed() < Duration::from_secs(5), "the listener's backend did not end");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Cut off, a follower still wakes, by the fallback; once the feed has
    // connected again (after about a second), notices wake it at once.
    let t0 = Instant::now();
    let mut step = 0;
    let woken_by_notice = loop {
        assert!(t0.elapsed() < Duration::from_secs(10), "no notice woke a follower within 10 s");
        step += 1;
        let hint = store.job_changed(&c.job.id);
        let t = Instant::now();
        store.queue().heartbeat(&c.lease, &progress(step)).await.unwrap();
        tokio::time::timeout(Duration::from_secs(3), hint).await.expect("the hint is bounded");
        if t.elapsed() < Duration::from_millis(300) {
            break t0.elapsed();
        }
    };
    assert!(woken_by_notice >= Duration::from_millis(900), "the killed listener cannot have woken it");
    let again: Vec<i32> = sql.query(listening, &[]).await.unwrap().iter().map(|r| r.get(0)).collect();
    assert!(again.len() == 1 && again != pids, "a new listener: {again:?} (was {pids:?})");
    store.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn models_and_videos_stay_while_jobs_need_them() {
    let (store, db, _pg) = open_pg(100).await;
    let scene = ready_scene(&store).await;
    let c = running_job(&store, &scene).await;
    let model = model_of(&c.job, &scene);
    store.queue().publish_model(&c.lease, &model, &"ab".repeat(32)).await.unwrap();
    let stored = store.get_model(&model.id).await.unwrap().expect("published");
    assert_eq!(serde_json::to_value(&stored).unwrap(), serde_json::to_value(&model).unwrap());
    let listed = store.list_models().await.unwrap();
    assert_eq!(listed.iter().map(|m| m.id.as_str()).collect::<Vec<_>>(), [model.id.as_str()]);
    // The training job writes it and trains on the scene.
    match store.delete_model(&model.id).await {
        Err(SchedError::ModelInUse { model: m, job, status }) => {
            assert_eq!((m.as_str(), job.as_str(), status), (model.id.as_str(), c.job.id.as_str(), "running"))
        }
        other => panic!("deleting a model being trained: {other:?}"),
    }
    assert!(matches!(store.delete_scene(&scene.id).await, Err(SchedError::SceneInUse { status: "running", .. })));
    store.queue().finish(&c.lease, RunEnd::Succeeded, &progress(10)).await.unwrap();

    // A queued video job renders it; its video record (as a worker will
    // publish it: no publish is built yet) cannot go before the job ends.
    let render = NewJob { model_id: Some(model.id.clone()), ..new_job(video(), 1) };
    let vjob = store.enqueue(render).await.unwrap();
    assert!(matches!(store.delete_model(&model.id).await, Err(SchedError::ModelInUse { status: "queued", .. })));
    let video_id = new_id("vid");
    let record = serde_json::json!({
        "id": video_id, "model_id": model.id, "job_id": vjob.id, "format": "gif", "frames": 1, "fps": 1,
        "width": 16, "height": 16, "size_bytes": 99, "created_at": now_ms(),
    });
    let sql = db.connect().await.unwrap();
    sql.execute(
        "INSERT INTO videos (id, model_id, job_id, created_at, record) VALUES ($1, $2, $3, $4, $5)",
        &[&video_id, &model.id, &vjob.id, &(now_ms() as i64), &record],
    )
    .await
    .unwrap();
    let listed = store.list_videos().await.unwrap();
    assert_eq!(serde_json::to_value(&listed).unwrap(), serde_json::json!([record]));
    assert_eq!(serde_json::to_value(store.get_video(&video_id).await.unwrap()).unwrap(), record);
    match store.delete_video(&video_id).await {
        Err(SchedError::VideoInUse { video, job, status }) => {
            assert_eq!((video.as_str(), job.as_str(), status), (video_id.as_str(), vjob.id.as_str(), "queued"))
        }
        other => panic!("deleting a video whose job is queued: {other:?}"),
    }
    // Once the job has ended, each goes once; the scene was free since the training ended.
    store.cancel(&vjob.id).await.unwrap();
    store.delete_video(&video_id).await.unwrap();
    assert!(store.get_video(&video_id).await.unwrap().is_none());
    assert!(matches!(store.delete_video(&video_id).await, Err(SchedError::VideoNotFound(_))));
    store.delete_model(&model.id).await.unwrap();
    assert!(store.get_model(&model.id).await.unwrap().is_none() && store.list_models().await.unwrap().is_empty());
    assert!(matches!(store.delete_model(&model.id).await, Err(SchedError::ModelNotFound(_))));
    store.delete_scene(&scene.id).await.unwrap();
    // A record that does not read back is an error naming it, not a panic.
    let bad = new_id("mdl");
    sql.execute(
        "INSERT INTO models (id, scene_id, job_id, created_at, updated_at, checkpoint_sha256, record) \
         VALUES ($1, 's', 'j', 0, 0, '', '{\"id\": 1}')",
        &[&bad],
    )
    .await
    .unwrap();
    let e = store.get_model(&bad).await.unwrap_err().to_string();
    assert!(e.starts_with(&format!("the record '{bad}' in the database cannot be read")), "{e}");
    store.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ready_needs_the_schema_and_an_answer_within_a_second() {
    let (store, db, pg) = open_pg(100).await;
    store.ready().await.unwrap();
    // Without the newest migration, the schema is not this binary's.
    let newest = migrate::newest_version();
    let sql = db.connect().await.unwrap();
    sql.execute("DELETE FROM radiance_migrations WHERE version = $1", &[&newest]).await.unwrap();
    let e = store.ready().await.unwrap_err().to_string();
    let needs = format!("the database schema is at migration {}; this binary needs migration {newest}", newest - 1);
    assert_eq!(e, needs);
    drop(sql);
    // The server gone: not ready, and said within about a second
    // (READY_WITHIN, and 5 s more for a starved test thread).
    drop(pg);
    let t0 = Instant::now();
    let e = store.ready().await.unwrap_err();
    assert!(t0.elapsed() < READY_WITHIN + Duration::from_secs(5), "answered after {:?}: {e}", t0.elapsed());
    store.shutdown().await;
    let e = store.ready().await.unwrap_err().to_string();
    assert_eq!(e, "the PostgreSQL job store was shut down");
}
