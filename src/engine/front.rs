//! The engine's front door: what the service (`api`, `jobs`, `worker`)
//! and the command line (`cli`) use of the engine, in one place. Load a
//! model from a checkpoint, render a view of it, run a training session on
//! a dataset, bake a model into splats and export them, estimate a job's
//! memory, and the types these take and give; for the command line also
//! what evaluating and benchmarking a model take. `tests/layering.rs`
//! checks that the service and the command line reach the engine through
//! nothing else, so what they depend on is this page, and the folders
//! behind it can move.

use std::path::Path;

pub use super::bake::{BakeError, BakeProgress, BakeSettings, bake};
pub use super::dataset::product::ProductScene;
pub use super::dataset::synthetic::{BallScene, write_blender};
pub use super::dataset::{Dataset, DatasetError, DatasetFormat, LoadOptions, MaskUse, Split, detect_format};
pub use super::geometry::camera::Camera;
pub use super::geometry::path::{CameraPath, Keyframe, MAX_KEYFRAMES};
pub use super::geometry::rig::Spiral;
pub use super::io::checkpoint::CheckpointError;
pub use super::io::fsio::write_atomic;
pub use super::mesh::export::{as_written as mesh_as_written, glb as mesh_glb, usdz as mesh_usdz};
pub use super::mesh::raster::{MeshView, render_antialiased as render_mesh};
pub use super::mesh::views::{auto_crop_for as auto_crop_any, photos as mesh_photos, scene_box};
pub use super::mesh::{
    MeshError, MeshOptions, MeshStats, Placement, STAGES as MESH_STAGES, TexturedMesh, make as make_mesh,
};
pub use super::metrics::psnr;
pub use super::models::auto::{AUTO, ModelChoice, SceneKind, choose as choose_model};
pub use super::models::config::{ConfigError, DEFAULT_BATCH_RAYS, ModelConfig, presets, trainable_presets};
pub use super::models::splats::SplatsConfig;
pub use super::models::splats::cleanup::{CleanupSettings, Removed, cleanup};
pub use super::models::splats::crop::{CropBox, CropError, auto_crop, auto_crop_for, crop, crop_model, world_centres};
pub use super::models::splats::export::spz::{read_spz, write_spz};
pub use super::models::splats::export::{Format as SplatsFormat, ply_len, splats_of, write as write_splats};
pub use super::models::training::{Budget, TrainConfig};
pub use super::models::{Model, ModelError};
pub use super::nn::pose_report::PoseReport;
pub use super::train::estimate::{
    DataSize, Estimate, bake as estimate_bake, mib, training as estimate_training, video as estimate_video,
};
pub use super::train::persist::{save as save_checkpoint, strip_training_state};
pub use super::train::session::{Event, HeldOut, Session, SessionConfig, SessionError, Start, Stop};
pub use super::train::trainer::{Progress, TrainState};
pub use super::view::appearance::{Appearance, AppearanceError, held_out_options};
pub use super::view::{render_heldout_view, render_view_until, render_view_with};

// What the command line uses besides: a model trained, scored and fitted
// step by step (`eval`, `bench`, `train --model splats`), the scene a
// model is made for and the demo's orbit.
pub use super::dataset::Frame;
pub use super::dataset::masks::{INSIDE as MASK_INSIDE, inside as mask_inside};
pub use super::dataset::occlude::{Occluders, Pasted, load_cutouts, occlude};
pub use super::geometry::camera::Orbit;
pub use super::geometry::math::Vec3;
pub use super::geometry::scene::Scene;
pub use super::io::checkpoint::Checkpoint;
pub use super::metrics::{psnr_inside, ssim_map};
pub use super::models::capture::KIND as CAPTURE_KIND;
pub use super::models::splats::SplatsModel;
pub use super::models::{RenderOptions, heldout_pose};
pub use super::nn::adam::Adam;
pub use super::train::appearance_fit::{AppearanceFit, FitError, FitSettings, Half};
pub use super::train::persist::{Restored, load as load_checkpoint};
pub use super::train::trainer::{StopReason, Trainer};
pub use super::transient::{FoundMasks, MOSTLY_MASKED, PhotoShare, TransientMaps, TransientReport};
pub use super::view::{View, render_view};

/// The model a checkpoint holds, ready to render (its optimiser state, if
/// the checkpoint has one, is dropped; a training session resumes from the
/// checkpoint itself: [`Start::Resume`]).
pub fn load_model(path: &Path) -> Result<Box<dyn Model>, CheckpointError> {
    Ok(super::train::persist::load(path)?.model)
}
