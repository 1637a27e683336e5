//! Posed-image datasets: one in-memory representation for the three formats
//! users have (Blender `transforms_*.json`, instant-ngp/nerfstudio
//! `transforms.json`, LLFF `poses_bounds.npy`).

use std::fmt;
use std::path::{Path, PathBuf};

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::{Aabb, Vec3};

mod blender;
mod colmap;
pub mod colmap_model;
mod images;
pub use images::{IMAGE_EXTENSIONS, MAX_PIXELS};
mod json;
mod llff;
pub mod masks;
mod ngp;
pub mod npy;
pub mod occlude;
pub mod product;
mod scene;
pub mod synthetic;
#[cfg(test)]
pub(crate) mod testutil;
pub mod textured;
mod validate;

pub use masks::MaskUse;
pub use npy::{NpyArray, parse_npy};

/// Which on-disk format a dataset came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DatasetFormat {
    /// NeRF synthetic: `transforms_{train,val,test}.json`.
    Blender,
    /// instant-ngp / nerfstudio: one `transforms.json`.
    Ngp,
    /// LLFF: `poses_bounds.npy` + `images_N/`.
    Llff,
    /// COLMAP: a sparse model in `sparse/0/` + `images/`.
    Colmap,
}

impl fmt::Display for DatasetFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Blender => "blender",
            Self::Ngp => "transforms",
            Self::Llff => "llff",
            Self::Colmap => "colmap",
        })
    }
}

/// A dataset split.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "train" => Ok(Split::Train),
            "val" => Ok(Split::Val),
            "test" => Ok(Split::Test),
            _ => Err(format!("unknown split '{s}' (expected train, val or test)")),
        }
    }
}

/// An 8-bit RGBA image, row-major, straight (not premultiplied) alpha.
/// Images without alpha have alpha 255 everywhere.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
    /// Whether the source had an alpha channel.
    pub has_alpha: bool,
}

impl Image {
    /// The pixel at `(i, j)` as f32 RGB composited on `background`.
    pub fn rgb_on(&self, i: u32, j: u32, background: [f32; 3]) -> [f32; 3] {
        let k = 4 * (j as usize * self.width as usize + i as usize);
        let p = &self.rgba[k..k + 4];
        let a = p[3] as f32 / 255.0;
        let c = |v: u8, b: f32| v as f32 / 255.0 * a + b * (1.0 - a);
        [c(p[0], background[0]), c(p[1], background[1]), c(p[2], background[2])]
    }

    /// Whether some pixel is not fully opaque (only images with an alpha
    /// channel can have one).
    pub fn has_transparent_pixels(&self) -> bool {
        self.has_alpha && self.rgba.chunks_exact(4).any(|p| p[3] < 255)
    }
}

/// One posed view.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The image file's stem (`./test/r_7` -> `r_7`): renders are named by it.
    pub name: String,
    /// The image file.
    pub path: PathBuf,
    pub camera: Camera,
    pub image: Image,
    /// The image's mask, one byte per pixel (row-major, 255 inside; see
    /// [`masks`]): every frame has one when masks are in effect
    /// ([`Dataset::masks`] is not `Off`), none has otherwise.
    pub mask: Option<Vec<u8>>,
}

/// Options for loading.
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Background RGBA images are composited on (white by default).
    pub background: [f32; 3],
    /// For Blender datasets: which split files to read (all that exist by
    /// default). Other formats always load every frame.
    pub splits: Vec<Split>,
    /// What per-image masks do ([`MaskUse::Auto`] by default).
    pub masks: MaskUse,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { background: [1.0; 3], splits: Split::ALL.to_vec(), masks: MaskUse::Auto }
    }
}

/// A loaded dataset in world units.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub format: DatasetFormat,
    pub root: PathBuf,
    pub frames: Vec<Frame>,
    /// Frame indices of each split. Formats without a split hold out every
    /// 8th frame (index % 8 == 0) as both `val` and `test`.
    pub train: Vec<usize>,
    pub val: Vec<usize>,
    pub test: Vec<usize>,
    /// Ray interval in world units.
    pub near: f32,
    pub far: f32,
    /// The scene's bounding box in world units: rays are clipped to it.
    pub aabb: Aabb,
    /// Background that RGBA images are composited on for evaluation.
    pub background: [f32; 3],
    /// Non-fatal observations (few views, ...).
    pub warnings: Vec<String>,
    /// What the frames' masks do: `Score`, `Ignore` or `Composite` when
    /// masks are in effect (every frame has one), `Off` otherwise.
    pub masks: MaskUse,
    /// The mask folder the masks came from (the first, should the images
    /// lie in several folders); `None` for masks from the alpha channel.
    pub mask_folder: Option<PathBuf>,
}

impl Dataset {
    /// Detects the format of the dataset at `root` and loads it.
    /// Per-image masks are read as `opts.masks` asks ([`masks`]).
    pub fn load(root: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
        let mut ds = match detect_format(root)? {
            DatasetFormat::Blender => blender::load(root, opts),
            DatasetFormat::Ngp => ngp::load(root, opts),
            DatasetFormat::Llff => llff::load(root, opts),
            DatasetFormat::Colmap => colmap::load(root, opts),
        }?;
        masks::attach(&mut ds, opts.masks)?;
        Ok(ds)
    }

    pub fn split(&self, s: Split) -> &[usize] {
        match s {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// The frames of a split.
    pub fn split_frames(&self, s: Split) -> impl Iterator<Item = &Frame> {
        self.split(s).iter().map(|&i| &self.frames[i])
    }

    /// Centre of the scene box.
    pub fn centre(&self) -> Vec3 {
        self.aabb.centre()
    }

    /// The mask folder relative to the dataset, as users name it
    /// (`masks_8/`); `None` without one.
    pub fn mask_folder_name(&self) -> Option<String> {
        self.mask_folder.as_deref().map(|d| masks::folder_name(d, &self.root))
    }
}

/// Finds which format the folder holds.
pub fn detect_format(root: &Path) -> Result<DatasetFormat, DatasetError> {
    if !root.is_dir() {
        return Err(DatasetError::NotFound(root.to_path_buf()));
    }
    if Split::ALL.iter().any(|s| root.join(format!("transforms_{}.json", s.name())).is_file()) {
        Ok(DatasetFormat::Blender)
    } else if root.join("transforms.json").is_file() {
        Ok(DatasetFormat::Ngp)
    } else if root.join("poses_bounds.npy").is_file() {
        Ok(DatasetFormat::Llff)
    } else if colmap::model_dir(root).is_some() {
        Ok(DatasetFormat::Colmap)
    } else {
        Err(DatasetError::UnknownFormat(root.to_path_buf()))
    }
}

/// Why a dataset could not be loaded. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("dataset folder {0} does not exist")]
    NotFound(PathBuf),
    #[error(
        "{0}: unknown dataset format (expected transforms_train.json, transforms.json, poses_bounds.npy or a COLMAP model in sparse/0)"
    )]
    UnknownFormat(PathBuf),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: invalid JSON: {message}")]
    Json { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    #[error("{path}: image is missing (referenced by {referenced_by})")]
    MissingImage { path: PathBuf, referenced_by: PathBuf },
    #[error(
        "{image}: no mask for this image in {looked_in} (a PNG or JPEG file with its stem); {missing} of {total} \
         images have none: add them, or load with masks off (`--masks off`) to leave the masks unused"
    )]
    MissingMask { image: PathBuf, looked_in: String, missing: usize, total: usize },
    #[error("{path}: image does not decode: {message}")]
    BadImage { path: PathBuf, message: String },
    #[error(
        "{path}: image declares {width}x{height} pixels ({:.0} megapixels), more than the {limit_mp} megapixels \
         an image may have; downscale it",
        *width as f64 * *height as f64 / 1e6
    )]
    TooManyPixels { path: PathBuf, width: u32, height: u32, limit_mp: u64 },
    #[error("{path}: image is {got_w}x{got_h}, expected {want_w}x{want_h}")]
    SizeMismatch { path: PathBuf, got_w: u32, got_h: u32, want_w: u32, want_h: u32 },
    #[error("{path}: frame {frame}: {message}")]
    BadPose { path: PathBuf, frame: usize, message: String },
}
