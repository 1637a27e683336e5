//! Safe extraction of uploaded archives (zip, tar, tar.gz).
//!
//! Every entry name must be a relative path of plain components (no `..`,
//! no root, no drive prefix, no backslash); only regular files and folders
//! are accepted (links, devices and fifos are refused); the unpacked size is
//! counted on the bytes actually written, not the sizes the archive claims,
//! so a decompression bomb stops at the limit. The caller extracts into a
//! fresh temporary folder and removes it on any error.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read};
use std::path::{Component, Path, PathBuf};

/// Archive formats accepted by `POST /v1/scenes`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ArchiveKind {
    Zip,
    Tar,
    TarGz,
}

impl ArchiveKind {
    /// From a `Content-Type` (parameters ignored).
    pub fn from_content_type(ct: &str) -> Option<Self> {
        match ct.split(';').next().unwrap_or("").trim().to_ascii_lowercase().as_str() {
            "application/zip" | "application/x-zip-compressed" => Some(Self::Zip),
            "application/x-tar" | "application/tar" => Some(Self::Tar),
            "application/gzip" | "application/x-gzip" | "application/x-compressed-tar" | "application/tar+gzip" => {
                Some(Self::TarGz)
            }
            _ => None,
        }
    }
}

/// Limits on what an archive may unpack to.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    pub max_unpacked_bytes: u64,
    pub max_entries: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// Malformed, truncated, or with a forbidden entry.
    #[error("{0}")]
    Bad(String),
    /// Over the unpacked-size or entry-count limit.
    #[error("{0}")]
    TooLarge(String),
    #[error("writing the extracted files: {0}")]
    Io(#[from] io::Error),
}

/// Checks an entry name and returns it as a relative path (`None` for the
/// archive's root folder itself, e.g. `./`).
pub fn safe_relative(name: &str) -> Result<Option<PathBuf>, ArchiveError> {
    let bad = |why: &str| Err(ArchiveError::Bad(format!("archive entry '{name}': {why}")));
    if name.contains('\0') || name.contains('\\') {
        return bad("name contains a backslash or NUL");
    }
    let mut out = PathBuf::new();
    for c in Path::new(name).components() {
        match c {
            Component::Normal(p) => out.push(p),
            Component::CurDir => {}
            Component::ParentDir => return bad("path contains '..'"),
            Component::RootDir | Component::Prefix(_) => return bad("absolute path"),
        }
    }
    Ok((!out.as_os_str().is_empty()).then_some(out))
}

/// Counts entries and bytes against the limits while writing.
struct Budget {
    limits: Limits,
    bytes: u64,
    entries: usize,
}

impl Budget {
    fn entry(&mut self) -> Result<(), ArchiveError> {
        self.entries += 1;
        if self.entries > self.limits.max_entries {
            return Err(ArchiveError::TooLarge(format!("archive has more than {} entries", self.limits.max_entries)));
        }
        Ok(())
    }

    /// Copies at most the remaining budget (plus one byte to detect excess).
    fn copy(&mut self, r: &mut dyn Read, dest: &Path, name: &str) -> Result<(), ArchiveError> {
        if let Some(p) = dest.parent() {
            fs::create_dir_all(p)?;
        }
        let mut f = match OpenOptions::new().write(true).create_new(true).open(dest) {
            Ok(f) => f,
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {
                return Err(ArchiveError::Bad(format!("archive entry '{name}' appears twice")));
            }
            Err(e) => return Err(e.into()),
        };
        let left = self.limits.max_unpacked_bytes - self.bytes;
        let n = copy_reading(&mut r.take(left + 1), &mut f, name)?;
        self.bytes += n;
        if self.bytes > self.limits.max_unpacked_bytes {
            return Err(ArchiveError::TooLarge(format!(
                "archive unpacks to more than {} bytes",
                self.limits.max_unpacked_bytes
            )));
        }
        Ok(())
    }
}

/// `io::copy` that reports read errors (corrupt data) as a bad archive and
/// write errors as I/O errors.
fn copy_reading(r: &mut dyn Read, w: &mut File, name: &str) -> Result<u64, ArchiveError> {
    use std::io::Write;
    let mut buf = vec![0u8; 64 * 1024];
    let mut total = 0u64;
    loop {
        let n = match r.read(&mut buf) {
            Ok(0) => return Ok(total),
            Ok(n) => n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(ArchiveError::Bad(format!("archive entry '{name}' is corrupt: {e}"))),
        };
        w.write_all(&buf[..n])?;
        total += n as u64;
    }
}

/// Extracts `bytes` into the existing empty folder `dest`. Returns the
/// unpacked size. On error `dest` may hold part of the files: the caller
/// removes it.
pub fn extract(kind: ArchiveKind, bytes: &[u8], dest: &Path, limits: Limits) -> Result<u64, ArchiveError> {
    let mut budget = Budget { limits, bytes: 0, entries: 0 };
    match kind {
        ArchiveKind::Zip => extract_zip(bytes, dest, &mut budget)?,
        ArchiveKind::Tar => extract_tar(bytes, dest, &mut budget)?,
        ArchiveKind::TarGz => extract_tar(flate2::read::MultiGzDecoder::new(bytes), dest, &mut budget)?,
    }
    Ok(budget.bytes)
}

fn extract_zip(bytes: &[u8], dest: &Path, budget: &mut Budget) -> Result<(), ArchiveError> {
    let mut zip = zip::ZipArchive::new(io::Cursor::new(bytes))
        .map_err(|e| ArchiveError::Bad(format!("not a valid zip archive: {e}")))?;
    for i in 0..zip.len() {
        budget.entry()?;
        let mut f = zip.by_index(i).map_err(|e| ArchiveError::Bad(format!("zip entry {i}: {e}")))?;
        let name = f.name().map_err(|e| ArchiveError::Bad(format!("zip entry {i}: bad name: {e}")))?.into_owned();
        let Some(rel) = safe_relative(&name)? else { continue };
        if f.is_symlink() {
            return Err(ArchiveError::Bad(format!("archive entry '{name}' is a link (not allowed)")));
        }
        if f.is_dir() {
            fs::create_dir_all(dest.join(rel))?;
        } else if f.is_file() {
            budget.copy(&mut f, &dest.join(rel), &name)?;
        } else {
            return Err(ArchiveError::Bad(format!("archive entry '{name}' is not a file or folder")));
        }
    }
    Ok(())
}

fn extract_tar<R: Read>(reader: R, dest: &Path, budget: &mut Budget) -> Result<(), ArchiveError> {
    use tar::EntryType as T;
    let mut ar = tar::Archive::new(reader);
    let entries = ar.entries().map_err(|e| ArchiveError::Bad(format!("not a valid tar archive: {e}")))?;
    for entry in entries {
        let mut e = entry.map_err(|e| ArchiveError::Bad(format!("not a valid tar archive: {e}")))?;
        let kind = e.header().entry_type();
        if matches!(kind, T::XGlobalHeader | T::XHeader | T::GNULongName | T::GNULongLink) {
            continue;
        }
        budget.entry()?;
        let raw = e.path_bytes();
        let name = String::from_utf8_lossy(&raw).into_owned();
        let Some(rel) = safe_relative(&name)? else { continue };
        match kind {
            T::Regular | T::Continuous => budget.copy(&mut e, &dest.join(rel), &name)?,
            T::Directory => fs::create_dir_all(dest.join(rel))?,
            T::Symlink | T::Link => {
                return Err(ArchiveError::Bad(format!("archive entry '{name}' is a link (not allowed)")));
            }
            _ => return Err(ArchiveError::Bad(format!("archive entry '{name}' is not a file or folder"))),
        }
    }
    Ok(())
}

/// The folder holding the dataset: `dir` itself, or the single folder it
/// contains when the archive wrapped the dataset in one (`lego/...`).
pub fn dataset_root(dir: &Path) -> PathBuf {
    let mut d = dir.to_path_buf();
    for _ in 0..4 {
        if crate::engine::dataset::detect_format(&d).is_ok() {
            break;
        }
        let Ok(rd) = fs::read_dir(&d) else { break };
        let subdirs: Vec<PathBuf> = rd
            .filter_map(|e| e.ok())
            .filter(|e| {
                let n = e.file_name();
                let n = n.to_string_lossy();
                !n.starts_with('.') && n != "__MACOSX"
            })
            .map(|e| e.path())
            .collect();
        match subdirs.as_slice() {
            [only] if only.is_dir() => d = only.clone(),
            _ => break,
        }
    }
    d
}

/// Total size of the regular files under a folder.
pub fn dir_size(dir: &Path) -> u64 {
    let Ok(rd) = fs::read_dir(dir) else { return 0 };
    rd.filter_map(|e| e.ok())
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => dir_size(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map_or(0, |m| m.len()),
            _ => 0,
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entry_names() {
        assert_eq!(safe_relative("a/b.png").unwrap(), Some(PathBuf::from("a/b.png")));
        assert_eq!(safe_relative("./a/./b").unwrap(), Some(PathBuf::from("a/b")));
        assert_eq!(safe_relative("./").unwrap(), None);
        for bad in ["../x", "a/../../x", "/etc/passwd", "a\\..\\b", "a/.."] {
            assert!(safe_relative(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn content_types() {
        assert_eq!(ArchiveKind::from_content_type("application/zip"), Some(ArchiveKind::Zip));
        assert_eq!(ArchiveKind::from_content_type("application/gzip; x=1"), Some(ArchiveKind::TarGz));
        assert_eq!(ArchiveKind::from_content_type("text/plain"), None);
    }
}
