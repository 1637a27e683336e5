//! Writing objects so that nothing is visible until it is whole
//! (docs/design/scale-out.md, section 2.4).
//!
//! Everything goes through `object_store`'s [`BufWriter`]: below its
//! capacity (the part size) one atomic PUT at shutdown, above it a
//! multipart upload of part-size parts that becomes an object only when it
//! completes. An upload that fails is aborted; one whose writer is dropped
//! is never completed, so no object appears either way. An upload whose
//! future is dropped (its task aborted, its request gone) stops at its
//! next write rather than sending the rest for nothing, and is aborted
//! (an S3 server keeps an incomplete upload's parts until then, or until
//! the bucket's lifecycle rule removes them).

use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

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
    let (bridge, _abandon) = Bridge::new(writer(store, key, part_size), key);
    let (bridge, made) = blocking(move || {
        let mut bridge = bridge;
        let made = write_tar(&mut bridge, &dir);
        bridge.abort_if_abandoned();
        (bridge, made)
    })
    .await?;
    finish(bridge.writer, made.map(|()| bridge.written), key).await
}

/// Stores the file `file` as object `key`, streamed. Answers its size.
pub async fn put_file(store: &Arc<dyn ObjectStore>, key: &Key, file: PathBuf, part_size: usize) -> io::Result<u64> {
    let (bridge, _abandon) = Bridge::new(writer(store, key, part_size), key);
    let (bridge, copied) = blocking(move || {
        let mut bridge = bridge;
        let copied = std::fs::File::open(&file).and_then(|mut f| io::copy(&mut f, &mut bridge));
        bridge.abort_if_abandoned();
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
    /// The object's key, for the log.
    key: Key,
    runtime: Handle,
    written: u64,
    /// Set once nobody waits for the upload any more ([`Abandon`]).
    abandoned: Arc<AtomicBool>,
}

/// Held by the future that waits for an upload: dropping it (the future
/// done or dropped) tells the blocking writer to stop.
struct Abandon(Arc<AtomicBool>);

impl Drop for Abandon {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

impl Bridge {
    /// A bridge to `writer` of `key` (on the current runtime), and the
    /// guard whose drop stops it.
    fn new(writer: BufWriter, key: &Key) -> (Bridge, Abandon) {
        let abandoned = Arc::new(AtomicBool::new(false));
        let bridge =
            Bridge { writer, key: key.clone(), runtime: Handle::current(), written: 0, abandoned: abandoned.clone() };
        (bridge, Abandon(abandoned))
    }

    /// Aborts the upload if nobody waits for it any more (nobody will
    /// complete or abort it then): its stored parts are deleted.
    fn abort_if_abandoned(&mut self) {
        if !self.abandoned.load(Ordering::Relaxed) {
            return;
        }
        match self.runtime.block_on(self.writer.abort()) {
            Ok(()) => tracing::info!(key = %self.key, "abandoned upload aborted"),
            Err(e) => tracing::warn!(key = %self.key, error = %io_error(e), "could not abort an abandoned upload"),
        }
    }
}

impl Write for Bridge {
    /// Refused once the upload is abandoned (the thread then aborts it).
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if self.abandoned.load(Ordering::Relaxed) {
            return Err(io::Error::other("the upload was abandoned: nobody waits for it any more"));
        }
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
    use object_store::memory::InMemory;

    // The uploads themselves are checked on a folder and on a real S3
    // server by tests/backend/objects.rs.

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_abandoned_bridge_refuses_to_write() {
        let store: Arc<dyn ObjectStore> = Arc::new(InMemory::new());
        let key = Key::from("a");
        let (mut bridge, abandon) = Bridge::new(writer(&store, &key, 1024), &key);
        let wrote = tokio::task::spawn_blocking(move || {
            let first = bridge.write_all(b"kept");
            (bridge, first)
        });
        let (mut bridge, first) = wrote.await.unwrap();
        first.unwrap();
        drop(abandon);
        let second = tokio::task::spawn_blocking(move || bridge.write_all(b"refused")).await.unwrap();
        let e = second.unwrap_err();
        assert!(e.to_string().contains("abandoned"), "{e}");
    }
}
