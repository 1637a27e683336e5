//! A bounded local cache of objects fetched from the object store
//! (docs/design/scale-out.md, section 2.4): scenes unpacked to folders and
//! checkpoints, under `DATA/cache/`.
//!
//! - Each entry is a file or folder at `<root>/<key>`. It is fetched into
//!   `<root>/tmp/<uuid>` and renamed in whole, so an entry is never seen
//!   half-written; `tmp/` is emptied when the cache opens.
//! - The entries' total size is bounded: when an entry comes in, the least
//!   recently used entries that nobody holds go until the total fits. A
//!   [`Pin`] (returned with every entry) keeps its entry from eviction
//!   while it lives; pinned entries may hold the total above the bound.
//! - Fetches are single-flight per key: a second caller asking for a key
//!   being fetched waits for that fetch and shares its entry.
//! - The index is in memory, rebuilt at open from the entries on disk,
//!   oldest modification time first.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

/// The cache: a folder and the index of its entries.
pub struct Cache {
    root: PathBuf,
    max_bytes: u64,
    index: Mutex<Index>,
    /// One lock per key being fetched (single flight).
    flights: Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
}

#[derive(Default)]
struct Index {
    entries: HashMap<String, Entry>,
    /// Sum of the entries' sizes, bytes.
    total: u64,
    /// Counts uses: an entry's `used` is the count at its last use.
    clock: u64,
}

struct Entry {
    size: u64,
    used: u64,
    pins: usize,
}

/// Keeps one entry from eviction while it lives.
pub struct Pin {
    cache: Arc<Cache>,
    key: String,
}

impl Drop for Pin {
    fn drop(&mut self) {
        if let Some(entry) = self.cache.lock().entries.get_mut(&self.key) {
            entry.pins -= 1;
        }
    }
}

/// The folders entries live in, one per kind (a key is `<kind>/<name>`).
const KINDS: [&str; 2] = ["scenes", "models"];

impl Cache {
    /// Opens the cache in `root` (created if missing), bounded to
    /// `max_bytes`: empties `tmp/` and indexes the entries already there.
    pub fn open(root: &Path, max_bytes: u64) -> io::Result<Arc<Self>> {
        let tmp = root.join("tmp");
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)?;
        }
        std::fs::create_dir_all(&tmp)?;
        let mut found = Vec::new();
        for kind in KINDS {
            let dir = root.join(kind);
            std::fs::create_dir_all(&dir)?;
            for item in std::fs::read_dir(&dir)? {
                let item = item?;
                let modified = item.metadata()?.modified()?;
                let key = format!("{kind}/{}", item.file_name().to_string_lossy());
                found.push((modified, key, size_of(&item.path())?));
            }
        }
        found.sort();
        let mut index = Index::default();
        for (_, key, size) in found {
            index.clock += 1;
            index.total += size;
            index.entries.insert(key, Entry { size, used: index.clock, pins: 0 });
        }
        let cache = Self { root: root.to_path_buf(), max_bytes, index: Mutex::new(index), flights: Mutex::default() };
        Ok(Arc::new(cache))
    }

    /// Where entry `key` lives (whether or not it is there).
    pub fn path(&self, key: &str) -> PathBuf {
        self.root.join(key)
    }

    /// Bytes held by the entries.
    pub fn total_bytes(&self) -> u64 {
        self.lock().total
    }

    /// Whether `key` is in the cache.
    pub fn contains(&self, key: &str) -> bool {
        self.lock().entries.contains_key(key)
    }

    /// Entry `key` (`<kind>/<name>`, `kind` one of `scenes`, `models`) and
    /// a pin on it. When it is missing, `fetch(tmp)` writes it to `tmp` (a
    /// path that does not exist yet: the fetch makes a file or a folder
    /// there), which is then renamed in; one fetch per key runs at a time,
    /// and those who waited for it share its entry.
    pub async fn get_or_fetch<F, Fut>(self: &Arc<Self>, key: &str, fetch: F) -> io::Result<(PathBuf, Pin)>
    where
        F: FnOnce(PathBuf) -> Fut,
        Fut: Future<Output = io::Result<()>>,
    {
        check_key(key)?;
        if let Some(pin) = self.pin(key) {
            return Ok((self.path(key), pin));
        }
        let flight = self.flights.lock().unwrap_or_else(|p| p.into_inner()).entry(key.to_string()).or_default().clone();
        let _flying = flight.lock().await;
        // The fetch we waited for may have brought it.
        if let Some(pin) = self.pin(key) {
            return Ok((self.path(key), pin));
        }
        let result = self.fetch_in(key, fetch).await;
        self.flights.lock().unwrap_or_else(|p| p.into_inner()).remove(key);
        result.map(|pin| (self.path(key), pin))
    }

    /// Fetches `key` into a temporary path, renames it in, indexes it
    /// (pinned) and evicts what no longer fits.
    async fn fetch_in<F, Fut>(self: &Arc<Self>, key: &str, fetch: F) -> io::Result<Pin>
    where
        F: FnOnce(PathBuf) -> Fut,
        Fut: Future<Output = io::Result<()>>,
    {
        let tmp = self.root.join("tmp").join(uuid::Uuid::now_v7().simple().to_string());
        let fetched = fetch(tmp.clone()).await;
        let moved = match fetched {
            Ok(()) => {
                let (tmp, dest) = (tmp.clone(), self.path(key));
                super::blocking(move || size_of(&tmp).and_then(|size| std::fs::rename(&tmp, &dest).map(|()| size)))
                    .await
                    .and_then(|moved| moved)
            }
            Err(e) => Err(e),
        };
        let size = match moved {
            Ok(size) => size,
            Err(e) => {
                let _ = super::blocking(move || remove_path(&tmp)).await;
                return Err(io::Error::new(e.kind(), format!("cache: fetching {key}: {e}")));
            }
        };
        let evicted = {
            let mut index = self.lock();
            index.clock += 1;
            let used = index.clock;
            index.total += size;
            index.entries.insert(key.to_string(), Entry { size, used, pins: 1 });
            // Out of the way while the index is locked (a rename, quick), so
            // a fetch of an evicted key finds its path free; removed after.
            let evicted = index.evict(self.max_bytes);
            evicted.iter().map(|k| self.set_aside(k)).collect::<io::Result<Vec<_>>>()?
        };
        super::blocking(move || evicted.iter().try_for_each(|p| remove_path(p))).await??;
        Ok(Pin { cache: self.clone(), key: key.to_string() })
    }

    /// A pin on `key` if it is there, marking it used.
    fn pin(self: &Arc<Self>, key: &str) -> Option<Pin> {
        let mut index = self.lock();
        index.clock += 1;
        let used = index.clock;
        let entry = index.entries.get_mut(key)?;
        entry.pins += 1;
        entry.used = used;
        Some(Pin { cache: self.clone(), key: key.to_string() })
    }

    /// Moves entry `key`'s file or folder into `tmp/` (to be removed);
    /// answers where it went.
    fn set_aside(&self, key: &str) -> io::Result<PathBuf> {
        let aside = self.root.join("tmp").join(format!("evicted-{}", uuid::Uuid::now_v7().simple()));
        match std::fs::rename(self.path(key), &aside) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(aside),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Index> {
        self.index.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl Index {
    /// Drops unpinned entries, least recently used first, until the total
    /// fits in `max_bytes` (or only pinned entries are left); answers the
    /// keys dropped, whose files the caller removes.
    fn evict(&mut self, max_bytes: u64) -> Vec<String> {
        let mut gone = Vec::new();
        while self.total > max_bytes {
            let oldest = self.entries.iter().filter(|(_, e)| e.pins == 0).min_by_key(|(_, e)| e.used);
            let Some((key, _)) = oldest else { break };
            let key = key.clone();
            let entry = self.entries.remove(&key).expect("the key was just found");
            self.total -= entry.size;
            gone.push(key);
        }
        gone
    }
}

/// A key is `<kind>/<name>` with a known kind and a plain name: it names a
/// path inside the cache and nothing else.
fn check_key(key: &str) -> io::Result<()> {
    let ok = key.split_once('/').is_some_and(|(kind, name)| {
        KINDS.contains(&kind) && !name.is_empty() && name != "." && name != ".." && !name.contains(['/', '\\'])
    });
    if ok { Ok(()) } else { Err(io::Error::new(io::ErrorKind::InvalidInput, format!("'{key}' is not a cache key"))) }
}

/// Bytes in a file, or in the files under a folder.
pub(super) fn size_of(path: &Path) -> io::Result<u64> {
    let meta = std::fs::symlink_metadata(path)?;
    if !meta.is_dir() {
        return Ok(meta.len());
    }
    let mut total = 0;
    for item in std::fs::read_dir(path)? {
        total += size_of(&item?.path())?;
    }
    Ok(total)
}

/// Removes a file or a folder; one already gone is fine.
fn remove_path(path: &Path) -> io::Result<()> {
    let removed = match std::fs::symlink_metadata(path) {
        Ok(meta) if meta.is_dir() => std::fs::remove_dir_all(path),
        Ok(_) => std::fs::remove_file(path),
        Err(e) => Err(e),
    };
    match removed {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    /// A fetch writing a file of `size` bytes.
    async fn file_of(tmp: PathBuf, size: usize) -> io::Result<()> {
        tokio::fs::write(tmp, vec![7u8; size]).await
    }

    /// A fetch that must not run: the entry is expected in the cache.
    async fn no_fetch(_: PathBuf) -> io::Result<()> {
        panic!("fetched an entry the cache holds");
    }

    #[tokio::test]
    async fn least_recently_used_unpinned_entries_go_to_keep_the_bound() {
        let dir = tempfile::tempdir().unwrap();
        let cache = Cache::open(dir.path(), 100).unwrap();
        drop(cache.get_or_fetch("models/a", |t| file_of(t, 40)).await.unwrap());
        drop(cache.get_or_fetch("models/b", |t| file_of(t, 40)).await.unwrap());
        // Using `a` makes `b` the least recently used.
        let (path_a, pin_a) = cache.get_or_fetch("models/a", no_fetch).await.unwrap();
        assert_eq!(std::fs::read(&path_a).unwrap().len(), 40);
        let (_, pin_c) = cache.get_or_fetch("models/c", |t| file_of(t, 40)).await.unwrap();
        assert!(!cache.contains("models/b") && !cache.path("models/b").exists(), "b, least recent, went");
        assert_eq!(cache.total_bytes(), 80);
        assert_eq!(std::fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0, "set aside, then removed");

        // `a` is older than `c` but pinned: `c` goes when `d` comes.
        drop(pin_c);
        let (_, pin_d) = cache.get_or_fetch("models/d", |t| file_of(t, 40)).await.unwrap();
        assert!(cache.contains("models/a") && path_a.exists(), "a pinned entry stays");
        assert!(!cache.contains("models/c"));
        // With everything pinned the bound gives way rather than a pin.
        let (_, pin_e) = cache.get_or_fetch("scenes/e", |t| file_of(t, 40)).await.unwrap();
        assert_eq!(cache.total_bytes(), 120);
        assert!(["models/a", "models/d", "scenes/e"].iter().all(|k| cache.contains(k)));
        // Once pins are let go, the next entry brings the total back under the bound.
        drop((pin_a, pin_d, pin_e));
        drop(cache.get_or_fetch("models/f", |t| file_of(t, 10)).await.unwrap());
        assert_eq!(cache.total_bytes(), 90);
        assert!(!cache.contains("models/a"), "a, now least recent, went");
        // A cache opened again finds the entries on disk, and no temporary files.
        std::fs::write(dir.path().join("tmp/leftover"), b"x").unwrap();
        drop(cache);
        let again = Cache::open(dir.path(), 100).unwrap();
        assert_eq!(again.total_bytes(), 90);
        assert!(["models/d", "scenes/e", "models/f"].iter().all(|k| again.contains(k)));
        assert_eq!(std::fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_fetches_of_one_key_download_once() {
        let dir = tempfile::tempdir().unwrap();
        let cache = Cache::open(dir.path(), 1 << 20).unwrap();
        let fetches = Arc::new(AtomicUsize::new(0));
        let fetch = |n: Arc<AtomicUsize>| {
            move |tmp: PathBuf| async move {
                n.fetch_add(1, Ordering::SeqCst);
                tokio::time::sleep(Duration::from_millis(100)).await;
                file_of(tmp, 5).await
            }
        };
        let (c1, c2) = (cache.clone(), cache.clone());
        let (f1, f2) = (fetch(fetches.clone()), fetch(fetches.clone()));
        let one = tokio::spawn(async move { c1.get_or_fetch("scenes/s-data", f1).await.map(|(p, _)| p) });
        let two = tokio::spawn(async move { c2.get_or_fetch("scenes/s-data", f2).await.map(|(p, _)| p) });
        let (one, two) = (one.await.unwrap().unwrap(), two.await.unwrap().unwrap());
        assert_eq!(fetches.load(Ordering::SeqCst), 1, "one download for both");
        assert_eq!(one, two);
        assert_eq!(std::fs::read(one).unwrap(), vec![7u8; 5]);
    }

    #[tokio::test]
    async fn a_failed_fetch_leaves_nothing_and_bad_keys_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let cache = Cache::open(dir.path(), 1 << 20).unwrap();
        let failing = |tmp: PathBuf| async move {
            tokio::fs::write(&tmp, b"half").await?;
            Err(io::Error::other("connection reset"))
        };
        let e = cache.get_or_fetch("models/x", failing).await.err().unwrap();
        assert!(e.to_string().contains("models/x") && e.to_string().contains("connection reset"), "{e}");
        assert!(!cache.contains("models/x") && !cache.path("models/x").exists());
        assert_eq!(std::fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0, "the partial file is removed");
        // The next caller tries again.
        cache.get_or_fetch("models/x", |t| file_of(t, 3)).await.unwrap();
        for key in ["models/../x", "other/x", "models/", "models/a/b", "x"] {
            let e = cache.get_or_fetch(key, no_fetch).await.err().unwrap();
            assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{key}");
        }
    }
}
