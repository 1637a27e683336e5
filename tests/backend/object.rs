//! The contract on the embedded job store with the object artifact store
//! (`ObjectArtifacts`), over a `file://` store in a temporary folder
//! (`file::`) and over a real S3 server (`s3::`, `common::s3`).
//!
//! The embedded scheduler runs the jobs and reads and writes its own data
//! directory (no worker publishes to an object store yet: design step 8),
//! so [`MirroredArtifacts`] plays the publishing side of that step, and is
//! the only adaptation:
//!
//! - `put_scene_files` stores the upload in the object store (a tar) and
//!   also stages a copy for the embedded scheduler's jobs;
//! - `checkpoint` and `video` put the embedded store's file into the object
//!   store (as a worker's publish will) and answer from the object store;
//!   once the embedded file is gone (its record deleted), they answer
//!   `NotFound`, as the object store will once deletes reach it.
//!
//! Reads of scenes (through the tar and the cache), checkpoints (content
//! addressed, through the cache), videos, usage and readiness are the
//! object store's own.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use radiance::backend::object::ObjectArtifacts;
use radiance::backend::{Artifact, ArtifactStore, Fut, embedded};
use radiance::datadir::{DiskUsage, Local, ScenePart};
use radiance::jobs::SchedulerConfig;
use radiance::records::{ModelInfo, SceneInfo, VideoInfo};

use crate::bucket::{Backend, Bucket};
use crate::contract::{Opening, Settings, Stores};

/// The object store, fed the embedded scheduler's files (see the module
/// comment).
pub struct MirroredArtifacts {
    embedded: embedded::EmbeddedArtifacts,
    object: ObjectArtifacts,
}

/// Copies the folder `from` to the new folder `to`.
fn copy_tree(from: &Path, to: &Path) -> io::Result<()> {
    std::fs::create_dir(to)?;
    for item in std::fs::read_dir(from)? {
        let item = item?;
        let dest = to.join(item.file_name());
        if item.file_type()?.is_dir() {
            copy_tree(&item.path(), &dest)?;
        } else {
            std::fs::copy(item.path(), dest)?;
        }
    }
    Ok(())
}

impl ArtifactStore for MirroredArtifacts {
    fn staging_dir(&self, id: &str) -> PathBuf {
        self.embedded.staging_dir(id)
    }

    /// The object store's put of a copy (which it removes once stored),
    /// then the embedded put of the files for the scheduler's jobs.
    fn put_scene_files<'a>(&'a self, id: &'a str, part: ScenePart, files: &'a Path) -> Fut<'a, io::Result<()>> {
        Box::pin(async move {
            let copy = files.with_file_name(format!("{}-object", part.dir_name()));
            copy_tree(files, &copy)?;
            self.object.put_scene_files(id, part, &copy).await?;
            self.embedded.put_scene_files(id, part, files).await
        })
    }

    fn scene_files<'a>(&'a self, scene: &'a SceneInfo, part: ScenePart) -> Fut<'a, io::Result<Local>> {
        self.object.scene_files(scene, part)
    }

    fn checkpoint<'a>(&'a self, model: &'a ModelInfo) -> Fut<'a, io::Result<Local>> {
        Box::pin(async move {
            let file = self.embedded.checkpoint(model).await?;
            if !file.path.exists() {
                return Err(io::Error::new(io::ErrorKind::NotFound, format!("model {}: no checkpoint", model.id)));
            }
            self.object.put_checkpoint(&model.id, &file.path).await?;
            self.object.checkpoint(model).await
        })
    }

    fn video<'a>(&'a self, video: &'a VideoInfo) -> Fut<'a, io::Result<Vec<u8>>> {
        Box::pin(async move {
            let bytes = self.embedded.video(video).await?;
            self.object.put_video(&video.id, bytes).await?;
            self.object.video(video).await
        })
    }

    fn usage(&self) -> Fut<'_, io::Result<DiskUsage>> {
        self.object.usage()
    }

    fn free_space(&self) -> Fut<'_, io::Result<Option<u64>>> {
        self.object.free_space()
    }

    fn ready(&self) -> Fut<'_, io::Result<()>> {
        self.object.ready()
    }

    /// The object store's copies (the embedded job store removed its own
    /// files with the record).
    fn remove<'a>(&'a self, what: Artifact<'a>) -> Fut<'a, io::Result<()>> {
        self.object.remove(what)
    }
}

/// The embedded job store over `dir/data` (checkpoints every 0.2 s of
/// training), the object store on `backend` (see `bucket`).
fn open(backend: Backend, settings: Settings) -> Opening {
    Box::pin(async move {
        let dir = tempfile::tempdir().unwrap();
        let config = SchedulerConfig {
            max_queued: settings.max_queued,
            run_jobs: settings.run_jobs,
            checkpoint_every: 0.2,
            ..SchedulerConfig::default()
        };
        let data = dir.path().join("data");
        let opened = tokio::task::spawn_blocking(move || embedded::open(&data, config)).await.unwrap();
        let (jobs, embedded) = opened.unwrap();
        let bucket = Bucket::new(backend, dir.path()).await;
        let object = bucket.open(&dir.path().join("data"));
        let artifacts = MirroredArtifacts { embedded, object };
        // Dropped after the stores: the S3 server before its folder.
        Stores { jobs: Arc::new(jobs), artifacts: Arc::new(artifacts), _keep: Box::new((bucket, dir)) }
    })
}

mod file {
    use super::*;

    fn open_file(settings: Settings) -> Opening {
        open(Backend::File, settings)
    }

    contract_tests!(open_file);
}

mod s3 {
    use super::*;

    fn open_s3(settings: Settings) -> Opening {
        open(Backend::S3, settings)
    }

    contract_tests!(open_s3);
}
