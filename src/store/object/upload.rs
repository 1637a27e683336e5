//! Writing objects so that nothing is visible until it is whole
//! (docs/design/scale-out.md, section 2.4).
//!
//! Everything goes through `object_store`'s [`BufWriter`]: below its
//! capacity (the part size) one atomic PUT at shutdown, above it a
//! multipart upload of part-size parts that becomes an object only when it
//! completes. An upload that fails is aborted; one whose writer is dropped
//! is never completed, so no object appears either way.

use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use object_store::ObjectStore;
use object_store::buffered::BufWriter;
use object_store::path::Path as Key;
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;
use tokio::runtime::Handle;

use super::{blocking, io_error};

/// A writer of object `key` in parts of `part_size` bytes.
pub fn writer(store: &Arc<dyn ObjectStore>, key: &Key, part_size: usize) -> BufWriter {
    BufWriter::with_capacity(store.clone(), key.clone(), part_size)
}

/// Stores the folder `dir` as the uncompressed tar `key` (entries relative
/// to `dir`), streamed: the tar is written into the upload as it is made,
/// never held whole. Answers the tar's size.
pub async fn put_tar(store: &Arc<dyn ObjectStore>, key: &Key, dir: PathBuf, part_size: usize) -> io::Result<u64> {
    let bridge = Bridge { writer: writer(store, key, part_size), runtime: Handle::current(), written: 0 };
    let (bridge, made) = blocking(move || {
        let mut bridge = bridge;
        let made = write_tar(&mut bridge, &dir);
        (bridge, made)
    })
    .await?;
    finish(bridge.writer, made.map(|()| bridge.written), key).await
}

/// Stores the file `file` as object `key`, streamed. Answers its size.
pub async fn put_file(store: &Arc<dyn ObjectStore>, key: &Key, file: PathBuf, part_size: usize) -> io::Result<u64> {
    let bridge = Bridge { writer: writer(store, key, part_size), runtime: Handle::current(), written: 0 };
    let (bridge, copied) = blocking(move || {
        let mut bridge = bridge;
        let copied = std::fs::File::open(&file).and_then(|mut f| io::copy(&mut f, &mut bridge));
        (bridge, copied)
    })
    .await?;
    finish(bridge.writer, copied, key).await
}

/// Completes the upload if the write went well (the object appears now),
/// aborts it otherwise.
async fn finish(mut writer: BufWriter, written: io::Result<u64>, key: &Key) -> io::Result<u64> {
    match written {
        Ok(size) => {
            writer.shutdown().await.map_err(|e| io::Error::new(e.kind(), format!("storing {key}: {e}")))?;
            tracing::info!(key = %key, bytes = size, "object stored");
            Ok(size)
        }
        Err(e) => {
            if let Err(abort) = writer.abort().await {
                tracing::warn!(key = %key, error = %io_error(abort), "could not abort an upload");
            }
            Err(io::Error::new(e.kind(), format!("storing {key}: {e}")))
        }
    }
}

/// Writes `dir`'s tree as a tar into `out`, symbolic links as links.
fn write_tar(out: &mut impl Write, dir: &Path) -> io::Result<()> {
    if !std::fs::metadata(dir)?.is_dir() {
        return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("{} is not a folder", dir.display())));
    }
    let mut tar = tar::Builder::new(out);
    tar.follow_symlinks(false);
    tar.append_dir_all(".", dir)?;
    tar.finish()
}

/// The SHA-256 of a file, as lowercase hex, and its size.
pub fn sha256_file(file: &Path) -> io::Result<(String, u64)> {
    let mut f = std::fs::File::open(file)?;
    let (mut hasher, mut buf, mut size) = (Sha256::new(), vec![0u8; 1 << 16], 0u64);
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
        size += n as u64;
    }
    let hex = hasher.finalize().iter().map(|b| format!("{b:02x}")).collect();
    Ok((hex, size))
}

/// The async writer seen as a `std::io::Write`, for code that writes
/// synchronously (`tar`) on a blocking thread: each write waits on the
/// runtime for the writer (which uploads a part whenever one fills).
struct Bridge {
    writer: BufWriter,
    runtime: Handle,
    written: u64,
}

impl Write for Bridge {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.runtime.block_on(self.writer.write(buf))?;
        self.written += n as u64;
        Ok(n)
    }

    /// Nothing to do: the writer sends whole parts, and the rest when the
    /// upload completes.
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use futures_util::StreamExt;
    use object_store::ObjectStoreExt;
    use object_store::local::LocalFileSystem;

    fn local(dir: &Path) -> Arc<dyn ObjectStore> {
        Arc::new(LocalFileSystem::new_with_prefix(dir).unwrap())
    }

    async fn listed(store: &Arc<dyn ObjectStore>) -> Vec<String> {
        store.list(None).map(|m| m.unwrap().location.to_string()).collect().await
    }

    /// Multipart staging files of the local store (`<key>#<n>`) in `dir`.
    fn staged(dir: &Path) -> usize {
        std::fs::read_dir(dir)
            .map_or(0, |d| d.filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().contains('#')).count())
    }

    #[tokio::test]
    async fn an_upload_over_two_parts_is_multipart_and_appears_only_when_complete() {
        let dir = tempfile::tempdir().unwrap();
        let store = local(dir.path());
        let key = Key::from("scenes/scn_a/dataset.tar");
        let bytes: Vec<u8> = (0..3000u32).map(|i| (i % 251) as u8).collect();
        let mut w = writer(&store, &key, 1024);
        w.write_all(&bytes).await.unwrap();
        // Over two parts in: a multipart upload is under way (its staging
        // file is there) and nothing is listed.
        assert_eq!(staged(&dir.path().join("scenes/scn_a")), 1, "multipart upload started");
        assert!(listed(&store).await.is_empty());
        w.shutdown().await.unwrap();
        assert_eq!(listed(&store).await, vec![key.to_string()]);
        assert_eq!(store.get(&key).await.unwrap().bytes().await.unwrap(), bytes);
        assert_eq!(staged(&dir.path().join("scenes/scn_a")), 0);

        // Below the part size: one put at the end, nothing staged before.
        let small = Key::from("videos/vid_a.bin");
        let mut w = writer(&store, &small, 1024);
        w.write_all(&bytes[..500]).await.unwrap();
        assert_eq!(staged(&dir.path().join("videos")), 0);
        w.shutdown().await.unwrap();
        assert_eq!(store.get(&small).await.unwrap().bytes().await.unwrap(), bytes[..500]);
    }

    #[tokio::test]
    async fn a_writer_dropped_midway_leaves_no_listed_object() {
        let dir = tempfile::tempdir().unwrap();
        let store = local(dir.path());
        let key = Key::from("models/mdl_a/x.ckpt");
        let mut w = writer(&store, &key, 1024);
        w.write_all(&[1u8; 3000]).await.unwrap();
        drop(w);
        assert!(listed(&store).await.is_empty());
        assert!(!dir.path().join("models/mdl_a/x.ckpt").exists());
        assert!(store.head(&key).await.is_err());
    }

    #[tokio::test]
    async fn a_failed_tar_is_aborted_and_names_the_key() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("bucket")).unwrap();
        let store = local(&dir.path().join("bucket"));
        let key = Key::from("scenes/scn_a/dataset.tar");
        let e = put_tar(&store, &key, dir.path().join("missing"), 1024).await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::NotFound);
        assert!(e.to_string().contains("scenes/scn_a/dataset.tar"), "{e}");
        assert!(listed(&store).await.is_empty());
    }
}
