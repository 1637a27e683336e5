//! The service's on-disk layout under the data directory, and its records.
//!
//! ```text
//! DATA/scenes/ID/scene.json   scene record (written before the folder appears)
//! DATA/scenes/ID/data/...     the uploaded dataset as extracted
//! DATA/models/ID.ckpt         checkpoint (engine::persist, atomic)
//! DATA/models/ID.json         model record
//! DATA/jobs/ID.json           job record (only enqueued and final states)
//! DATA/tmp/                   uploads being extracted, scenes being deleted
//! ```
//!
//! Every file is written atomically ([`write_atomic`]) and every folder
//! appears by one `rename`, so a crash leaves either the old state or the
//! new one. `tmp/` is emptied at start-up.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize, de::DeserializeOwned};

use crate::engine::fsio::write_atomic;

/// Paths of the data directory.
#[derive(Clone, Debug)]
pub struct Storage {
    pub root: PathBuf,
}

impl Storage {
    /// Creates the layout (if missing) and clears leftovers of interrupted
    /// uploads and deletions.
    pub fn open(root: &Path) -> io::Result<Self> {
        let s = Self { root: root.to_path_buf() };
        for d in ["scenes", "models", "jobs", "videos"] {
            std::fs::create_dir_all(s.root.join(d))?;
        }
        let tmp = s.tmp_dir();
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)?;
        }
        std::fs::create_dir_all(&tmp)?;
        Ok(s)
    }

    pub fn tmp_dir(&self) -> PathBuf {
        self.root.join("tmp")
    }
    pub fn scenes_dir(&self) -> PathBuf {
        self.root.join("scenes")
    }
    pub fn scene_dir(&self, id: &str) -> PathBuf {
        self.scenes_dir().join(id)
    }
    pub fn scene_record(&self, id: &str) -> PathBuf {
        self.scene_dir(id).join("scene.json")
    }
    pub fn models_dir(&self) -> PathBuf {
        self.root.join("models")
    }
    pub fn checkpoint(&self, model_id: &str) -> PathBuf {
        self.models_dir().join(format!("{model_id}.ckpt"))
    }
    pub fn model_record(&self, model_id: &str) -> PathBuf {
        self.models_dir().join(format!("{model_id}.json"))
    }
    pub fn jobs_dir(&self) -> PathBuf {
        self.root.join("jobs")
    }
    pub fn job_record(&self, id: &str) -> PathBuf {
        self.jobs_dir().join(format!("{id}.json"))
    }

    pub fn load_scene(&self, id: &str) -> io::Result<Option<SceneInfo>> {
        if !valid_id(id) {
            return Ok(None);
        }
        read_json_opt(&self.scene_record(id))
    }

    pub fn list_scenes(&self) -> io::Result<Vec<SceneInfo>> {
        let mut v: Vec<SceneInfo> = Vec::new();
        for e in std::fs::read_dir(self.scenes_dir())? {
            let name = e?.file_name().to_string_lossy().into_owned();
            if let Some(s) = self.load_scene(&name)? {
                v.push(s);
            }
        }
        v.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        Ok(v)
    }

    pub fn videos_dir(&self) -> PathBuf {
        self.root.join("videos")
    }
    /// The video file (its record says the format).
    pub fn video_file(&self, id: &str) -> PathBuf {
        self.videos_dir().join(format!("{id}.bin"))
    }
    pub fn video_record(&self, id: &str) -> PathBuf {
        self.videos_dir().join(format!("{id}.json"))
    }

    pub fn load_video(&self, id: &str) -> io::Result<Option<VideoInfo>> {
        if !valid_id(id) {
            return Ok(None);
        }
        read_json_opt(&self.video_record(id))
    }

    pub fn load_model(&self, id: &str) -> io::Result<Option<ModelInfo>> {
        if !valid_id(id) {
            return Ok(None);
        }
        read_json_opt(&self.model_record(id))
    }

    pub fn list_models(&self) -> io::Result<Vec<ModelInfo>> {
        let mut v: Vec<ModelInfo> = list_json(&self.models_dir())?;
        v.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        Ok(v)
    }
}

/// Ids are made here and only ever contain `[a-z0-9_]`: a path component
/// that cannot escape its folder.
pub fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 64 && id.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

/// A fresh id: `PREFIX` + milliseconds since the epoch + a mixed counter,
/// so ids sort roughly by creation and never repeat within a process.
pub fn new_id(prefix: &str) -> String {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let ms = now_ms();
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    // splitmix64 of (time, pid, counter): unique enough across restarts too
    let mut z = ms ^ ((std::process::id() as u64) << 32) ^ n.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    format!("{prefix}_{ms:011x}{:06x}", z & 0xFF_FFFF)
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// Writes pretty JSON atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> io::Result<()> {
    let bytes = serde_json::to_vec_pretty(value).map_err(io::Error::other)?;
    write_atomic(path, &bytes)
}

/// Reads JSON, `None` when the file does not exist.
pub fn read_json_opt<T: DeserializeOwned>(path: &Path) -> io::Result<Option<T>> {
    match std::fs::read(path) {
        Ok(b) => serde_json::from_slice(&b)
            .map(Some)
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidData, format!("{}: {e}", path.display()))),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e),
    }
}

/// Every `*.json` record of a folder (temporary files start with a dot).
pub fn list_json<T: DeserializeOwned>(dir: &Path) -> io::Result<Vec<T>> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir)? {
        let p = e?.path();
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.starts_with('.') || !name.ends_with(".json") {
            continue;
        }
        if let Some(r) = read_json_opt(&p)? {
            v.push(r);
        }
    }
    Ok(v)
}

/// Image counts of a dataset's splits.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SplitCounts {
    pub train: usize,
    pub val: usize,
    pub test: usize,
}

/// How to look at a scene by default: the training cameras' image size and
/// field of view, the scene centre, the mean up vector and camera distance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewDefaults {
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view in degrees.
    pub fov: f32,
    pub centre: [f32; 3],
    pub up: [f32; 3],
    /// Mean distance of the training cameras from the centre.
    pub radius: f32,
    /// Far plane in world units (depth images map it to white).
    pub far: f32,
}

/// A stored scene.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneInfo {
    pub id: String,
    /// `blender`, `ngp` or `llff`.
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
}

/// A trained (or training) model.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ModelInfo {
    pub id: String,
    pub scene_id: String,
    pub job_id: String,
    /// Preset name (`nerf`, `nerf-tiny`).
    pub model: String,
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
    pub view: ViewDefaults,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_valid_and_distinct() {
        let a = new_id("job");
        let b = new_id("job");
        assert_ne!(a, b);
        assert!(valid_id(&a) && valid_id(&b));
        assert!(!valid_id("../x") && !valid_id("") && !valid_id("A"));
    }
}
