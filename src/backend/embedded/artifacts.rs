//! The embedded artifact store: the data directory's files, in place.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use super::{blocking, invalid};
use crate::backend::{Artifact, ArtifactStore, Fut};
use crate::datadir::{DataDir, DiskUsage, Local, ScenePart, valid_id};
use crate::records::{ModelInfo, SceneInfo, VideoInfo};

/// The data directory's files.
pub struct EmbeddedArtifacts {
    storage: DataDir,
    /// Numbers the files the readiness probe writes (two probes at once
    /// write two files).
    probes: AtomicU64,
}

impl EmbeddedArtifacts {
    pub fn new(storage: DataDir) -> Self {
        Self { storage, probes: AtomicU64::new(0) }
    }
}

/// Moves an upload's files to the `part` folder of its staging folder
/// (`tmp/ID/data` or `tmp/ID/upload`), where the scene's insert finds them;
/// files already there stay.
fn put_scene_files(storage: &DataDir, id: &str, part: ScenePart, files: &Path) -> io::Result<()> {
    if !valid_id(id) {
        return Err(invalid(format!("'{id}' is not a valid scene id")));
    }
    let dest = storage.staging_dir(id).join(part.dir_name());
    if files != dest {
        std::fs::rename(files, &dest)?;
    }
    Ok(())
}

/// The data directory's folders are there, and a file can be made (and
/// removed) in `tmp/`: what uploads and jobs need.
fn check_writable(storage: &DataDir, probe: u64) -> io::Result<()> {
    let dirs = [storage.scenes_dir(), storage.models_dir(), storage.videos_dir(), storage.tmp_dir()];
    for dir in &dirs {
        if !std::fs::metadata(dir).map_err(|e| at(dir, e))?.is_dir() {
            return Err(at(dir, io::Error::other("not a folder")));
        }
    }
    let file = storage.tmp_dir().join(format!(".ready-{}-{probe}", std::process::id()));
    std::fs::File::create_new(&file).map_err(|e| at(&file, e))?;
    std::fs::remove_file(&file).map_err(|e| at(&file, e))
}

/// `e` naming the path it is about.
fn at(path: &Path, e: io::Error) -> io::Error {
    io::Error::new(e.kind(), format!("{}: {e}", path.display()))
}

impl ArtifactStore for EmbeddedArtifacts {
    /// `tmp/ID/` (emptied at start-up, should the server stop mid-upload).
    fn staging_dir(&self, id: &str) -> PathBuf {
        self.storage.staging_dir(id)
    }

    fn put_scene_files<'a>(&'a self, id: &'a str, part: ScenePart, files: &'a Path) -> Fut<'a, io::Result<()>> {
        let (storage, id, files) = (self.storage.clone(), id.to_string(), files.to_path_buf());
        Box::pin(async move { blocking(move || put_scene_files(&storage, &id, part, &files)).await? })
    }

    /// `scenes/ID/`, which holds both parts.
    fn scene_files<'a>(&'a self, scene: &'a SceneInfo, _part: ScenePart) -> Fut<'a, io::Result<Local>> {
        Box::pin(std::future::ready(Ok(Local::at(self.storage.scene_dir(&scene.id)))))
    }

    /// `models/ID.ckpt`.
    fn checkpoint<'a>(&'a self, model: &'a ModelInfo) -> Fut<'a, io::Result<Local>> {
        Box::pin(std::future::ready(Ok(Local::at(self.storage.checkpoint(&model.id)))))
    }

    /// `videos/ID.bin`, whole.
    fn video<'a>(&'a self, video: &'a VideoInfo) -> Fut<'a, io::Result<Vec<u8>>> {
        let path = self.storage.video_file(&video.id);
        Box::pin(async move { blocking(move || std::fs::read(path)).await? })
    }

    /// Bytes under each folder of the data directory.
    fn usage(&self) -> Fut<'_, io::Result<DiskUsage>> {
        let storage = self.storage.clone();
        Box::pin(async move { blocking(move || storage.disk_usage()).await? })
    }

    /// Free space on the data directory's file system (`None` where the
    /// system does not say).
    fn free_space(&self) -> Fut<'_, io::Result<Option<u64>>> {
        let root = self.storage.root.clone();
        Box::pin(async move { blocking(move || crate::system::free_disk(&root)).await })
    }

    fn ready(&self) -> Fut<'_, io::Result<()>> {
        let (storage, probe) = (self.storage.clone(), self.probes.fetch_add(1, Ordering::Relaxed));
        Box::pin(async move { blocking(move || check_writable(&storage, probe)).await? })
    }

    /// Nothing: the embedded job store's deletes remove the files with
    /// their records.
    fn remove<'a>(&'a self, _what: Artifact<'a>) -> Fut<'a, io::Result<()>> {
        Box::pin(std::future::ready(Ok(())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn store(dir: &Path) -> (EmbeddedArtifacts, DataDir) {
        let storage = DataDir::open(dir).unwrap();
        (EmbeddedArtifacts::new(storage.clone()), storage)
    }

    #[tokio::test]
    async fn uploads_are_staged_by_part_and_show_nowhere_else() {
        let dir = tempfile::tempdir().unwrap();
        let (artifacts, storage) = store(dir.path());
        let staging = artifacts.staging_dir("scn_a");
        assert_eq!(staging, storage.tmp_dir().join("scn_a"));
        let data = staging.join("data");
        std::fs::create_dir_all(&data).unwrap();
        std::fs::write(data.join("a.jpg"), b"jpeg").unwrap();
        // Photos waiting for pose estimation move to `upload/`...
        artifacts.put_scene_files("scn_a", ScenePart::Upload, &data).await.unwrap();
        assert_eq!(std::fs::read(staging.join("upload/a.jpg")).unwrap(), b"jpeg");
        assert!(!data.exists());
        // ... a dataset stays in `data/`.
        std::fs::create_dir_all(&data).unwrap();
        artifacts.put_scene_files("scn_a", ScenePart::Data, &data).await.unwrap();
        assert!(data.is_dir());
        // Nothing is a scene before its record is inserted.
        assert_eq!(std::fs::read_dir(storage.scenes_dir()).unwrap().count(), 0);
        let e = artifacts.put_scene_files("../a", ScenePart::Data, &data).await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
        assert!(e.to_string().contains("'../a'"), "{e}");
    }

    #[tokio::test]
    async fn ready_names_an_unusable_data_directory_and_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (artifacts, storage) = store(dir.path());
        artifacts.ready().await.unwrap();
        artifacts.ready().await.unwrap();
        assert_eq!(std::fs::read_dir(storage.tmp_dir()).unwrap().count(), 0, "the probes are removed");

        std::fs::remove_dir(storage.tmp_dir()).unwrap();
        let e = artifacts.ready().await.unwrap_err();
        assert!(e.to_string().contains(&storage.tmp_dir().display().to_string()), "{e}");
        std::fs::write(storage.tmp_dir(), b"").unwrap();
        let e = artifacts.ready().await.unwrap_err();
        assert!(e.to_string().ends_with("not a folder"), "{e}");
        std::fs::remove_file(storage.tmp_dir()).unwrap();
        std::fs::create_dir(storage.tmp_dir()).unwrap();
        artifacts.ready().await.unwrap();
    }

    #[tokio::test]
    #[cfg(target_os = "linux")]
    async fn free_space_is_the_data_directorys_file_system() {
        let dir = tempfile::tempdir().unwrap();
        let (artifacts, storage) = store(dir.path());
        let free = artifacts.free_space().await.unwrap();
        assert_eq!(free.is_some(), crate::system::free_disk(&storage.root).is_some());
        assert!(free.is_some_and(|f| f > 0), "{free:?}");
    }
}
