//! The records of the service: scenes, models and videos as clients see
//! them (and as the data directory, the PostgreSQL records and the API
//! store and answer them), with the view defaults a scene's training
//! cameras give.

use serde::{Deserialize, Serialize};

use crate::engine::dataset::Dataset;
use crate::engine::geometry::camera::Orbit;
use crate::engine::geometry::math::Vec3;
use crate::engine::geometry::rig::Spiral;
use crate::engine::models::auto::SceneKind;
use crate::system::now_ms;

/// A model's crop volume: an oriented box in world units.
pub use crate::engine::front::CropBox;

/// Image counts of a dataset's splits.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SplitCounts {
    pub train: usize,
    pub val: usize,
    pub test: usize,
}

/// How to look at a scene by default, from its training cameras (see
/// `engine::geometry::rig`): their image size and field of view, the point
/// they look at, their up vector, distance, elevation and mean direction.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewDefaults {
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view in degrees.
    pub fov: f32,
    /// The point the training cameras look at (orbits turn around it).
    pub centre: [f32; 3],
    pub up: [f32; 3],
    /// Median distance of the training cameras from the centre.
    pub radius: f32,
    /// Far plane in world units (depth images map it to white).
    pub far: f32,
    /// The capture's near bound in world units: the field's rays start
    /// there and splats are drawn from there on, so the web viewer's near
    /// plane is there too. `None` in records from before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub near: Option<f32>,
    /// Mean elevation of the training cameras above the centre, degrees:
    /// the default of renders and orbit videos. (Records from before it
    /// existed: 30, the default then.)
    #[serde(default = "ViewDefaults::default_elevation")]
    pub elevation: f32,
    /// Unit direction from the centre towards the cameras, perpendicular to
    /// `up`: azimuth 0. `None` in records from before it existed (azimuth 0
    /// was then the direction of world x, projected).
    #[serde(default)]
    pub front: Option<[f32; 3]>,
    /// For forward-facing captures (all cameras look the same way): the
    /// spiral that default videos follow instead of a full orbit.
    #[serde(default)]
    pub spiral: Option<Spiral>,
    /// For captures that saw the subject from one side (the cameras leave a
    /// gap of more than 120 degrees around it): the azimuths they span,
    /// degrees `[start, end]` (0 towards `front`); default videos sweep
    /// across this arc and back instead of a full orbit. `None` otherwise
    /// and in records from before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc: Option<[f32; 2]>,
}

impl ViewDefaults {
    /// The frame size for an optional width and height: the training
    /// cameras' size, or the given width with their aspect ratio.
    pub fn frame_size(&self, width: Option<u32>, height: Option<u32>) -> (u32, u32) {
        let w = width.unwrap_or(self.width);
        let h = height.unwrap_or_else(|| match width {
            Some(w) => ((w as u64 * self.height as u64) / self.width.max(1) as u64).max(1) as u32,
            None => self.height,
        });
        (w, h)
    }

    fn default_elevation() -> f32 {
        30.0
    }

    /// The orbit around the scene centre, about its up axis, at
    /// `elevation_deg` above the horizon and `radius` from the centre,
    /// azimuth 0 towards `front`.
    pub fn orbit(&self, elevation_deg: f32, radius: f32) -> Orbit {
        Orbit {
            centre: Vec3::from_array(self.centre),
            up: Vec3::from_array(self.up),
            front: self.front.map(Vec3::from_array),
            elevation_deg,
            radius,
        }
    }

    /// The defaults of a dataset's training cameras.
    pub fn from_dataset(ds: &Dataset) -> ViewDefaults {
        let cam = &ds.frames[ds.train[0]].camera;
        let rig = ds.rig();
        ViewDefaults {
            width: cam.width,
            height: cam.height,
            fov: (2.0 * (0.5 * cam.width as f32 / cam.fx).atan()).to_degrees(),
            centre: rig.as_ref().map_or(ds.centre().to_array(), |r| r.focus),
            up: rig.as_ref().map_or([0.0, 0.0, 1.0], |r| r.up),
            radius: rig.as_ref().map_or(1.0, |r| r.radius),
            far: ds.far,
            near: Some(ds.near),
            elevation: rig.as_ref().map_or(Self::default_elevation(), |r| r.elevation_deg),
            front: rig.as_ref().map(|r| r.front),
            arc: rig.as_ref().and_then(|r| r.arc_deg),
            spiral: rig.filter(|r| r.forward_facing).map(|r| r.spiral),
        }
    }
}

/// Whether a scene can be trained on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneStatus {
    /// Its dataset is stored and valid.
    #[default]
    Ready,
    /// Photos without poses: a `poses` job is estimating them.
    Posing,
    /// Pose estimation failed (`error` says why); the scene cannot be trained on.
    Failed,
}

impl SceneStatus {
    pub fn name(self) -> &'static str {
        match self {
            Self::Ready => "ready",
            Self::Posing => "posing",
            Self::Failed => "failed",
        }
    }
}

/// The pose estimation of a scene uploaded as photos (or a video) only.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScenePoses {
    /// The `poses` job.
    pub job_id: String,
    /// `photos` or `video`.
    pub source: String,
    /// Photos uploaded (0 for a video, whose frames are counted in `report`).
    pub photos: usize,
    /// What the estimation found, once it succeeded.
    pub report: Option<crate::poses::PoseReport>,
}

/// A stored scene.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneInfo {
    pub id: String,
    /// What the upload was called, to show people: the archive's file name
    /// or the folder's (`POST /v1/scenes?name=`, or a multipart upload's one
    /// top folder); `None` when it is not known (and in records from before
    /// names were kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    #[serde(default)]
    pub status: SceneStatus,
    /// Why pose estimation failed (status `failed`).
    #[serde(default)]
    pub error: Option<String>,
    /// For photo-only uploads: the pose estimation and its results.
    #[serde(default)]
    pub poses: Option<ScenePoses>,
    /// `blender`, `ngp`, `llff` or `colmap` (photo-only uploads become `colmap`).
    pub format: crate::engine::dataset::DatasetFormat,
    pub images: SplitCounts,
    /// `[width, height]` of the first training image.
    pub resolution: [u32; 2],
    pub warnings: Vec<String>,
    pub created_at: u64,
    /// Bytes of the extracted dataset.
    pub size_bytes: u64,
    /// The dataset folder relative to the scene folder.
    pub root: String,
    pub view: ViewDefaults,
    /// The mask folder found beside the images (`masks_8/`), relative to
    /// the dataset folder; `None` without one (and in records from before
    /// masks existed).
    #[serde(default)]
    pub mask_folder: Option<String>,
    /// What the automatic model choice looks at (transparent training
    /// images, the cameras' spread), measured at upload; `None` in records
    /// from before it existed (a job's `auto` then loads the dataset).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kind: Option<SceneKind>,
}

impl SceneInfo {
    /// The record of a ready scene whose dataset `ds` (of `size_bytes`) is
    /// stored in the folder `root` of the scene's folder.
    pub fn from_dataset(id: &str, ds: &Dataset, size_bytes: u64, root: String) -> SceneInfo {
        let cam = &ds.frames[ds.train[0]].camera;
        let mut warnings = ds.warnings.clone();
        if ds.test.is_empty() && ds.val.is_empty() {
            warnings.push("no held-out views: models of this scene cannot be measured".into());
        }
        SceneInfo {
            id: id.to_string(),
            name: None,
            status: SceneStatus::Ready,
            error: None,
            poses: None,
            format: ds.format,
            images: SplitCounts { train: ds.train.len(), val: ds.val.len(), test: ds.test.len() },
            resolution: [cam.width, cam.height],
            warnings,
            created_at: now_ms(),
            size_bytes,
            root,
            view: ViewDefaults::from_dataset(ds),
            mask_folder: ds.mask_folder_name(),
            kind: Some(SceneKind::of_dataset(ds)),
        }
    }
}

/// A trained (or training) model.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ModelInfo {
    pub id: String,
    pub scene_id: String,
    pub job_id: String,
    /// Preset name (one of `engine::models::config::presets()`: `instant`, `instant-tiny`, `nerf`, `nerf-tiny`,
    /// `capture`, `capture-tiny`); for a job that asked for `auto`, the one chosen.
    pub model: String,
    /// Why `auto` chose `model` (the evidence, as a sentence); `None` when
    /// the job named its model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_reason: Option<String>,
    pub config: serde_json::Value,
    pub steps: u64,
    pub training_seconds: f64,
    /// Mean PSNR on held-out views, when measured.
    pub test_psnr: Option<f64>,
    /// Held-out views measured.
    pub test_views: usize,
    pub size_bytes: u64,
    pub created_at: u64,
    pub updated_at: u64,
    /// Whether training has finished (succeeded or canceled).
    pub complete: bool,
    /// Whether the checkpoint still holds the optimiser state (needed only
    /// to resume training); dropped `--keep-training-state-hours` after
    /// training has ended.
    #[serde(default = "yes")]
    pub training_state: bool,
    pub view: ViewDefaults,
    /// For a capture model that refines its cameras: how far they moved
    /// (written when training ends).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub poses: Option<crate::engine::nn::pose_report::PoseReport>,
    /// For a splats model: how many Gaussians it has.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussians: Option<u64>,
    /// For a model trained with `drop_transients`: what was dropped, per
    /// training photo (written when training ends; each photo's mask is
    /// `GET /v1/models/{id}/transients/{photo}`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transients: Option<crate::engine::front::TransientReport>,
    /// The crop volume (`PUT /v1/models/{id}/crop`): a splats model's
    /// views, videos and exports keep only the Gaussians inside it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<CropBox>,
}

fn yes() -> bool {
    true
}

/// A rendered orbit video. The file is written before the record, so a
/// record always points at a whole file.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct VideoInfo {
    pub id: String,
    pub model_id: String,
    pub job_id: String,
    pub format: crate::media::video::VideoFormat,
    pub frames: u32,
    pub fps: u32,
    pub width: u32,
    pub height: u32,
    pub size_bytes: u64,
    pub created_at: u64,
}

/// View defaults with small made-up values, for tests' records.
#[cfg(test)]
pub(crate) fn sample_view() -> ViewDefaults {
    ViewDefaults {
        width: 4,
        height: 4,
        fov: 40.0,
        centre: [0.0; 3],
        up: [0.0, 0.0, 1.0],
        radius: 1.0,
        far: 2.0,
        near: None,
        elevation: 30.0,
        front: None,
        spiral: None,
        arc: None,
    }
}

/// A ready scene's record with small made-up values (what tests that
/// only need a record to enqueue on use).
#[cfg(test)]
pub(crate) fn sample_scene(id: &str) -> SceneInfo {
    let view = sample_view();
    SceneInfo {
        status: SceneStatus::Ready,
        error: None,
        poses: None,
        id: id.into(),
        name: None,
        format: crate::engine::dataset::DatasetFormat::Blender,
        images: SplitCounts { train: 1, val: 0, test: 0 },
        resolution: [4, 4],
        warnings: Vec::new(),
        created_at: 0,
        size_bytes: 0,
        root: "data".into(),
        mask_folder: None,
        kind: None,
        view,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_defaults_from_before_the_camera_rig_still_load() {
        let old =
            r#"{"width":4,"height":3,"fov":40.0,"centre":[1.0,2.0,3.0],"up":[0.0,0.0,1.0],"radius":2.0,"far":9.0}"#;
        let v: ViewDefaults = serde_json::from_str(old).unwrap();
        assert_eq!((v.elevation, v.front, &v.spiral), (30.0, None, &None));
        // Azimuth 0 then was world x, as before.
        let eye = v.orbit(0.0, 2.0).pose(0.0).unwrap();
        assert!((eye[0][3] - 3.0).abs() < 1e-6 && (eye[1][3] - 2.0).abs() < 1e-6, "{eye:?}");
    }
}
