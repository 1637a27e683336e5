//! The contract on the PostgreSQL job store (a throwaway cluster per check,
//! `common::pg`) with the embedded artifact store over a temporary data
//! directory.
//!
//! Two differences are inherent, and the only adaptations:
//!
//! - The embedded artifact store leaves an upload's files in `tmp/ID/` for
//!   the embedded job store's insert to rename into `scenes/ID/` with the
//!   record; the PostgreSQL job store stores records only and cannot move
//!   files. [`PublishingArtifacts`] therefore moves them at
//!   `put_scene_files`, as the object store will store them (nothing is
//!   listed before the record is inserted either way: listings come from
//!   the records).
//! - No worker runs PostgreSQL jobs yet (design step 8), so the checks that
//!   need jobs to run (`running_jobs_stop_on_cancel_and_keep_their_model`)
//!   are left out; `pg_jobs` covers what this store does for a running job
//!   (cancel reaching the worker's heartbeat, the in-use refusals) by
//!   playing the worker through `PgQueue`.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use radiance::backend::embedded::EmbeddedArtifacts;
use radiance::backend::pg::{Database, PgJobStore, PgStoreConfig, QueueConfig};
use radiance::backend::{Artifact, ArtifactStore, Fut};
use radiance::datadir::{DataDir, DiskUsage, Local, ScenePart};
use radiance::records::{ModelInfo, SceneInfo, VideoInfo};

use crate::common::pg::Pg;
use crate::contract::{Opening, Settings, Stores};

/// The embedded artifact store, storing an upload's part in `scenes/ID/`
/// when it is put (see the module comment).
pub struct PublishingArtifacts {
    inner: EmbeddedArtifacts,
    storage: DataDir,
}

impl PublishingArtifacts {
    pub fn open(data_dir: &Path) -> io::Result<Self> {
        let storage = DataDir::open(data_dir)?;
        Ok(Self { inner: EmbeddedArtifacts::new(storage.clone()), storage })
    }
}

impl ArtifactStore for PublishingArtifacts {
    fn staging_dir(&self, id: &str) -> PathBuf {
        self.inner.staging_dir(id)
    }

    /// The embedded put (which checks the id and stages the part in
    /// `tmp/ID/<part>`), then a rename into `scenes/ID/<part>`.
    fn put_scene_files<'a>(&'a self, id: &'a str, part: ScenePart, files: &'a Path) -> Fut<'a, io::Result<()>> {
        Box::pin(async move {
            self.inner.put_scene_files(id, part, files).await?;
            let scene = self.storage.scene_dir(id);
            std::fs::create_dir_all(&scene)?;
            std::fs::rename(self.storage.staging_dir(id).join(part.dir_name()), scene.join(part.dir_name()))
        })
    }

    fn scene_files<'a>(&'a self, scene: &'a SceneInfo, part: ScenePart) -> Fut<'a, io::Result<Local>> {
        self.inner.scene_files(scene, part)
    }

    fn checkpoint<'a>(&'a self, model: &'a ModelInfo) -> Fut<'a, io::Result<Local>> {
        self.inner.checkpoint(model)
    }

    fn video<'a>(&'a self, video: &'a VideoInfo) -> Fut<'a, io::Result<Vec<u8>>> {
        self.inner.video(video)
    }

    fn usage(&self) -> Fut<'_, io::Result<DiskUsage>> {
        self.inner.usage()
    }

    fn free_space(&self) -> Fut<'_, io::Result<Option<u64>>> {
        self.inner.free_space()
    }

    fn ready(&self) -> Fut<'_, io::Result<()>> {
        self.inner.ready()
    }

    fn remove<'a>(&'a self, what: Artifact<'a>) -> Fut<'a, io::Result<()>> {
        self.inner.remove(what)
    }
}

/// A PostgreSQL job store on a fresh cluster, migrated, with `max_queued`.
/// The cluster stops when the returned `Pg` is dropped.
pub async fn open_pg(max_queued: usize) -> (PgJobStore, Database, Pg) {
    let pg = Pg::start().await;
    let db = Database::parse(&pg.database().await).unwrap();
    let config = PgStoreConfig { pool_size: 4, queue: QueueConfig { max_queued } };
    let store = tokio::time::timeout(std::time::Duration::from_secs(30), PgJobStore::open(&db, config))
        .await
        .expect("opened within 30 s")
        .unwrap();
    (store, db, pg)
}

fn open(settings: Settings) -> Opening {
    Box::pin(async move {
        assert!(!settings.run_jobs, "no worker runs PostgreSQL jobs yet");
        let (jobs, _db, pg) = open_pg(settings.max_queued).await;
        let dir = tempfile::tempdir().unwrap();
        let artifacts = PublishingArtifacts::open(dir.path()).unwrap();
        // Dropped after the stores: the pool goes before the server.
        Stores { jobs: Arc::new(jobs), artifacts: Arc::new(artifacts), _keep: Box::new((pg, dir)) }
    })
}

contract_tests!(
    open;
    scenes_appear_with_their_files_or_not_at_all,
    jobs_keep_their_order_and_read_back_as_enqueued,
    refusals_name_what_is_missing_or_not_ready,
    a_full_queue_refuses_and_a_photo_upload_comes_with_its_job_or_not_at_all,
    queued_jobs_cancel_at_once_and_deletes_happen_once,
    ready_until_shut_down,
);
