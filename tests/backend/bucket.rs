//! Where the object-store tests keep their objects: a folder (`file://`)
//! or a real S3 server (`common::s3`), a fresh one per test. The same
//! tests run on both (`Backend`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use object_store::ObjectStore;
use radiance::backend::object::{ObjectArtifacts, ObjectConfig, open_url};

use crate::common::s3::S3;

/// The kind of store a test runs on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    File,
    S3,
}

/// A fresh, empty store, and what must live as long as it does.
pub struct Bucket {
    pub backend: Backend,
    /// `file:///…` or `s3://radiance-test/t-…`.
    pub url: String,
    /// How `ObjectArtifacts` opens it (its S3 settings, small parts).
    pub config: ObjectConfig,
    /// The S3 server (`None` on `file://`).
    pub s3: Option<S3>,
    /// The `file://` store's folder.
    folder: Option<PathBuf>,
}

impl Bucket {
    /// A store of `backend`, the `file://` one in `dir/bucket`. Parts are
    /// the smallest each allows in practice: 1 KiB in a folder, 5 MiB on
    /// S3 (its minimum for all parts but the last).
    pub async fn new(backend: Backend, dir: &Path) -> Bucket {
        match backend {
            Backend::File => Bucket {
                backend,
                url: format!("file://{}", dir.join("bucket").display()),
                config: ObjectConfig { part_size: 1024, cache_max_bytes: 1 << 20, ..ObjectConfig::default() },
                s3: None,
                folder: Some(dir.join("bucket")),
            },
            Backend::S3 => {
                let s3 = S3::start().await;
                let config = ObjectConfig {
                    part_size: 5 << 20,
                    cache_max_bytes: 64 << 20,
                    s3: s3.options(),
                    ..ObjectConfig::default()
                };
                Bucket { backend, url: s3.url(), config, s3: Some(s3), folder: None }
            }
        }
    }

    /// `ObjectArtifacts` over the store, its local folders in `data_dir`.
    pub fn open(&self, data_dir: &Path) -> ObjectArtifacts {
        ObjectArtifacts::open(data_dir, &self.url, self.config.clone())
            .unwrap_or_else(|e| panic!("cannot open {}: {e}", self.url))
    }

    /// The object store itself.
    pub fn store(&self) -> Arc<dyn ObjectStore> {
        open_url(&self.url, &self.config.s3).unwrap()
    }

    /// The part size of its uploads.
    pub fn part_size(&self) -> usize {
        self.config.part_size
    }

    /// Bytes of multipart uploads under way (parts stored, not yet an
    /// object): `file://` stages an upload in `<key>#<n>` beside its key,
    /// s3s-fs keeps parts as `.upload_id-<id>.part-<n>` in its folder.
    /// `None` on an existing S3 server, whose folder the test cannot see.
    pub fn staged_bytes(&self) -> Option<u64> {
        if let Some(folder) = &self.folder {
            return Some(files_under(folder, &|name| name.contains('#')));
        }
        let root = self.s3.as_ref()?.root()?;
        Some(files_under(root, &|name| name.starts_with(".upload_id-")))
    }
}

/// Bytes of the files under `dir` whose names `pick` picks, recursively.
fn files_under(dir: &Path, pick: &dyn Fn(&str) -> bool) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    let mut total = 0;
    for entry in entries.flatten() {
        let Ok(meta) = entry.metadata() else { continue };
        if meta.is_dir() {
            total += files_under(&entry.path(), pick);
        } else if pick(&entry.file_name().to_string_lossy()) {
            total += meta.len();
        }
    }
    total
}
