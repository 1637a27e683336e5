//! The data directory: its on-disk layout, the
//! job database, and the file helpers the records are written with (the
//! records themselves are `crate::records`).
//!
//! ```text
//! DATA/scenes/ID/scene.json   scene record (written before the folder appears)
//! DATA/scenes/ID/data/...     the uploaded dataset as extracted
//! DATA/models/ID.ckpt         checkpoint (engine::train::persist, atomic)
//! DATA/models/ID.json         model record
//! DATA/videos/ID.bin, ID.json video file and record
//! DATA/jobs.redb              job records (redb; only enqueued, started and final states;
//!                             held open by the scheduler, see jobs::journal)
//! DATA/tmp/                   uploads being extracted, scenes being deleted
//! ```
//!
//! Job records live in an embedded database (redb: transactions are atomic
//! and durable when they commit); the large artifacts are files beside it.
//! Every file is written atomically ([`write_atomic`]) and every folder
//! appears by one `rename`, so a crash leaves either the old state or the
//! new one. `tmp/` is emptied at start-up.

use std::io;
use std::path::{Path, PathBuf};

use redb::{ReadableDatabase, ReadableTable};
use serde::{Serialize, de::DeserializeOwned};

use crate::engine::io::fsio::write_atomic;
use crate::records::{ModelInfo, SceneInfo, VideoInfo};
pub use crate::system::now_ms;

/// The name of a video job's frames folder before its job's id.
pub const VIDEO_FRAMES_PREFIX: &str = ".frames-";

/// Paths of the data directory.
#[derive(Clone, Debug)]
pub struct DataDir {
    pub root: PathBuf,
}

/// The job table: id -> the job record as JSON.
const JOBS: redb::TableDefinition<&str, &[u8]> = redb::TableDefinition::new("jobs");

fn db_error(e: impl std::fmt::Display) -> io::Error {
    io::Error::other(format!("job database: {e}"))
}

/// The open job database: job records as JSON by id. Each write is one
/// committed transaction (atomic and durable when it returns).
pub struct JobDb(redb::Database);

impl JobDb {
    /// Writes a job record.
    pub fn put<T: Serialize>(&self, id: &str, job: &T) -> io::Result<()> {
        let bytes = serde_json::to_vec(job).map_err(io::Error::other)?;
        let tx = self.0.begin_write().map_err(db_error)?;
        {
            let mut t = tx.open_table(JOBS).map_err(db_error)?;
            t.insert(id, bytes.as_slice()).map_err(db_error)?;
        }
        tx.commit().map_err(db_error)
    }

    /// Every job record (in id order).
    pub fn list<T: DeserializeOwned>(&self) -> io::Result<Vec<T>> {
        let tx = self.0.begin_read().map_err(db_error)?;
        let t = match tx.open_table(JOBS) {
            Ok(t) => t,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(Vec::new()),
            Err(e) => return Err(db_error(e)),
        };
        let mut v = Vec::new();
        for row in t.iter().map_err(db_error)? {
            let (k, bytes) = row.map_err(db_error)?;
            let job =
                serde_json::from_slice(bytes.value()).map_err(|e| db_error(format!("record '{}': {e}", k.value())))?;
            v.push(job);
        }
        Ok(v)
    }

    /// One job record.
    pub fn get<T: DeserializeOwned>(&self, id: &str) -> io::Result<Option<T>> {
        let tx = self.0.begin_read().map_err(db_error)?;
        let t = match tx.open_table(JOBS) {
            Ok(t) => t,
            Err(redb::TableError::TableDoesNotExist(_)) => return Ok(None),
            Err(e) => return Err(db_error(e)),
        };
        match t.get(id).map_err(db_error)? {
            Some(bytes) => serde_json::from_slice(bytes.value()).map(Some).map_err(db_error),
            None => Ok(None),
        }
    }

    /// Whether the database answers a read (readiness checks).
    pub fn check(&self) -> io::Result<()> {
        let tx = self.0.begin_read().map_err(db_error)?;
        match tx.open_table(JOBS) {
            Ok(_) | Err(redb::TableError::TableDoesNotExist(_)) => Ok(()),
            Err(e) => Err(db_error(e)),
        }
    }

    /// Removes a job record; `false` if there was none.
    pub fn remove(&self, id: &str) -> io::Result<bool> {
        let tx = self.0.begin_write().map_err(db_error)?;
        let removed = {
            let mut t = tx.open_table(JOBS).map_err(db_error)?;
            t.remove(id).map_err(db_error)?.is_some()
        };
        tx.commit().map_err(db_error)?;
        Ok(removed)
    }
}

impl DataDir {
    /// Creates the layout (if missing) and clears leftovers of interrupted
    /// uploads and deletions.
    pub fn open(root: &Path) -> io::Result<Self> {
        let s = Self { root: root.to_path_buf() };
        for d in ["scenes", "models", "videos"] {
            std::fs::create_dir_all(s.root.join(d))?;
        }
        let tmp = s.tmp_dir();
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)?;
        }
        std::fs::create_dir_all(&tmp)?;
        let removed = remove_stale_temporaries(&s.root, &s.scenes_dir())?;
        if removed > 0 {
            tracing::info!(files = removed, "removed temporary files left by an interrupted write");
        }
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
    /// Where an upload of scene `id` is written and checked before it
    /// appears as `scenes/ID` in one rename.
    pub fn staging_dir(&self, id: &str) -> PathBuf {
        self.tmp_dir().join(id)
    }
    /// Where a scene's folder is moved to disappear in one rename before its
    /// files are removed (in `tmp/`, emptied at start-up should that stop).
    pub fn scene_trash(&self, id: &str) -> PathBuf {
        self.tmp_dir().join(format!("deleted_{id}"))
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
    pub fn jobs_db(&self) -> PathBuf {
        self.root.join("jobs.redb")
    }

    /// Opens the job database (creating it if missing). redb locks the file
    /// while it is open: the scheduler opens it once and holds it; see
    /// `jobs::journal`.
    pub fn open_jobs(&self) -> io::Result<JobDb> {
        redb::Database::create(self.jobs_db()).map(JobDb).map_err(db_error)
    }

    /// One job record, read from a database opened for this call: for tools
    /// and tests while no server holds it.
    pub fn get_job<T: DeserializeOwned>(&self, id: &str) -> io::Result<Option<T>> {
        self.open_jobs()?.get(id)
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
    /// The folder of a video job's saved frames (kept across a crash).
    pub fn video_frames_dir(&self, job_id: &str) -> PathBuf {
        self.videos_dir().join(format!("{VIDEO_FRAMES_PREFIX}{job_id}"))
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

    pub fn list_videos(&self) -> io::Result<Vec<VideoInfo>> {
        let mut v: Vec<VideoInfo> = list_json(&self.videos_dir())?;
        v.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        Ok(v)
    }

    /// Removes a model: its record first, then its checkpoint, so a record
    /// never points at a missing file (a crash between the two leaves an
    /// orphaned checkpoint, which the next start-up removes).
    pub fn remove_model(&self, id: &str) -> io::Result<()> {
        remove_file_if_exists(&self.model_record(id))?;
        remove_file_if_exists(&self.checkpoint(id))
    }

    /// Removes a video: its record first, then its file.
    pub fn remove_video(&self, id: &str) -> io::Result<()> {
        remove_file_if_exists(&self.video_record(id))?;
        remove_file_if_exists(&self.video_file(id))
    }

    /// Bytes of the files under each folder of the data directory.
    pub fn disk_usage(&self) -> io::Result<DiskUsage> {
        Ok(DiskUsage {
            scenes: tree_bytes(&self.scenes_dir())?,
            models: tree_bytes(&self.models_dir())?,
            videos: tree_bytes(&self.videos_dir())?,
            tmp: tree_bytes(&self.tmp_dir())?,
        })
    }

    pub fn list_models(&self) -> io::Result<Vec<ModelInfo>> {
        let mut v: Vec<ModelInfo> = list_json(&self.models_dir())?;
        v.sort_by(|a, b| (a.created_at, &a.id).cmp(&(b.created_at, &b.id)));
        Ok(v)
    }
}

/// Removes every temporary file of an interrupted atomic write
/// ([`crate::engine::io::fsio::is_temporary`]) below `dir`, except inside the
/// uploaded datasets (`scenes/ID/data/`, the user's files, which no atomic
/// write of ours touches). Returns how many it removed. Only for start-up:
/// a running writer's temporary file would be removed too.
fn remove_stale_temporaries(dir: &Path, scenes: &Path) -> io::Result<usize> {
    let mut removed = 0;
    for e in std::fs::read_dir(dir)? {
        let e = e?;
        let path = e.path();
        let kind = e.file_type()?;
        if kind.is_dir() {
            let dataset = path.parent().and_then(Path::parent) == Some(scenes) && e.file_name() == "data";
            if !dataset {
                removed += remove_stale_temporaries(&path, scenes)?;
            }
        } else if kind.is_file() && crate::engine::io::fsio::is_temporary(&e.file_name()) {
            std::fs::remove_file(&path)?;
            removed += 1;
        }
    }
    Ok(removed)
}

/// Ids are made here and only ever contain `[a-z0-9_]`: a path component
/// that cannot escape its folder.
pub fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= 64 && id.bytes().all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

/// A fresh id: `PREFIX_` and a UUID v7 in 32 lower-case hex digits (48
/// bits of milliseconds, then 74 random bits, monotonic within a process):
/// ids sort by creation, and two processes (two containers, both pid 1)
/// making ids in the same millisecond do not collide.
pub fn new_id(prefix: &str) -> String {
    format!("{prefix}_{}", uuid::Uuid::now_v7().simple())
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

/// Removes a file; a missing one is not an error.
pub fn remove_file_if_exists(path: &Path) -> io::Result<()> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

/// Bytes of the files under `dir` (recursively; links are not followed,
/// entries that vanish meanwhile are skipped).
pub fn tree_bytes(dir: &Path) -> io::Result<u64> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(0),
        Err(e) => return Err(e),
    };
    let mut total = 0;
    for e in entries {
        let e = e?;
        let meta = match e.metadata() {
            Ok(m) => m,
            Err(err) if err.kind() == io::ErrorKind::NotFound => continue,
            Err(err) => return Err(err),
        };
        total += if meta.is_dir() { tree_bytes(&e.path())? } else { meta.len() };
    }
    Ok(total)
}

/// The two folders a scene's files can be in: its posed dataset (`data/`,
/// which the record's `root` points into) or the photos of a photo-only
/// upload waiting for pose estimation (`upload/`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScenePart {
    Data,
    Upload,
}

impl ScenePart {
    /// The part's folder in the scene's folder.
    pub const fn dir_name(self) -> &'static str {
        match self {
            ScenePart::Data => "data",
            ScenePart::Upload => "upload",
        }
    }
}

/// A file or folder on this machine, valid while this value is held: the
/// data directory's own file for the embedded store (which holds nothing
/// more), or a copy in a local cache that a remote store keeps from being
/// evicted until the value is dropped.
pub struct Local {
    pub path: PathBuf,
    /// What keeps `path` in place (a cache pin); `None` for files that stay.
    _hold: Option<Box<dyn Send + Sync>>,
}

impl Local {
    /// A path that stays valid without being held.
    pub fn at(path: PathBuf) -> Self {
        Self { path, _hold: None }
    }

    /// A path that stays valid while `hold` lives.
    pub fn held(path: PathBuf, hold: Box<dyn Send + Sync>) -> Self {
        Self { path, _hold: Some(hold) }
    }
}

impl std::fmt::Debug for Local {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Local").field("path", &self.path).field("held", &self._hold.is_some()).finish()
    }
}

/// Disk use of the data directory's folders, in bytes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DiskUsage {
    pub scenes: u64,
    pub models: u64,
    pub videos: u64,
    pub tmp: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_held_path_keeps_its_hold_until_dropped() {
        let hold = std::sync::Arc::new(());
        let local = Local::held(PathBuf::from("/x"), Box::new(hold.clone()));
        assert_eq!(std::sync::Arc::strong_count(&hold), 2);
        drop(local);
        assert_eq!(std::sync::Arc::strong_count(&hold), 1);
    }

    #[test]
    fn job_records_round_trip_through_the_database() {
        let dir = tempfile::tempdir().unwrap();
        let s = DataDir::open(dir.path()).unwrap();
        let db = s.open_jobs().unwrap();
        assert_eq!(db.list::<serde_json::Value>().unwrap(), Vec::<serde_json::Value>::new());
        assert_eq!(db.get::<serde_json::Value>("job_a").unwrap(), None);
        db.put("job_b", &serde_json::json!({ "id": "job_b", "n": 1 })).unwrap();
        db.put("job_a", &serde_json::json!({ "id": "job_a" })).unwrap();
        db.put("job_b", &serde_json::json!({ "id": "job_b", "n": 2 })).unwrap();
        db.put("job_c", &serde_json::json!({ "id": "job_c" })).unwrap();
        assert!(db.remove("job_c").unwrap() && !db.remove("job_c").unwrap());
        // The file is locked while open: a second handle waits for a restart.
        assert!(s.open_jobs().is_err());
        drop(db);
        // A second handle (as after a restart) sees what was committed.
        let again = DataDir::open(dir.path()).unwrap();
        let all: Vec<serde_json::Value> = again.open_jobs().unwrap().list().unwrap();
        assert_eq!(all, vec![serde_json::json!({ "id": "job_a" }), serde_json::json!({ "id": "job_b", "n": 2 })]);
        assert_eq!(again.get_job::<serde_json::Value>("job_b").unwrap().unwrap()["n"], 2);
    }

    #[test]
    fn start_up_removes_stale_temporaries_but_not_uploaded_files() {
        let dir = tempfile::tempdir().unwrap();
        let s = DataDir::open(dir.path()).unwrap();
        let stale = [
            s.models_dir().join(".mdl_a.ckpt.tmp19226.2"),
            s.videos_dir().join(".vid_a.bin.tmp7.0"),
            s.scene_dir("scn_a").join(".scene.json.tmp3.1"),
            dir.path().join(".jobs.redb.tmp1.1"),
        ];
        let kept = [
            s.models_dir().join("mdl_a.ckpt"),
            s.scene_dir("scn_a").join("data").join(".img.png.tmp1.1"),
            s.scene_dir("scn_a").join("data").join("sub").join(".x.tmp2.2"),
        ];
        for p in stale.iter().chain(&kept) {
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, b"partial").unwrap();
        }
        DataDir::open(dir.path()).unwrap();
        for p in &stale {
            assert!(!p.exists(), "{} should be gone", p.display());
        }
        for p in &kept {
            assert!(p.exists(), "{} should stay", p.display());
        }
    }

    #[test]
    fn ids_are_valid_distinct_and_sorted_by_creation() {
        let ids: Vec<String> = (0..20_000).map(|_| new_id("job")).collect();
        assert!(ids.iter().all(|id| valid_id(id) && id.len() == 36 && id.starts_with("job_")), "{}", ids[0]);
        assert!(ids.windows(2).all(|w| w[0] < w[1]), "not increasing");
        // Four threads at once: no repeats.
        let all: std::collections::HashSet<String> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..4).map(|_| s.spawn(|| (0..5000).map(|_| new_id("scn")).collect::<Vec<_>>())).collect();
            hs.into_iter().flat_map(|h| h.join().unwrap()).collect()
        });
        assert_eq!(all.len(), 20_000);
        // The first 12 hex digits are the creation time in milliseconds.
        let ms = u64::from_str_radix(&ids[0][4..16], 16).unwrap();
        assert!(ms.abs_diff(now_ms()) < 60_000, "{ms}");
        assert!(!valid_id("../x") && !valid_id("") && !valid_id("A"));
    }
}
