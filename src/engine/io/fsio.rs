//! Crash-safe file replacement.
//!
//! [`write_atomic`] and [`write_atomic_with`] write the new content to a
//! uniquely named temporary file in the destination's directory
//! (`.<file name>.tmp<pid>.<counter>`), fsync it, rename it over the
//! destination and finally fsync the directory (on unix) so the rename itself
//! is durable. A reader therefore sees either the complete old file or the
//! complete new one, never a partial write, even across a crash or power loss.
//!
//! If anything fails before the rename, the temporary file is removed and the
//! destination is left untouched.

use std::ffi::OsString;
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Distinguishes temporary files of concurrent writers in one process.
static COUNTER: AtomicU64 = AtomicU64::new(0);

/// Atomically replaces (or creates) `path` with `bytes`.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Atomically replaces (or creates) `path` with whatever `f` writes.
///
/// `f` streams into a buffered writer over the temporary file; if it returns
/// an error, that error is returned, the temporary file is removed and `path`
/// keeps its old content.
///
/// Errors after the rename (fsyncing the directory) are reported too; at that
/// point `path` already holds the new content.
pub fn write_atomic_with<F>(path: &Path, f: F) -> io::Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    let name = path
        .file_name()
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, format!("{}: not a file path", path.display())))?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };

    let (tmp, file) = create_temp(dir, name)?;
    let written = (|| {
        let mut w = BufWriter::new(file);
        f(&mut w)?;
        let file = w.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()?;
        drop(file);
        fs::rename(&tmp, path)
    })();
    if let Err(e) = written {
        let _ = fs::remove_file(&tmp);
        return Err(e);
    }
    sync_dir(dir)
}

/// Creates a fresh temporary file next to the destination. `create_new`
/// guarantees we never clobber someone else's file (for example a stale
/// temporary left by a crashed process that had the same pid).
fn create_temp(dir: &Path, name: &std::ffi::OsStr) -> io::Result<(PathBuf, File)> {
    let pid = std::process::id();
    let mut attempts = 0;
    loop {
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(temp_name(name, pid, n));
        match OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Ok(file) => return Ok((tmp, file)),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && attempts < 100 => attempts += 1,
            Err(e) => return Err(e),
        }
    }
}

fn temp_name(name: &std::ffi::OsStr, pid: u32, n: u64) -> OsString {
    let mut s = OsString::from(".");
    s.push(name);
    s.push(format!(".tmp{pid}.{n}"));
    s
}

/// Whether a file name is one of [`write_atomic_with`]'s temporary files
/// (`.<name>.tmp<pid>.<counter>`): what a crash mid-write leaves behind.
pub fn is_temporary(name: &std::ffi::OsStr) -> bool {
    let Some(s) = name.to_str() else { return false };
    let Some(rest) = s.strip_prefix('.') else { return false };
    let Some((stem, counter)) = rest.rsplit_once('.') else { return false };
    let Some((file, pid)) = stem.rsplit_once(".tmp") else { return false };
    let digits = |t: &str| !t.is_empty() && t.bytes().all(|b| b.is_ascii_digit());
    !file.is_empty() && digits(pid) && digits(counter)
}

#[cfg(unix)]
fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

#[cfg(not(unix))]
fn sync_dir(_dir: &Path) -> io::Result<()> {
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir_entries(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> =
            fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        v.sort();
        v
    }

    #[test]
    fn temporary_names_are_recognised() {
        assert!(is_temporary(&temp_name(std::ffi::OsStr::new("model.ckpt"), 42, 7)));
        assert!(is_temporary(std::ffi::OsStr::new(".mdl_1.ckpt.tmp19226.2")));
        for name in
            ["model.ckpt", ".model.ckpt", ".x.tmp12", ".x.tmp.3", ".x.tmpa.3", ".x.tmp1.", ".tmp1.2", "x.tmp1.2"]
        {
            assert!(!is_temporary(std::ffi::OsStr::new(name)), "{name}");
        }
    }

    #[test]
    fn creates_new_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("out.bin");
        write_atomic(&p, b"hello").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"hello");
        assert_eq!(dir_entries(dir.path()), vec!["out.bin"]);
    }

    #[test]
    fn replaces_content_and_leaves_no_temp_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model.ckpt");
        fs::write(&p, vec![7u8; 10_000]).unwrap();
        for i in 0..5u8 {
            write_atomic(&p, &[i; 3]).unwrap();
            assert_eq!(fs::read(&p).unwrap(), vec![i; 3]);
        }
        write_atomic(&p, b"").unwrap();
        assert_eq!(fs::read(&p).unwrap(), b"");
        assert_eq!(dir_entries(dir.path()), vec!["model.ckpt"]);
    }

    #[test]
    fn streaming_writer() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.txt");
        write_atomic_with(&p, |w| {
            for i in 0..1000 {
                writeln!(w, "{i}")?;
            }
            Ok(())
        })
        .unwrap();
        let text = fs::read_to_string(&p).unwrap();
        assert_eq!(text.lines().count(), 1000);
        assert_eq!(text.lines().last(), Some("999"));
        assert_eq!(dir_entries(dir.path()), vec!["s.txt"]);
    }

    #[test]
    fn temp_file_is_in_same_directory_with_expected_name() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.json");
        let mut seen = Vec::new();
        write_atomic_with(&p, |w| {
            seen = dir_entries(dir.path());
            w.write_all(b"{}")
        })
        .unwrap();
        assert_eq!(seen.len(), 1, "{seen:?}");
        let prefix = format!(".a.json.tmp{}.", std::process::id());
        assert!(seen[0].starts_with(&prefix), "{seen:?}");
        assert_eq!(dir_entries(dir.path()), vec!["a.json"]);
    }

    #[test]
    fn writer_error_leaves_destination_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("keep.txt");
        fs::write(&p, b"old").unwrap();
        let err = write_atomic_with(&p, |w| {
            w.write_all(&[1u8; 100_000])?; // forces flushed bytes on disk
            Err(io::Error::other("boom"))
        })
        .unwrap_err();
        assert_eq!(err.to_string(), "boom");
        assert_eq!(fs::read(&p).unwrap(), b"old");
        assert_eq!(dir_entries(dir.path()), vec!["keep.txt"]);
    }

    #[test]
    fn writer_error_without_existing_file_creates_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("new.txt");
        assert!(write_atomic_with(&p, |_| Err(io::Error::other("no"))).is_err());
        assert!(dir_entries(dir.path()).is_empty());
    }

    #[test]
    fn missing_directory_is_an_error_and_creates_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("missing").join("out.bin");
        let err = write_atomic(&p, b"x").unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::NotFound);
        assert!(!dir.path().join("missing").exists());
        assert!(dir_entries(dir.path()).is_empty());
    }

    #[test]
    fn rename_failure_cleans_up() {
        // The destination is a non-empty directory: the rename fails after the
        // temporary file has been fully written.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("occupied");
        fs::create_dir(&p).unwrap();
        fs::write(p.join("inner"), b"x").unwrap();
        assert!(write_atomic(&p, b"data").is_err());
        assert!(p.is_dir());
        assert_eq!(dir_entries(dir.path()), vec!["occupied"]);
    }

    #[test]
    fn path_without_file_name_is_invalid_input() {
        let err = write_atomic(Path::new("/"), b"x").unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput);
        let err = write_atomic(Path::new(".."), b"x").unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput);
    }

    #[test]
    fn temp_names_are_unique() {
        let a = temp_name("f".as_ref(), 1, 0);
        let b = temp_name("f".as_ref(), 1, 1);
        assert_eq!(a, ".f.tmp1.0");
        assert_ne!(a, b);
    }

    #[test]
    fn concurrent_writers_never_produce_a_mix() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("shared.bin");
        std::thread::scope(|s| {
            for t in 0..4u8 {
                let p = &p;
                s.spawn(move || {
                    for _ in 0..20 {
                        write_atomic(p, &vec![t; 4096]).unwrap();
                    }
                });
            }
        });
        let data = fs::read(&p).unwrap();
        assert_eq!(data.len(), 4096);
        assert!(data.iter().all(|&b| b == data[0]));
        assert_eq!(dir_entries(dir.path()), vec!["shared.bin"]);
    }
}
