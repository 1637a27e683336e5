//! Why a job body failed. A job's `error`, as clients read it, is this
//! error's message (`Outcome::Failed`), written in one place
//! ([`super::run_body`]).

use std::io;

use crate::engine::front::{
    AppearanceError, BakeError, CheckpointError, CropError, DatasetError, ModelError, SessionError, Stop,
};
use crate::media::video::VideoError;
use crate::poses::PoseError;

/// A job body's failure (a pose estimation's own errors are [`PoseError`]s).
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The job's scene was deleted before it ran.
    #[error("scene '{0}' no longer exists")]
    SceneGone(String),
    /// The video job's model was deleted before it ran.
    #[error("model '{0}' no longer exists")]
    ModelGone(String),
    /// The scene's dataset does not load.
    #[error("{0}")]
    Dataset(#[from] DatasetError),
    #[error("the scene has no training views")]
    NoTrainingViews,
    /// The model could not be built from the job's configuration.
    #[error("{0}")]
    Model(#[from] ModelError),
    #[error("{0}")]
    Session(#[from] SessionError),
    /// Training diverged again and again (the last periodic checkpoint stays).
    #[error("{0}")]
    Diverged(Stop),
    /// The video's model: its checkpoint could not be fetched.
    #[error("loading the model: {0}")]
    ModelFile(io::Error),
    /// The video's model: its checkpoint does not load.
    #[error("loading the model: {0}")]
    Checkpoint(#[from] CheckpointError),
    #[error("making the frames folder: {0}")]
    FramesFolder(io::Error),
    #[error("this orbit gives no well-defined camera (elevation of +-90 degrees?)")]
    NoOrbitCamera,
    #[error("{0}")]
    Appearance(#[from] AppearanceError),
    /// A rendered frame could not become an image.
    #[error("{0}")]
    Frame(io::Error),
    /// A frame to keep could not be encoded as a PNG.
    #[error("{0}")]
    PngEncode(image::ImageError),
    #[error("saving a frame: {0}")]
    SaveFrame(io::Error),
    #[error("encoding the video: {0}")]
    Encode(#[from] VideoError),
    #[error("{0}")]
    Poses(#[from] PoseError),
    /// Baking failed (a cancelled bake is `Outcome::Stopped`, not this).
    #[error("{0}")]
    Bake(#[from] BakeError),
    /// The baked model's checkpoint could not be written.
    #[error("saving the splats: {0}")]
    SaveSplats(CheckpointError),
    /// A training job's model is trained, but the bake it asked for could
    /// not be enqueued.
    #[error("the model is trained, but its bake could not be queued: {0}")]
    BakeNotQueued(String),
    /// The video's model has a crop that cannot be used.
    #[error("the model's crop: {0}")]
    Crop(#[from] CropError),
    /// Reading records or files, or publishing what the job made.
    #[error("{0}")]
    Io(#[from] io::Error),
}
