//! The checks every pair of stores passes. Each takes an [`Open`]er that
//! makes a pair over fresh, empty state with the given [`Settings`], and
//! drives it only through the `JobStore` and `ArtifactStore` traits, as the
//! API does:
//!
//! - a scene appears with its files, or not at all (no record without its
//!   data), and a photo-only upload is stored with its job or not at all;
//! - jobs keep their enqueue order and read back exactly as enqueued;
//! - refusals name what is missing, not ready, in use, or full;
//! - cancel of queued and running jobs; a running one keeps its model;
//! - deletes: once, then "not found";
//! - videos and checkpoints are readable once their records are listed;
//! - readiness, until shut down.

use std::future::Future;
use std::path::Path;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, Instant};

use radiance::backend::{ArtifactStore, JobStore, NewJob};
use radiance::datadir::{ScenePart, new_id, now_ms, tree_bytes, valid_id};
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::dataset::{Dataset, LoadOptions};
use radiance::engine::models::config::ModelConfig;
use radiance::engine::train::persist;
use radiance::jobs::{Job, JobBudget, JobProgress, JobSpec, PosesSpec, SchedError, Status, TrainSpec, VideoSpec};
use radiance::media::video::VideoFormat;
use radiance::records::{CropBox, SceneInfo, ScenePoses, SceneStatus, SplitCounts};
use serde_json::Value;

/// What a check needs of a fresh pair.
pub struct Settings {
    /// Queued jobs beyond this are refused.
    pub max_queued: usize,
    /// Whether jobs run (off: they stay queued).
    pub run_jobs: bool,
}

impl Default for Settings {
    fn default() -> Self {
        Self { max_queued: 100, run_jobs: false }
    }
}

/// A pair of stores, and what must live as long as they do (a temporary
/// folder, a database server).
pub struct Stores {
    pub jobs: Arc<dyn JobStore>,
    pub artifacts: Arc<dyn ArtifactStore>,
    pub _keep: Box<dyn std::any::Any + Send>,
}

pub type Opening = Pin<Box<dyn Future<Output = Stores> + Send>>;

/// Opens a pair over fresh, empty state. Training jobs must save a
/// checkpoint within about a second of training.
pub type Open = fn(Settings) -> Opening;

/// One `#[tokio::test]` per check, on the pair `$open` opens.
macro_rules! contract_tests {
    ($open:path) => {
        contract_tests!(
            $open;
            scenes_appear_with_their_files_or_not_at_all,
            jobs_keep_their_order_and_read_back_as_enqueued,
            refusals_name_what_is_missing_or_not_ready,
            a_full_queue_refuses_and_a_photo_upload_comes_with_its_job_or_not_at_all,
            queued_jobs_cancel_at_once_and_deletes_happen_once,
            running_jobs_stop_on_cancel_and_keep_their_model,
            ready_until_shut_down,
        );
    };
    ($open:path; $($check:ident),* $(,)?) => {
        $(
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            async fn $check() {
                crate::contract::$check($open).await
            }
        )*
    };
}

// ---- helpers ----

/// The ball scene (8 views of 16x16) staged, checked and stored as an
/// upload is; checks that nothing of it is visible before its record is
/// inserted.
async fn add_ball_scene(st: &Stores) -> SceneInfo {
    let id = new_id("scn");
    let data = st.artifacts.staging_dir(&id).join(ScenePart::Data.dir_name());
    let (id2, data2) = (id.clone(), data.clone());
    let info = tokio::task::spawn_blocking(move || {
        BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data2).unwrap();
        let ds = Dataset::load(&data2, &LoadOptions::default()).unwrap();
        SceneInfo::from_dataset(&id2, &ds, tree_bytes(&data2).unwrap(), "data".into())
    })
    .await
    .unwrap();
    st.artifacts.put_scene_files(&id, ScenePart::Data, &data).await.unwrap();
    assert!(st.jobs.get_scene(&id).await.unwrap().is_none(), "visible before its record");
    assert!(!listed_scenes(st).await.contains(&id));
    assert!(st.jobs.insert_scene(info.clone(), None).await.unwrap().is_none());
    info
}

/// A photo-only upload: its photos staged as `upload/`, its record naming
/// its pose estimation job, stored together. Returns the record and what
/// the insert answered.
async fn add_posing_scene(st: &Stores) -> (SceneInfo, Result<Option<Job>, SchedError>) {
    let id = new_id("scn");
    let job_id = new_id("job");
    let data = st.artifacts.staging_dir(&id).join(ScenePart::Data.dir_name());
    std::fs::create_dir_all(&data).unwrap();
    for k in 0..3 {
        std::fs::write(data.join(format!("IMG_{k}.jpg")), b"not decoded by the stores").unwrap();
    }
    let poses = ScenePoses { job_id: job_id.clone(), source: "photos".into(), photos: 3, report: None };
    let info = SceneInfo {
        status: SceneStatus::Posing,
        poses: Some(poses),
        images: SplitCounts::default(),
        format: radiance::engine::dataset::DatasetFormat::Colmap,
        ..sample_view_scene(&id)
    };
    st.artifacts.put_scene_files(&id, ScenePart::Upload, &data).await.unwrap();
    let job = NewJob {
        id: Some(job_id),
        spec: JobSpec::Poses(PosesSpec { scene_id: id.clone() }),
        model_id: None,
        memory_estimate: 1 << 30,
    };
    let answer = st.jobs.insert_scene(info.clone(), Some(job)).await;
    (info, answer)
}

/// A scene record with made-up view defaults (the posing scene's).
pub fn sample_view_scene(id: &str) -> SceneInfo {
    let view = serde_json::json!({
        "width": 16, "height": 16, "fov": 40.0, "centre": [0.0, 0.0, 0.0], "up": [0.0, 0.0, 1.0],
        "radius": 4.0, "far": 6.0,
    });
    SceneInfo {
        id: id.into(),
        name: None,
        status: SceneStatus::Ready,
        error: None,
        poses: None,
        format: radiance::engine::dataset::DatasetFormat::Blender,
        images: SplitCounts { train: 1, val: 0, test: 0 },
        resolution: [16, 16],
        warnings: Vec::new(),
        created_at: now_ms(),
        size_bytes: 0,
        root: "data".into(),
        mask_folder: None,
        kind: None,
        view: serde_json::from_value(view).unwrap(),
    }
}

async fn listed_scenes(st: &Stores) -> Vec<String> {
    st.jobs.list_scenes().await.unwrap().into_iter().map(|s| s.id).collect()
}

async fn listed_jobs(st: &Stores, status: Option<Status>) -> Vec<String> {
    st.jobs.list_jobs(status).await.unwrap().into_iter().map(|j| j.id).collect()
}

/// A nerf-tiny training job of `steps` steps on `scene`.
pub fn train(scene: &str, steps: u64, seed: u64) -> JobSpec {
    JobSpec::Train(Box::new(TrainSpec {
        scene_id: scene.into(),
        model: "nerf-tiny".into(),
        config: ModelConfig::preset("nerf-tiny").unwrap(),
        budget: JobBudget { steps: Some(steps), ..Default::default() },
        seed,
        batch_rays: 64,
        masks: Default::default(),
        model_reason: None,
        bake: None,
        drop_transients: false,
    }))
}

/// A one-frame 16x16 GIF orbit.
pub fn video() -> JobSpec {
    JobSpec::Video(VideoSpec {
        frames: 1,
        fps: 1,
        width: 16,
        height: 16,
        elevation: 30.0,
        radius: 4.0,
        fov: 40.0,
        format: VideoFormat::Gif,
        path: None,
        appearance: Default::default(),
    })
}

pub fn new_job(spec: JobSpec, memory_estimate: u64) -> NewJob {
    NewJob { id: None, spec, model_id: None, memory_estimate }
}

/// The queued record a store must answer for `new`, given the id, order
/// and time it assigned.
fn queued_as_enqueued(new: &NewJob, got: &Job) -> Value {
    let job = Job {
        id: got.id.clone(),
        seq: got.seq,
        status: Status::Queued,
        spec: new.spec.clone(),
        created_at: got.created_at,
        started_at: None,
        finished_at: None,
        error: None,
        model_id: new.model_id.clone(),
        video_id: None,
        progress: JobProgress::default(),
        attempts: 0,
        memory_estimate_bytes: new.memory_estimate,
        crashes: 0,
    };
    serde_json::to_value(job).unwrap()
}

fn json(job: &Job) -> Value {
    serde_json::to_value(job).unwrap()
}

/// Follows a job as its events do (read, then wait for the store's hint)
/// until `done` holds; fails after `secs`.
async fn follow(st: &Stores, id: &str, secs: f64, done: impl Fn(&Job) -> bool) -> Job {
    let t0 = Instant::now();
    loop {
        let job = st.jobs.get_job(id).await.unwrap().expect("the job exists");
        if done(&job) {
            return job;
        }
        assert!(t0.elapsed().as_secs_f64() < secs, "timed out following {}", json(&job));
        tokio::time::timeout(Duration::from_secs(5), st.jobs.job_changed(id)).await.expect("the hint resolves");
    }
}

/// Loads a checkpoint the artifact store hands out, off the async threads.
async fn load_checkpoint(path: &Path) -> Result<u64, String> {
    let path = path.to_path_buf();
    let loaded = tokio::task::spawn_blocking(move || persist::load(&path)).await.unwrap();
    loaded.map(|r| r.state.step).map_err(|e| e.to_string())
}

// ---- the checks ----

pub async fn scenes_appear_with_their_files_or_not_at_all(open: Open) {
    let st = open(Settings::default()).await;
    let info = add_ball_scene(&st).await;
    let got = st.jobs.get_scene(&info.id).await.unwrap().expect("stored");
    assert_eq!(serde_json::to_value(&got).unwrap(), serde_json::to_value(&info).unwrap());
    assert_eq!(listed_scenes(&st).await, vec![info.id.clone()]);
    // Its files come with it: the dataset loads where the record says.
    let files = st.artifacts.scene_files(&info, ScenePart::Data).await.unwrap();
    let root = files.path.join(&info.root);
    let ds = tokio::task::spawn_blocking(move || Dataset::load(&root, &LoadOptions::default())).await.unwrap();
    assert_eq!(ds.unwrap().train.len(), info.images.train);
    assert!(st.artifacts.usage().await.unwrap().scenes > 0);

    // A job stored with a scene must be that scene's pose estimation.
    let other = add_ball_scene(&st).await;
    let id = new_id("scn");
    let data = st.artifacts.staging_dir(&id).join(ScenePart::Data.dir_name());
    std::fs::create_dir_all(&data).unwrap();
    std::fs::write(data.join("x.jpg"), b"x").unwrap();
    st.artifacts.put_scene_files(&id, ScenePart::Upload, &data).await.unwrap();
    let wrong = NewJob {
        id: Some(new_id("job")),
        spec: JobSpec::Poses(PosesSpec { scene_id: other.id.clone() }),
        model_id: None,
        memory_estimate: 0,
    };
    let refused =
        st.jobs.insert_scene(SceneInfo { status: SceneStatus::Posing, ..sample_view_scene(&id) }, Some(wrong));
    assert!(refused.await.is_err());
    assert!(st.jobs.get_scene(&id).await.unwrap().is_none());
    assert!(listed_jobs(&st, None).await.is_empty(), "no job without its scene");
    // Bad ids are refused, not acted on.
    assert!(st.artifacts.put_scene_files("../x", ScenePart::Data, &data).await.is_err());
    assert!(st.jobs.insert_scene(sample_view_scene("../x"), None).await.is_err());

    // A scene goes once.
    st.jobs.delete_scene(&info.id).await.unwrap();
    assert!(st.jobs.get_scene(&info.id).await.unwrap().is_none());
    assert_eq!(listed_scenes(&st).await, vec![other.id.clone()]);
    match st.jobs.delete_scene(&info.id).await {
        Err(SchedError::SceneNotFound(id)) => assert_eq!(id, info.id),
        other => panic!("a second delete: {other:?}"),
    }
    st.jobs.shutdown().await;
}

pub async fn jobs_keep_their_order_and_read_back_as_enqueued(open: Open) {
    let st = open(Settings::default()).await;
    let scene = add_ball_scene(&st).await;
    let (before, mut enqueued) = (now_ms(), Vec::new());
    for k in 1..=4u64 {
        let new = new_job(train(&scene.id, 10 * k, k), k << 20);
        let job = st.jobs.enqueue(new.clone()).await.unwrap();
        assert_eq!(json(&job), queued_as_enqueued(&new, &job));
        assert!(valid_id(&job.id) && job.id.starts_with("job_"), "{}", job.id);
        assert!((before..=now_ms()).contains(&job.created_at), "{}", job.created_at);
        enqueued.push(job);
    }
    assert!(enqueued.windows(2).all(|w| w[0].seq < w[1].seq), "seq follows enqueue order");
    let ids: Vec<String> = enqueued.iter().map(|j| j.id.clone()).collect();
    assert_eq!(listed_jobs(&st, None).await, ids);
    assert_eq!(listed_jobs(&st, Some(Status::Queued)).await, ids);
    assert!(listed_jobs(&st, Some(Status::Running)).await.is_empty());
    // Read back, one by one and in the list, exactly as answered.
    let listed = st.jobs.list_jobs(None).await.unwrap();
    for (job, in_list) in enqueued.iter().zip(&listed) {
        assert_eq!(json(&st.jobs.get_job(&job.id).await.unwrap().unwrap()), json(job));
        assert_eq!(json(in_list), json(job));
    }
    assert!(st.jobs.get_job(&new_id("job")).await.unwrap().is_none());
    let stats = st.jobs.stats().await.unwrap();
    assert_eq!((stats.queued, stats.by_status.get(&Status::Queued).copied()), (4, Some(4)));
    assert_eq!(stats.by_status.get(&Status::Running).copied().unwrap_or(0), 0);

    // An id chosen by the caller is kept; taken or malformed, it is refused.
    let chosen = new_id("job");
    let new = NewJob { id: Some(chosen.clone()), ..new_job(train(&scene.id, 1, 9), 0) };
    let job = st.jobs.enqueue(new.clone()).await.unwrap();
    assert_eq!(json(&job), queued_as_enqueued(&new, &job));
    assert_eq!(job.id, chosen);
    assert!(job.seq > enqueued[3].seq);
    assert!(st.jobs.enqueue(new).await.is_err(), "a taken id");
    let bad = NewJob { id: Some("job_../x".into()), ..new_job(train(&scene.id, 1, 9), 0) };
    assert!(st.jobs.enqueue(bad).await.is_err(), "a malformed id");
    assert_eq!(listed_jobs(&st, None).await.len(), 5);
    st.jobs.shutdown().await;
}

pub async fn refusals_name_what_is_missing_or_not_ready(open: Open) {
    let st = open(Settings::default()).await;
    let missing = new_id("scn");
    match st.jobs.enqueue(new_job(train(&missing, 1, 0), 0)).await {
        Err(SchedError::SceneNotFound(id)) => assert_eq!(id, missing),
        other => panic!("training on a missing scene: {other:?}"),
    }
    let poses = JobSpec::Poses(PosesSpec { scene_id: missing.clone() });
    assert!(matches!(st.jobs.enqueue(new_job(poses, 0)).await, Err(SchedError::SceneNotFound(_))));
    let model = new_id("mdl");
    let render = NewJob { model_id: Some(model.clone()), ..new_job(video(), 0) };
    match st.jobs.enqueue(render).await {
        Err(SchedError::ModelNotFound(id)) => assert_eq!(id, model),
        other => panic!("a video of a missing model: {other:?}"),
    }
    // A scene still being posed cannot be trained on, and says why.
    let (posing, job) = add_posing_scene(&st).await;
    let job = job.unwrap().expect("its job is queued with it");
    assert_eq!((job.status, job.spec.name()), (Status::Queued, "poses"));
    assert_eq!(Some(job.id.as_str()), posing.poses.as_ref().map(|p| p.job_id.as_str()));
    match st.jobs.enqueue(new_job(train(&posing.id, 1, 0), 0)).await {
        Err(SchedError::SceneNotReady { scene, status, reason }) => {
            assert_eq!((scene.as_str(), status), (posing.id.as_str(), "posing"));
            assert!(reason.is_some_and(|r| r.contains("poses are being estimated")));
        }
        other => panic!("training on a posing scene: {other:?}"),
    }
    assert_eq!(listed_jobs(&st, None).await, vec![job.id]);
    st.jobs.shutdown().await;
}

pub async fn a_full_queue_refuses_and_a_photo_upload_comes_with_its_job_or_not_at_all(open: Open) {
    let st = open(Settings { max_queued: 2, ..Settings::default() }).await;
    let scene = add_ball_scene(&st).await;
    let first = st.jobs.enqueue(new_job(train(&scene.id, 1, 0), 0)).await.unwrap();
    st.jobs.enqueue(new_job(train(&scene.id, 1, 1), 0)).await.unwrap();
    match st.jobs.enqueue(new_job(train(&scene.id, 1, 2), 0)).await {
        Err(SchedError::QueueFull(n)) => assert_eq!(n, 2),
        other => panic!("a third job in a queue of two: {other:?}"),
    }
    // The photo upload's job does not fit: neither it nor the scene is stored.
    let (posing, answer) = add_posing_scene(&st).await;
    assert!(matches!(answer, Err(SchedError::QueueFull(2))), "{answer:?}");
    assert!(st.jobs.get_scene(&posing.id).await.unwrap().is_none());
    assert_eq!(listed_scenes(&st).await, vec![scene.id.clone()]);
    assert_eq!(listed_jobs(&st, None).await.len(), 2);
    // A canceled job makes room.
    st.jobs.cancel(&first.id).await.unwrap();
    st.jobs.enqueue(new_job(train(&scene.id, 1, 3), 0)).await.unwrap();
    st.jobs.shutdown().await;
}

pub async fn queued_jobs_cancel_at_once_and_deletes_happen_once(open: Open) {
    let st = open(Settings::default()).await;
    let scene = add_ball_scene(&st).await;
    let job = st.jobs.enqueue(new_job(train(&scene.id, 1, 0), 0)).await.unwrap();
    match st.jobs.delete_scene(&scene.id).await {
        Err(SchedError::SceneInUse { scene: s, job: j, status }) => {
            assert_eq!((s.as_str(), j.as_str(), status), (scene.id.as_str(), job.id.as_str(), "queued"))
        }
        other => panic!("deleting a scene a queued job trains on: {other:?}"),
    }
    match st.jobs.delete_job(&job.id).await {
        Err(SchedError::JobNotFinal { id, status }) => assert_eq!((id.as_str(), status), (job.id.as_str(), "queued")),
        other => panic!("deleting a queued job: {other:?}"),
    }

    let canceled = st.jobs.cancel(&job.id).await.unwrap();
    assert_eq!(canceled.status, Status::Canceled);
    assert!(canceled.finished_at.is_some_and(|t| t >= job.created_at));
    assert_eq!(json(&st.jobs.get_job(&job.id).await.unwrap().unwrap()), json(&canceled));
    assert!(matches!(st.jobs.cancel(&job.id).await, Err(SchedError::AlreadyFinal { status: "canceled", .. })));
    assert!(matches!(st.jobs.cancel(&new_id("job")).await, Err(SchedError::JobNotFound(_))));
    let stats = st.jobs.stats().await.unwrap();
    assert_eq!((stats.queued, stats.by_status.get(&Status::Canceled).copied()), (0, Some(1)));

    // Each delete happens once; then the thing is not found.
    st.jobs.delete_job(&job.id).await.unwrap();
    assert!(st.jobs.get_job(&job.id).await.unwrap().is_none());
    assert!(listed_jobs(&st, None).await.is_empty());
    assert!(matches!(st.jobs.delete_job(&job.id).await, Err(SchedError::JobNotFound(_))));
    st.jobs.delete_scene(&scene.id).await.unwrap();
    assert!(matches!(st.jobs.delete_scene(&scene.id).await, Err(SchedError::SceneNotFound(_))));
    assert!(matches!(st.jobs.delete_model(&new_id("mdl")).await, Err(SchedError::ModelNotFound(_))));
    assert!(matches!(st.jobs.delete_video(&new_id("vid")).await, Err(SchedError::VideoNotFound(_))));

    // A pose estimation canceled while queued fails its scene, saying so.
    let (posing, job) = add_posing_scene(&st).await;
    let job = job.unwrap().unwrap();
    assert_eq!(st.jobs.cancel(&job.id).await.unwrap().status, Status::Canceled);
    let failed = st.jobs.get_scene(&posing.id).await.unwrap().unwrap();
    assert_eq!(failed.status, SceneStatus::Failed);
    assert_eq!(failed.error.as_deref(), Some("pose estimation was canceled"));
    st.jobs.shutdown().await;
}

pub async fn running_jobs_stop_on_cancel_and_keep_their_model(open: Open) {
    let st = open(Settings { run_jobs: true, ..Settings::default() }).await;
    let scene = add_ball_scene(&st).await;
    let job = st.jobs.enqueue(new_job(train(&scene.id, 1_000_000, 0), 0)).await.unwrap();
    let running = follow(&st, &job.id, 120.0, |j| j.status == Status::Running && j.model_id.is_some()).await;
    let model_id = running.model_id.clone().unwrap();
    // The model's record is listed only with a checkpoint that loads.
    let model = st.jobs.get_model(&model_id).await.unwrap().expect("a model record once model_id is set");
    let ckpt = st.artifacts.checkpoint(&model).await.unwrap();
    let saved = load_checkpoint(&ckpt.path).await.unwrap();
    assert!(saved >= model.steps, "the record names step {}, the checkpoint holds {saved}", model.steps);
    drop(ckpt);

    // What the running job uses cannot go.
    let in_use = |e: Result<(), SchedError>| match e {
        Err(
            SchedError::SceneInUse { job: j, status, .. }
            | SchedError::ModelInUse { job: j, status, .. }
            | SchedError::JobNotFinal { id: j, status },
        ) => (j, status),
        other => panic!("expected a conflict with the running job: {other:?}"),
    };
    assert_eq!(in_use(st.jobs.delete_scene(&scene.id).await), (job.id.clone(), "running"));
    assert_eq!(in_use(st.jobs.delete_model(&model_id).await), (job.id.clone(), "running"));
    assert_eq!(in_use(st.jobs.delete_job(&job.id).await), (job.id.clone(), "running"));
    // Nor can its crop change: the job writes its record.
    let b =
        CropBox { centre: [0.1, 0.2, 0.3], axes: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], half: [0.5; 3] };
    assert_eq!(in_use(st.jobs.set_crop(&model_id, Some(b)).await.map(|_| ())), (job.id.clone(), "running"));

    // Cancel is asked for, answered while the job still runs, and reaches it.
    let asked = st.jobs.cancel(&job.id).await.unwrap();
    assert_eq!(asked.status, Status::Running);
    let ended = follow(&st, &job.id, 60.0, |j| j.status.is_final()).await;
    assert_eq!((ended.status, ended.error.as_deref()), (Status::Canceled, None), "{}", json(&ended));
    assert!(matches!(st.jobs.cancel(&job.id).await, Err(SchedError::AlreadyFinal { status: "canceled", .. })));
    let kept = st.jobs.get_model(&model_id).await.unwrap().expect("a canceled job keeps its model");
    assert!(kept.complete && kept.steps >= model.steps, "{kept:?}");
    let ckpt = st.artifacts.checkpoint(&kept).await.unwrap();
    assert_eq!(load_checkpoint(&ckpt.path).await, Ok(kept.steps));
    drop(ckpt);

    // Once it has ended, its crop is set, kept as given, and removed; each
    // change is a later `updated_at`.
    assert!(kept.crop.is_none());
    let cropped = st.jobs.set_crop(&model_id, Some(b)).await.unwrap();
    assert_eq!(cropped.crop, Some(b));
    assert!(cropped.updated_at > kept.updated_at);
    let record = |m: &radiance::records::ModelInfo| serde_json::to_value(m).unwrap();
    assert_eq!(record(&st.jobs.get_model(&model_id).await.unwrap().unwrap()), record(&cropped));
    let uncropped = st.jobs.set_crop(&model_id, None).await.unwrap();
    assert!(uncropped.crop.is_none() && uncropped.updated_at > cropped.updated_at);
    assert_eq!(record(&st.jobs.get_model(&model_id).await.unwrap().unwrap()), record(&uncropped));
    assert!(matches!(st.jobs.set_crop(&new_id("mdl"), Some(b)).await, Err(SchedError::ModelNotFound(_))));
    // A field model's crop leaves its videos as they are (and carries over
    // to its bake).
    let kept = st.jobs.set_crop(&model_id, Some(b)).await.unwrap();
    if let Some(c) = st.jobs.counters() {
        assert!(c.train_steps.load(std::sync::atomic::Ordering::Relaxed) >= kept.steps);
    }

    // A video of it: listed only once its bytes are there.
    let render = NewJob { model_id: Some(model_id.clone()), ..new_job(video(), 0) };
    let vjob = st.jobs.enqueue(render).await.unwrap();
    let done = follow(&st, &vjob.id, 60.0, |j| j.status.is_final()).await;
    assert_eq!(done.status, Status::Succeeded, "{}", json(&done));
    let video_id = done.video_id.clone().expect("a video id");
    let info = st.jobs.get_video(&video_id).await.unwrap().expect("its record");
    assert_eq!((info.model_id.as_str(), info.job_id.as_str()), (model_id.as_str(), vjob.id.as_str()));
    assert_eq!(st.jobs.list_videos().await.unwrap().len(), 1);
    let bytes = st.artifacts.video(&info).await.unwrap();
    assert_eq!(bytes.len() as u64, info.size_bytes);
    assert!(bytes.starts_with(b"GIF8"));
    let stats = st.jobs.stats().await.unwrap();
    assert_eq!(stats.by_status.get(&Status::Succeeded).copied(), Some(1));
    assert_eq!(stats.by_status.get(&Status::Canceled).copied(), Some(1));

    // Deletes happen once, and take the bytes with the record.
    st.jobs.delete_video(&video_id).await.unwrap();
    assert!(st.jobs.get_video(&video_id).await.unwrap().is_none());
    assert!(st.artifacts.video(&info).await.is_err(), "the video's bytes are gone");
    assert!(matches!(st.jobs.delete_video(&video_id).await, Err(SchedError::VideoNotFound(_))));
    st.jobs.delete_model(&model_id).await.unwrap();
    assert!(st.jobs.get_model(&model_id).await.unwrap().is_none());
    assert!(st.jobs.list_models().await.unwrap().is_empty());
    if let Ok(ckpt) = st.artifacts.checkpoint(&kept).await {
        assert!(load_checkpoint(&ckpt.path).await.is_err(), "the checkpoint is gone");
    }
    assert!(matches!(st.jobs.delete_model(&model_id).await, Err(SchedError::ModelNotFound(_))));
    st.jobs.shutdown().await;
}

pub async fn ready_until_shut_down(open: Open) {
    let st = open(Settings::default()).await;
    st.jobs.ready().await.unwrap();
    st.artifacts.ready().await.unwrap();
    st.jobs.shutdown().await;
    assert!(st.jobs.ready().await.is_err(), "a job store that was shut down is not ready");
}
