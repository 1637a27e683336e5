//! A job record: its kind and what it does, its state and its progress.

use serde::{Deserialize, Serialize};

use crate::engine::front::{Appearance, Budget, CameraPath, MaskUse, ModelConfig};
use crate::media::video::VideoFormat;

/// A job's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl Status {
    pub const ALL: [Status; 5] = [Status::Queued, Status::Running, Status::Succeeded, Status::Failed, Status::Canceled];
    pub fn name(self) -> &'static str {
        match self {
            Status::Queued => "queued",
            Status::Running => "running",
            Status::Succeeded => "succeeded",
            Status::Failed => "failed",
            Status::Canceled => "canceled",
        }
    }
    pub fn is_final(self) -> bool {
        matches!(self, Status::Succeeded | Status::Failed | Status::Canceled)
    }
}

impl std::str::FromStr for Status {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Status::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("unknown status '{s}' (expected queued, running, succeeded, failed or canceled)"))
    }
}

/// What a training job trains.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TrainSpec {
    pub scene_id: String,
    /// Preset name (`instant`, `instant-tiny`, `nerf`, `nerf-tiny`,
    /// `capture`, `capture-tiny`); for a job that asked for `auto`, the one
    /// chosen when it was posted.
    pub model: String,
    /// Why `auto` chose `model` (the evidence, as a sentence); `None` when
    /// the job named its model (and in records from before `auto`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_reason: Option<String>,
    /// The model configuration (the preset's, or the one given).
    pub config: ModelConfig,
    pub budget: JobBudget,
    pub seed: u64,
    pub batch_rays: usize,
    /// What the scene's per-image masks do (`auto` in records from before
    /// masks existed).
    #[serde(default)]
    pub masks: MaskUse,
    /// Bake the model into splats when training succeeds: the bake job's
    /// id (chosen when the training job was posted) and its budget.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bake: Option<BakeAfter>,
    /// Drop the transient occluders found from the training errors.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub drop_transients: bool,
}

/// The bake a training job asks for when it succeeds (`TrainSpec::bake`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BakeAfter {
    /// The id the bake job gets: clients follow it once training ends.
    pub job_id: String,
    pub seconds: Option<f64>,
    pub steps: Option<u64>,
}

/// What a bake job bakes: a trained model (`model_id`) of scene
/// `scene_id`, optimised against the scene's training photos, into a new
/// model of kind `splats` (the job's reserved model id).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BakeSpec {
    /// The trained model baked (instant, nerf or capture).
    pub source_model_id: String,
    /// Its scene: the dataset it was trained on.
    pub scene_id: String,
    /// Wall-clock budget (seconds).
    pub seconds: Option<f64>,
    /// Optimisation steps (one photo each); the first budget reached ends it.
    pub steps: Option<u64>,
    /// Spherical-harmonic degree of the colours (0-3).
    pub sh_degree: u32,
    /// The most Gaussians.
    pub max_gaussians: usize,
    pub seed: u64,
}

/// When a training job stops: at the first limit reached.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JobBudget {
    pub seconds: Option<f64>,
    pub steps: Option<u64>,
    /// Held-out PSNR (dB) at which training stops early.
    pub target_psnr: Option<f64>,
}

impl JobBudget {
    /// Training time allowed when only a target PSNR is given.
    pub const DEFAULT_CAP_SECONDS: f64 = 3600.0;

    /// The engine's budget: steps and seconds (a target-only budget is
    /// capped at [`Self::DEFAULT_CAP_SECONDS`]).
    pub fn engine(&self) -> Budget {
        let seconds = match (self.seconds, self.steps) {
            (None, None) => Some(Self::DEFAULT_CAP_SECONDS),
            (s, _) => s,
        };
        Budget { steps: self.steps, seconds }
    }
}

/// What a video job renders: an orbit around the scene centre of the job's
/// model (`Job::model_id`), or a camera path through keyframes.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VideoSpec {
    pub frames: u32,
    pub fps: u32,
    pub width: u32,
    pub height: u32,
    /// Degrees above the horizon.
    pub elevation: f32,
    /// Distance from the scene centre, world units.
    pub radius: f32,
    /// Horizontal field of view, degrees.
    pub fov: f32,
    pub format: VideoFormat,
    /// Keyframes to fly through instead of the orbit (frames spread evenly
    /// over their times; each keyframe has its own field of view).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<CameraPath>,
    /// The frames' appearance (`view::appearance`): the mean of the
    /// images trained on (left out of the record), or one image's.
    #[serde(default, skip_serializing_if = "Appearance::is_mean")]
    pub appearance: Appearance,
}

/// What a pose-estimation job poses: the photos (or video) uploaded to a
/// scene in its `upload/` folder, written as a COLMAP dataset to `data/`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PosesSpec {
    pub scene_id: String,
}

/// A job's kind and what it does.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum JobSpec {
    Train(Box<TrainSpec>),
    Video(VideoSpec),
    Poses(PosesSpec),
    Bake(BakeSpec),
}

impl JobSpec {
    pub fn name(&self) -> &'static str {
        match self {
            JobSpec::Train(_) => "train",
            JobSpec::Video(_) => "video",
            JobSpec::Poses(_) => "poses",
            JobSpec::Bake(_) => "bake",
        }
    }
    /// The scene a training, pose-estimation or bake job works on.
    pub fn scene_id(&self) -> Option<&str> {
        match self {
            JobSpec::Train(t) => Some(&t.scene_id),
            JobSpec::Poses(p) => Some(&p.scene_id),
            JobSpec::Bake(b) => Some(&b.scene_id),
            JobSpec::Video(_) => None,
        }
    }
}

/// Where a job is, as clients see it.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct JobProgress {
    /// Training steps done, or video frames rendered (pose estimation:
    /// thousandths of the whole).
    pub step: u64,
    /// Steps (or frames) in all, when known in advance.
    #[serde(default)]
    pub total_steps: Option<u64>,
    pub loss: f64,
    pub train_psnr: f64,
    /// Seconds of training (across restarts), or of rendering.
    pub elapsed: f64,
    pub eta: Option<f64>,
    /// Mean PSNR on held-out views: estimated on a sample of held-out pixels
    /// as training goes, then measured on whole views at the end.
    pub test_psnr: Option<f64>,
    /// Training step of the last `test_psnr`.
    #[serde(default)]
    pub test_psnr_step: Option<u64>,
    pub rays_per_second: f64,
    /// Steps skipped because the loss or a gradient was not finite.
    #[serde(default)]
    pub diverged_steps: u64,
    /// Rollbacks to the last good parameters, each halving the learning rate.
    #[serde(default)]
    pub rollbacks: u32,
    /// Pose estimation: the stage running (`preparing photos`, `feature
    /// extraction`, `matching`, `mapping`, ...).
    #[serde(default)]
    pub stage: Option<String>,
    /// Baking: the Gaussians the splats have now.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians: Option<u64>,
}

/// A job record.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Job {
    pub id: String,
    /// Enqueue order.
    pub seq: u64,
    pub status: Status,
    #[serde(flatten)]
    pub spec: JobSpec,
    pub created_at: u64,
    pub started_at: Option<u64>,
    pub finished_at: Option<u64>,
    pub error: Option<String>,
    /// Training: set once a checkpoint exists. Video: the model rendered.
    /// Bake: the splats model, set once it is saved.
    pub model_id: Option<String>,
    /// Video: set when the video is ready at `/v1/videos/{video_id}`.
    #[serde(default)]
    pub video_id: Option<String>,
    pub progress: JobProgress,
    /// Times the job was started (more than one after a restart).
    #[serde(default)]
    pub attempts: u32,
    /// Estimated peak memory of the job (bytes), checked against the
    /// server's limits before it was queued and before it starts.
    #[serde(default)]
    pub memory_estimate_bytes: u64,
    /// Runs in a row that ended with the server process dying (killed, or
    /// out of memory) without the job saving anything new; at two the job
    /// is failed instead of being run again.
    #[serde(default)]
    pub crashes: u32,
}

impl Job {
    /// The id its model gets: the job id with the `mdl` prefix.
    pub fn reserved_model_id(&self) -> String {
        reserved_model_id(&self.id)
    }
    /// The id its video gets: the job id with the `vid` prefix.
    pub fn reserved_video_id(&self) -> String {
        format!("vid{}", self.id.trim_start_matches("job"))
    }
}

/// The id the model of job `job_id` gets: the job id with the `mdl` prefix
/// (for stores that know the job's id before they hold its record).
pub fn reserved_model_id(job_id: &str) -> String {
    format!("mdl{}", job_id.trim_start_matches("job"))
}
