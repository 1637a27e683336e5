//! The object-store artifact store (docs/design/scale-out.md, section 2.4):
//! scenes, checkpoints and videos as objects in a bucket (`s3://`) or a
//! folder (`file://`), shared by many nodes, with a bounded local cache of
//! what this node reads.
//!
//! Object layout:
//!
//! | Key | Content |
//! |---|---|
//! | `scenes/<id>/dataset.tar` | a scene's `data/` folder, an uncompressed tar |
//! | `scenes/<id>/upload.tar` | the photos of a photo-only upload, a tar |
//! | `models/<id>/<sha256>.ckpt` | a checkpoint, named by its content |
//! | `videos/<id>.bin` | a video's bytes |
//!
//! An object appears whole or not at all (`upload`); it becomes part of the
//! service when the job store commits its record. Reads go through the
//! cache (`cache`): a scene is unpacked once to `DATA/cache/scenes/`, a
//! checkpoint fetched once to `DATA/cache/models/`.
//!
//! Its S3 settings come from the AWS environment with [`S3Options`] over
//! it (`s3`). `radiance serve` uses it in distributed mode
//! (`--object-store`); its workers put checkpoints and videos with the
//! inherent `put_*` methods.

use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures_util::StreamExt;
use object_store::path::Path as Key;
use object_store::{ObjectStore, ObjectStoreExt};
use tokio::io::AsyncWriteExt;

use crate::backend::{Artifact, ArtifactStore, Fut};
use crate::datadir::{DiskUsage, Local, ScenePart, valid_id};
use crate::records::{ModelInfo, SceneInfo, VideoInfo};

pub mod cache;
pub mod s3;
pub mod upload;
pub mod url;

pub use cache::{Cache, Pin};
pub use s3::{S3Keys, S3Options};
pub use url::open_url;

/// How an [`ObjectArtifacts`] writes and caches.
#[derive(Clone, Debug)]
pub struct ObjectConfig {
    /// Uploads up to this size are one PUT; larger ones are multipart
    /// uploads of parts this size (S3 wants at least 5 MiB but the last).
    pub part_size: usize,
    /// Bound on the local cache, bytes (entries in use may exceed it).
    pub cache_max_bytes: u64,
    /// How long `ready` waits for the store to answer a listing.
    pub ready_timeout: Duration,
    /// S3 settings over the AWS environment's (`s3://` stores only; see
    /// [`s3`]): what `serve`'s `--s3-endpoint` and `--s3-region` set.
    pub s3: S3Options,
}

impl Default for ObjectConfig {
    /// 8 MiB parts (`--upload-part-mb`), a 4 GiB cache (`--cache-max-mb`),
    /// 1 s for readiness, S3 settings from the environment alone.
    fn default() -> Self {
        Self {
            part_size: 8 << 20,
            cache_max_bytes: 4096 << 20,
            ready_timeout: Duration::from_secs(1),
            s3: S3Options::default(),
        }
    }
}

/// What a put stored: the content's SHA-256 (lowercase hex) and size.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Stored {
    pub sha256: String,
    pub size: u64,
}

/// Scenes, checkpoints and videos in an object store, read through a
/// local cache.
pub struct ObjectArtifacts {
    store: Arc<dyn ObjectStore>,
    /// What readiness errors call the store: its URL.
    name: String,
    /// `DATA/tmp`: where uploads are staged before they are stored.
    tmp: PathBuf,
    cache: Arc<Cache>,
    config: ObjectConfig,
}

impl ObjectArtifacts {
    /// The store `url` names (see [`open_url`]), with its local folders
    /// (`tmp/`, `cache/`) in `data_dir`. An `s3://` store's settings are the
    /// AWS environment's with `config.s3` over them ([`s3`]); nothing is
    /// asked of the server yet (`ready` does).
    pub fn open(data_dir: &Path, url: &str, config: ObjectConfig) -> io::Result<Self> {
        let mut opened = Self::with_store(data_dir, open_url(url, &config.s3)?, config)?;
        opened.name = url.to_string();
        Ok(opened)
    }

    /// `store`, with its local folders in `data_dir`; the cache's leftover
    /// temporary files are removed and its entries indexed, and `tmp/` is
    /// emptied: what is there is staged uploads of a node that died before
    /// storing them (a kill -9 mid-upload), which nobody will finish.
    pub fn with_store(data_dir: &Path, store: Arc<dyn ObjectStore>, config: ObjectConfig) -> io::Result<Self> {
        let tmp = data_dir.join("tmp");
        if tmp.exists() {
            let leftovers = std::fs::read_dir(&tmp)?.count();
            std::fs::remove_dir_all(&tmp)?;
            if leftovers > 0 {
                tracing::info!(entries = leftovers, "removed uploads staged by an interrupted run");
            }
        }
        std::fs::create_dir_all(&tmp)?;
        let cache = Cache::open(&data_dir.join("cache"), config.cache_max_bytes)?;
        let name = store.to_string();
        Ok(Self { store, name, tmp, cache, config })
    }

    /// The object store underneath.
    pub fn store(&self) -> &Arc<dyn ObjectStore> {
        &self.store
    }

    /// The local cache.
    pub fn cache(&self) -> &Arc<Cache> {
        &self.cache
    }

    /// Stores the checkpoint `file` of model `model_id` at
    /// `models/<id>/<sha256>.ckpt`. The same bytes make the same key, so a
    /// checkpoint already there is not uploaded again.
    pub async fn put_checkpoint(&self, model_id: &str, file: &Path) -> io::Result<Stored> {
        check_id(model_id, "model")?;
        let path = file.to_path_buf();
        let (sha256, size) = blocking(move || upload::sha256_file(&path)).await??;
        let key = checkpoint_key(model_id, &sha256);
        match self.store.head(&key).await {
            Ok(_) => {}
            Err(object_store::Error::NotFound { .. }) => {
                upload::put_file(&self.store, &key, file.to_path_buf(), self.config.part_size).await?;
            }
            Err(e) => return Err(io_error(e)),
        }
        Ok(Stored { sha256, size })
    }

    /// Downloads checkpoint `sha256` of model `model_id` to the new file
    /// `dest` (a worker resuming a job writes its session's checkpoint
    /// there), through a temporary name beside it: `dest` appears whole.
    pub async fn fetch_checkpoint(&self, model_id: &str, sha256: &str, dest: &Path) -> io::Result<()> {
        check_id(model_id, "model")?;
        let tmp = dest.with_extension("download");
        let _ = tokio::fs::remove_file(&tmp).await;
        let fetched = download(&self.store, &checkpoint_key(model_id, sha256), &tmp).await;
        match fetched {
            Ok(()) => tokio::fs::rename(&tmp, dest).await,
            Err(e) => {
                let _ = tokio::fs::remove_file(&tmp).await;
                Err(e)
            }
        }
    }

    /// Deletes checkpoint `sha256` of model `model_id` (one a newer
    /// checkpoint replaced); a missing object is not an error.
    pub async fn delete_checkpoint(&self, model_id: &str, sha256: &str) -> io::Result<()> {
        check_id(model_id, "model")?;
        self.delete_if_present(&checkpoint_key(model_id, sha256)).await
    }

    /// Deletes object `key`; one already gone is no error.
    async fn delete_if_present(&self, key: &Key) -> io::Result<()> {
        match self.store.delete(key).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(io_error(e)),
        }
    }

    /// Stores a video's bytes at `videos/<id>.bin` (one atomic put).
    pub async fn put_video(&self, id: &str, bytes: Vec<u8>) -> io::Result<()> {
        check_id(id, "video")?;
        self.store.put(&Key::from(format!("videos/{id}.bin")), bytes.into()).await.map(drop).map_err(io_error)
    }

    /// The newest checkpoint stored for model `id`: its key and SHA-256.
    /// (Model records do not carry the checkpoint's hash yet; when they do,
    /// the record will name it and this listing goes.)
    async fn latest_checkpoint(&self, id: &str) -> io::Result<(Key, String)> {
        let prefix = Key::from(format!("models/{id}"));
        let mut newest: Option<object_store::ObjectMeta> = None;
        let mut listing = self.store.list(Some(&prefix));
        while let Some(meta) = listing.next().await {
            let meta = meta.map_err(io_error)?;
            let is_ckpt = meta.location.filename().is_some_and(|f| f.ends_with(".ckpt"));
            if is_ckpt && newest.as_ref().is_none_or(|n| meta.last_modified > n.last_modified) {
                newest = Some(meta);
            }
        }
        let meta =
            newest.ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, format!("model {id}: no checkpoint")))?;
        let name = meta.location.filename().unwrap_or_default();
        let sha = name.trim_end_matches(".ckpt").to_string();
        Ok((meta.location, sha))
    }

    /// Bytes under a key prefix.
    async fn bytes_under(&self, prefix: &str) -> io::Result<u64> {
        let prefix = Key::from(prefix);
        let mut listing = self.store.list(Some(&prefix));
        let mut total = 0;
        while let Some(meta) = listing.next().await {
            total += meta.map_err(io_error)?.size;
        }
        Ok(total)
    }
}

/// `scenes/<id>/dataset.tar` or `scenes/<id>/upload.tar`.
pub fn scene_key(id: &str, part: ScenePart) -> Key {
    let name = match part {
        ScenePart::Data => "dataset",
        ScenePart::Upload => "upload",
    };
    Key::from(format!("scenes/{id}/{name}.tar"))
}

/// `models/<id>/<sha256>.ckpt`.
pub fn checkpoint_key(id: &str, sha256: &str) -> Key {
    Key::from(format!("models/{id}/{sha256}.ckpt"))
}

/// Downloads object `key` to the new file `file`.
async fn download(store: &Arc<dyn ObjectStore>, key: &Key, file: &Path) -> io::Result<()> {
    let got = store.get(key).await.map_err(io_error)?;
    let mut out = tokio::fs::File::create_new(file).await?;
    let mut body = got.into_stream();
    while let Some(chunk) = body.next().await {
        out.write_all(&chunk.map_err(io_error)?).await?;
    }
    out.sync_all().await
}

/// Downloads the tar `key` and unpacks it to `<dest>/<part>`, `dest` a
/// new folder laid out as a scene's.
async fn fetch_scene(store: &Arc<dyn ObjectStore>, key: &Key, part: ScenePart, dest: PathBuf) -> io::Result<()> {
    tokio::fs::create_dir(&dest).await?;
    let tar = dest.join(".download.tar");
    download(store, key, &tar).await?;
    blocking(move || {
        let unpacked = std::fs::File::open(&tar)
            .and_then(|f| tar::Archive::new(io::BufReader::new(f)).unpack(dest.join(part.dir_name())));
        std::fs::remove_file(&tar)?;
        unpacked
    })
    .await?
}

impl ArtifactStore for ObjectArtifacts {
    /// `DATA/tmp/ID`: a local scratch folder; the upload is stored from it.
    fn staging_dir(&self, id: &str) -> PathBuf {
        self.tmp.join(id)
    }

    /// Tars `files` into `scenes/ID/dataset.tar` (or `upload.tar`),
    /// streamed, then removes the local copy. Nothing is listed before the
    /// job store inserts the record (listings come from the records); the
    /// object itself appears only once whole.
    fn put_scene_files<'a>(&'a self, id: &'a str, part: ScenePart, files: &'a Path) -> Fut<'a, io::Result<()>> {
        Box::pin(async move {
            check_id(id, "scene")?;
            // The folder is removed once stored: only a staged upload is.
            if !files.starts_with(self.staging_dir(id)) {
                let staging = self.staging_dir(id);
                return Err(io::Error::new(
                    io::ErrorKind::InvalidInput,
                    format!("{} is not in scene {id}'s staging folder {}", files.display(), staging.display()),
                ));
            }
            let key = scene_key(id, part);
            let size = upload::put_tar(&self.store, &key, files.to_path_buf(), self.config.part_size).await?;
            tracing::info!(scene = id, bytes = size, "scene upload stored");
            let files = files.to_path_buf();
            blocking(move || std::fs::remove_dir_all(files)).await?
        })
    }

    /// `DATA/cache/scenes/ID-PART/`, holding `PART/` (`data/` or
    /// `upload/`), unpacked from the scene's tar on first use.
    fn scene_files<'a>(&'a self, scene: &'a SceneInfo, part: ScenePart) -> Fut<'a, io::Result<Local>> {
        Box::pin(async move {
            check_id(&scene.id, "scene")?;
            let key = scene_key(&scene.id, part);
            let entry = format!("scenes/{}-{}", scene.id, part.dir_name());
            let store = self.store.clone();
            let (path, pin) = self
                .cache
                .get_or_fetch(&entry, |tmp| async move { fetch_scene(&store, &key, part, tmp).await })
                .await?;
            Ok(Local::held(path, Box::new(pin)))
        })
    }

    /// `DATA/cache/models/<sha256>.ckpt`, the model's newest checkpoint,
    /// fetched on first use.
    fn checkpoint<'a>(&'a self, model: &'a ModelInfo) -> Fut<'a, io::Result<Local>> {
        Box::pin(async move {
            check_id(&model.id, "model")?;
            let (key, sha) = self.latest_checkpoint(&model.id).await?;
            let store = self.store.clone();
            let entry = format!("models/{sha}.ckpt");
            let (path, pin) =
                self.cache.get_or_fetch(&entry, |tmp| async move { download(&store, &key, &tmp).await }).await?;
            Ok(Local::held(path, Box::new(pin)))
        })
    }

    /// `videos/ID.bin`, whole.
    fn video<'a>(&'a self, video: &'a VideoInfo) -> Fut<'a, io::Result<Vec<u8>>> {
        Box::pin(async move {
            check_id(&video.id, "video")?;
            let got = self.store.get(&Key::from(format!("videos/{}.bin", video.id))).await.map_err(io_error)?;
            Ok(got.bytes().await.map_err(io_error)?.to_vec())
        })
    }

    /// Bytes stored under `scenes/`, `models/` and `videos/` (a listing of
    /// each), and in the local staging folder.
    fn usage(&self) -> Fut<'_, io::Result<DiskUsage>> {
        Box::pin(async move {
            let tmp = self.tmp.clone();
            Ok(DiskUsage {
                scenes: self.bytes_under("scenes").await?,
                models: self.bytes_under("models").await?,
                videos: self.bytes_under("videos").await?,
                tmp: blocking(move || cache::size_of(&tmp)).await??,
            })
        })
    }

    /// `None`: a bucket has no free space to speak of.
    fn free_space(&self) -> Fut<'_, io::Result<Option<u64>>> {
        Box::pin(std::future::ready(Ok(None)))
    }

    /// The store answers a listing of `scenes/` (its first entry, if any)
    /// within `ready_timeout`. The errors name the store.
    fn ready(&self) -> Fut<'_, io::Result<()>> {
        Box::pin(async move {
            let prefix = Key::from("scenes");
            let mut listing = self.store.list(Some(&prefix));
            match tokio::time::timeout(self.config.ready_timeout, listing.next()).await {
                Err(_) => Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!(
                        "the object store {} did not answer a listing within {:?}",
                        self.name, self.config.ready_timeout
                    ),
                )),
                Ok(Some(Err(e))) => {
                    let e = io_error(e);
                    Err(io::Error::new(e.kind(), format!("the object store {}: {e}", self.name)))
                }
                Ok(_) => Ok(()),
            }
        })
    }

    /// Deletes `scenes/ID/*`, `models/ID/*` or `videos/ID.bin` (a listing
    /// of the folder, then each object; a missing object is no error).
    fn remove<'a>(&'a self, what: Artifact<'a>) -> Fut<'a, io::Result<()>> {
        Box::pin(async move {
            let (id, kind, prefix) = match what {
                Artifact::Scene(id) => (id, "scene", Some(format!("scenes/{id}"))),
                Artifact::Model(id) => (id, "model", Some(format!("models/{id}"))),
                Artifact::Video(id) => (id, "video", None),
            };
            check_id(id, kind)?;
            let keys: Vec<Key> = match prefix {
                Some(p) => {
                    let prefix = Key::from(p);
                    let mut listing = self.store.list(Some(&prefix));
                    let mut keys = Vec::new();
                    while let Some(meta) = listing.next().await {
                        keys.push(meta.map_err(io_error)?.location);
                    }
                    keys
                }
                None => vec![Key::from(format!("videos/{id}.bin"))],
            };
            for key in keys {
                self.delete_if_present(&key).await?;
            }
            tracing::info!(what = ?what, "object store: removed the bytes of a deleted record");
            Ok(())
        })
    }
}

/// Ids are made by the service: a bad one is a caller's mistake, refused
/// before it becomes part of a key.
fn check_id(id: &str, what: &str) -> io::Result<()> {
    if valid_id(id) {
        Ok(())
    } else {
        Err(io::Error::new(io::ErrorKind::InvalidInput, format!("'{id}' is not a valid {what} id")))
    }
}

/// An object store error as an `io::Error` (a missing object is `NotFound`).
fn io_error(e: object_store::Error) -> io::Error {
    let kind = match e {
        object_store::Error::NotFound { .. } => io::ErrorKind::NotFound,
        _ => io::ErrorKind::Other,
    };
    io::Error::new(kind, e.to_string())
}

/// Runs file work on tokio's blocking threads.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> io::Result<T> {
    tokio::task::spawn_blocking(f).await.map_err(|e| io::Error::other(format!("worker task failed: {e}")))
}

// Tested on a folder and on a real S3 server by tests/backend/objects.rs
// (and the contract, tests/backend/object.rs).
