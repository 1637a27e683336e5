//! Safe extraction of uploaded archives (zip, tar, tar.gz).
//!
//! Every entry name must be a relative path of plain components (no `..`,
//! no root, no drive prefix, no backslash); only regular files and folders
//! are accepted (links, devices and fifos are refused). Sizes are checked
//! twice. First from what the archive declares, before anything is written:
//! a zip's central directory (the declared total, and each entry's
//! compression ratio), a tar entry's header before that entry is copied; so
//! a decompression bomb is refused without unpacking it. Then on the bytes
//! actually written, since declared sizes can lie: extraction stops at the
//! limit. The caller extracts into a fresh temporary folder and removes it on
//! any error.

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

/// A limit an upload passed, and its value.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Limit {
    Bytes(u64),
    Entries(usize),
    Ratio(u64),
}

#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    /// Malformed, truncated, or with a forbidden entry.
    #[error("{0}")]
    Bad(String),
    /// Over the unpacked-size, entry-count or compression-ratio limit.
    #[error("{message}")]
    TooLarge { message: String, limit: Limit },
    #[error("writing the extracted files: {0}")]
    Io(#[from] io::Error),
}

/// The longest entry name accepted, bytes (the data directory's own path
/// and the upload's folders come before it, within Linux's 4096).
pub const MAX_NAME_BYTES: usize = 1024;

/// The longest folder or file name in an entry name, bytes (Linux's).
pub const MAX_COMPONENT_BYTES: usize = 255;

/// Checks an entry name and returns it as a relative path (`None` for the
/// archive's root folder itself, e.g. `./`).
pub fn safe_relative(name: &str) -> Result<Option<PathBuf>, ArchiveError> {
    let shown: String = name.chars().take(100).collect();
    let shown = if shown.len() < name.len() { format!("{shown}...") } else { shown };
    let bad = |why: &str| Err(ArchiveError::Bad(format!("archive entry '{shown}': {why}")));
    if name.contains('\0') || name.contains('\\') {
        return bad("name contains a backslash or NUL");
    }
    // The file system refuses longer names (ENAMETOOLONG), which would be
    // the server's error rather than the client's.
    if name.len() > MAX_NAME_BYTES {
        return bad(&format!("name is {} bytes long, more than {MAX_NAME_BYTES}", name.len()));
    }
    let mut out = PathBuf::new();
    for c in Path::new(name).components() {
        match c {
            Component::Normal(p) if p.len() > MAX_COMPONENT_BYTES => {
                return bad(&format!("a folder or file name in it is longer than {MAX_COMPONENT_BYTES} bytes"));
            }
            Component::Normal(p) => out.push(p),
            Component::CurDir => {}
            Component::ParentDir => return bad("path contains '..'"),
            Component::RootDir | Component::Prefix(_) => return bad("absolute path"),
        }
    }
    Ok((!out.as_os_str().is_empty()).then_some(out))
}

/// Entries declaring more than this unpacked are checked for their
/// compression ratio; smaller ones cannot do harm whatever their ratio.
pub const RATIO_CHECKED_ABOVE: u64 = 4 << 20;

/// The largest compression ratio accepted for an entry over
/// [`RATIO_CHECKED_ABOVE`]. Datasets are images that are already compressed
/// (about 1:1) and JSON or NumPy files (a few to a few tens to one); only
/// near-constant data packs better, and that is what bombs are made of
/// (deflate packs zeros at up to about 1030:1, or 230:1 at its fastest
/// level). 100:1 is Apache POI's bound for zip bombs, and catches a bomb
/// packed at any level while leaving a wide margin for real data.
pub const MAX_RATIO: u64 = 100;

/// Counts entries and bytes against the limits while writing.
struct Budget {
    limits: Limits,
    bytes: u64,
    entries: usize,
}

impl Budget {
    /// Refuses an entry whose declared size would take the total past the
    /// limit, before any of it is written.
    fn declared(&self, size: u64, name: &str) -> Result<(), ArchiveError> {
        let limit = self.limits.max_unpacked_bytes;
        if self.bytes.saturating_add(size) > limit {
            let message = format!(
                "archive entry '{name}' declares {size} bytes, which would unpack the archive past the limit of \
                 {limit} bytes"
            );
            return Err(ArchiveError::TooLarge { message, limit: Limit::Bytes(limit) });
        }
        Ok(())
    }

    fn entry(&mut self) -> Result<(), ArchiveError> {
        self.entries += 1;
        if self.entries > self.limits.max_entries {
            let (message, max) =
                (format!("archive has more than {} entries", self.limits.max_entries), self.limits.max_entries);
            return Err(ArchiveError::TooLarge { message, limit: Limit::Entries(max) });
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
            let max = self.limits.max_unpacked_bytes;
            let message = format!("archive unpacks to more than {max} bytes");
            return Err(ArchiveError::TooLarge { message, limit: Limit::Bytes(max) });
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
    check_zip_declared(&mut zip, budget.limits)?;
    if let Some(name) = zip_repeated_name(bytes) {
        // The zip reader keeps one entry per name: the other would vanish.
        return Err(ArchiveError::Bad(format!("archive entry '{name}' appears twice")));
    }
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

/// The first name a zip's central directory lists twice, read from its
/// end-of-directory record and the directory's headers (the zip crate
/// keeps one entry per name). `None` when there is none, or when the
/// directory cannot be walked this simply (zip64, data before the archive):
/// the zip reader then judges it alone.
fn zip_repeated_name(bytes: &[u8]) -> Option<String> {
    let u16_at = |at: usize| bytes.get(at..at + 2).map(|b| u16::from_le_bytes([b[0], b[1]]) as usize);
    let u32_at = |at: usize| bytes.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
    // The end record: its signature in the last 22 + 65535 bytes.
    let from = bytes.len().saturating_sub(22 + 0xffff);
    let eocd = (from..bytes.len().saturating_sub(21)).rev().find(|&i| bytes[i..i + 4] == *b"PK\x05\x06")?;
    let (count, mut at) = (u16_at(eocd + 10)?, u32_at(eocd + 16)?);
    if count == 0xffff || at == 0xffff_ffff {
        return None;
    }
    let mut seen = std::collections::HashSet::with_capacity(count);
    for _ in 0..count {
        if bytes.get(at..at + 4)? != b"PK\x01\x02" {
            return None;
        }
        let (name_len, extra, comment) = (u16_at(at + 28)?, u16_at(at + 30)?, u16_at(at + 32)?);
        let name = bytes.get(at + 46..at + 46 + name_len)?;
        if !seen.insert(name) {
            return Some(String::from_utf8_lossy(name).into_owned());
        }
        at += 46 + name_len + extra + comment;
    }
    None
}

/// Refuses a zip from its central directory alone: when the declared sizes
/// add up to more than the limit, or when an entry over
/// [`RATIO_CHECKED_ABOVE`] declares a ratio over [`MAX_RATIO`]:1.
fn check_zip_declared(zip: &mut zip::ZipArchive<io::Cursor<&[u8]>>, limits: Limits) -> Result<(), ArchiveError> {
    let (mut total, mut bomb) = (0u64, None);
    for i in 0..zip.len() {
        let f = zip.by_index_raw(i).map_err(|e| ArchiveError::Bad(format!("zip entry {i}: {e}")))?;
        let (size, packed) = (f.size(), f.compressed_size());
        total = total.saturating_add(size);
        if bomb.is_none() && size > RATIO_CHECKED_ABOVE && size / packed.max(1) > MAX_RATIO {
            bomb = Some((String::from_utf8_lossy(f.name_raw()).into_owned(), size, packed));
        }
    }
    let limit = limits.max_unpacked_bytes;
    if total > limit {
        let message = format!("archive declares {total} bytes unpacked, more than the limit of {limit} bytes");
        return Err(ArchiveError::TooLarge { message, limit: Limit::Bytes(limit) });
    }
    if let Some((name, size, packed)) = bomb {
        let message = format!(
            "archive entry '{name}' declares {size} bytes packed into {packed}: a ratio over {MAX_RATIO}:1 \
             (for entries over {RATIO_CHECKED_ABOVE} bytes) is refused as a decompression bomb"
        );
        return Err(ArchiveError::TooLarge { message, limit: Limit::Ratio(MAX_RATIO) });
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
            T::Regular | T::Continuous => {
                budget.declared(e.size(), &name)?;
                budget.copy(&mut e, &dest.join(rel), &name)?;
            }
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
        if crate::engine::front::detect_format(&d).is_ok() {
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
        // Names the file system would refuse are the client's error, named.
        let long = format!("images/{}.png", "n".repeat(251));
        assert!(safe_relative(&long).is_ok());
        let longer = format!("images/{}.png", "n".repeat(252));
        let e = safe_relative(&longer).unwrap_err().to_string();
        assert!(e.contains("longer than 255 bytes") && e.len() < 300, "{e}");
        let deep = "d/".repeat(600) + "x.png";
        let e = safe_relative(&deep).unwrap_err().to_string();
        assert!(e.contains("1205 bytes long, more than 1024"), "{e}");
    }

    #[test]
    fn content_types() {
        assert_eq!(ArchiveKind::from_content_type("application/zip"), Some(ArchiveKind::Zip));
        assert_eq!(ArchiveKind::from_content_type("application/gzip; x=1"), Some(ArchiveKind::TarGz));
        assert_eq!(ArchiveKind::from_content_type("text/plain"), None);
    }

    use std::io::Write;

    fn limits(max_unpacked_bytes: u64) -> Limits {
        Limits { max_unpacked_bytes, max_entries: 100 }
    }

    /// A zip of `entries`, deflated at `level` (`None`: the default).
    fn zip_of(entries: &[(&str, &[u8])], level: Option<i64>) -> Vec<u8> {
        let mut w = zip::ZipWriter::new(io::Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated)
            .compression_level(level);
        for (name, data) in entries {
            w.start_file(*name, opts).unwrap();
            w.write_all(data).unwrap();
        }
        w.finish().unwrap().into_inner()
    }

    /// Bytes that do not compress (a xorshift stream).
    fn noise(n: usize) -> Vec<u8> {
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        (0..n)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                x as u8
            })
            .collect()
    }

    /// Extracts into a fresh folder; returns the result and the names left in it.
    fn extract_listing(kind: ArchiveKind, bytes: &[u8], limits: Limits) -> (Result<u64, ArchiveError>, Vec<String>) {
        let dir = tempfile::tempdir().unwrap();
        let r = extract(kind, bytes, dir.path(), limits);
        let left = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
        (r, left)
    }

    fn too_large(r: Result<u64, ArchiveError>) -> String {
        match r {
            Err(ArchiveError::TooLarge { message, .. }) => message,
            other => panic!("expected TooLarge, got {other:?}"),
        }
    }

    /// Renames every `from` to `to` (of the same length) in a zip's bytes:
    /// its local and central headers both, as a hand-made zip may have them.
    fn rename_in(zip: &mut [u8], from: &[u8], to: &[u8]) {
        for i in 0..zip.len() - from.len() {
            if &zip[i..i + from.len()] == from {
                zip[i..i + from.len()].copy_from_slice(to);
            }
        }
    }

    #[test]
    fn a_zip_naming_an_entry_twice_is_refused() {
        let mut zip = zip_of(&[("images/a.png", b"first"), ("images/b.png", b"second")], None);
        assert!(zip_repeated_name(&zip).is_none());
        rename_in(&mut zip, b"images/b.png", b"images/a.png");
        // The zip reader itself sees one entry (it keeps one per name).
        assert_eq!(zip::ZipArchive::new(io::Cursor::new(&zip[..])).unwrap().len(), 1);
        let (r, _) = extract_listing(ArchiveKind::Zip, &zip, limits(1 << 20));
        match r {
            Err(ArchiveError::Bad(m)) => assert_eq!(m, "archive entry 'images/a.png' appears twice"),
            other => panic!("expected Bad, got {other:?}"),
        }
        // Junk after or before the directory does not confuse the walk.
        assert!(zip_repeated_name(b"PK\x05\x06").is_none() && zip_repeated_name(b"").is_none());
    }

    #[test]
    fn zip_declaring_more_than_the_limit_is_refused_before_writing() {
        let zeros = vec![0u8; 64 << 20];
        let zip = zip_of(&[("a.txt", b"hello"), ("zeros.bin", &zeros)], None);
        assert!(zip.len() < 100 << 10, "{} bytes", zip.len());
        let (r, left) = extract_listing(ArchiveKind::Zip, &zip, limits(16 << 20));
        let m = too_large(r);
        // The message gives the declared total and the limit: it was read
        // from the central directory, not counted while writing.
        assert!(m.contains(&format!("declares {} bytes", (64 << 20) + 5)) && m.contains("16777216"), "{m}");
        assert!(left.is_empty(), "written before refusing: {left:?}");
    }

    #[test]
    fn zip_entries_with_absurd_ratios_are_refused_before_writing() {
        // 8 MiB of zeros: deflate packs them about 230:1 at its fastest
        // level and 1000:1 at its default; both are bombs.
        let zeros = vec![0u8; 8 << 20];
        for level in [Some(1), None] {
            let zip = zip_of(&[("a.txt", b"hello"), ("zeros.bin", &zeros)], level);
            let (r, left) = extract_listing(ArchiveKind::Zip, &zip, limits(1 << 30));
            let m = too_large(r);
            assert!(m.contains("'zeros.bin' declares 8388608 bytes") && m.contains("ratio over 100:1"), "{m}");
            assert!(left.is_empty(), "written before refusing: {left:?}");
        }
        // Small entries may pack as well as they like; large ones of real data pass.
        let zip = zip_of(&[("small.bin", &vec![0u8; 2 << 20]), ("large.bin", &noise(6 << 20))], None);
        let (r, left) = extract_listing(ArchiveKind::Zip, &zip, limits(1 << 30));
        assert_eq!(r.unwrap(), 8 << 20);
        assert_eq!(left.len(), 2);
    }

    #[test]
    fn zip_lying_about_its_sizes_stops_at_the_limit() {
        // 8 MiB of zeros whose headers claim 1000 bytes: the declared checks
        // pass; extraction still stops (the zip reader refuses data past the
        // declared size, and the bytes written are counted against the limit).
        let mut zip = zip_of(&[("zeros.bin", &vec![0u8; 8 << 20])], None);
        let patch = |zip: &mut Vec<u8>, signature: &[u8], offset: usize| {
            let at = zip.windows(4).position(|w| w == signature).unwrap();
            zip[at + offset..at + offset + 4].copy_from_slice(&1000u32.to_le_bytes());
        };
        patch(&mut zip, b"PK\x03\x04", 22);
        patch(&mut zip, b"PK\x01\x02", 24);
        let dir = tempfile::tempdir().unwrap();
        let r = extract(ArchiveKind::Zip, &zip, dir.path(), limits(1 << 20));
        assert!(r.is_err(), "{r:?}");
        assert!(dir_size(dir.path()) <= 1 << 20, "{} bytes written", dir_size(dir.path()));
    }

    /// A tar.gz with one entry whose header declares `declared` bytes,
    /// followed by `data` (possibly fewer bytes: a truncated archive).
    fn tar_gz_declaring(declared: u64, data: &[u8]) -> Vec<u8> {
        let mut h = tar::Header::new_gnu();
        h.set_path("big.bin").unwrap();
        h.set_size(declared);
        h.set_mode(0o644);
        h.set_entry_type(tar::EntryType::Regular);
        h.set_cksum();
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        let mut first = tar::Builder::new(Vec::new());
        let mut small = tar::Header::new_gnu();
        small.set_size(5);
        small.set_mode(0o644);
        small.set_entry_type(tar::EntryType::Regular);
        first.append_data(&mut small, "a.txt", &b"hello"[..]).unwrap();
        let mut head = first.into_inner().unwrap();
        head.truncate(head.len() - 1024); // without the end-of-archive blocks
        gz.write_all(&head).unwrap();
        gz.write_all(h.as_bytes()).unwrap();
        gz.write_all(data).unwrap();
        gz.finish().unwrap()
    }

    #[test]
    fn tar_entries_declaring_past_the_limit_are_refused_before_copying() {
        // A header claiming 1 GiB with a few bytes behind it: refused from
        // the header (413), not read to its end (which would be "corrupt").
        let (r, left) = extract_listing(ArchiveKind::TarGz, &tar_gz_declaring(1 << 30, b"x"), limits(16 << 20));
        let m = too_large(r);
        assert!(m.contains("'big.bin' declares 1073741824 bytes") && m.contains("16777216"), "{m}");
        assert_eq!(left, ["a.txt"], "the entry over the limit is not started");
        // Within the limit, the same layout unpacks.
        let data = vec![7u8; 1024];
        let (r, mut left) = extract_listing(ArchiveKind::TarGz, &tar_gz_declaring(1024, &data), limits(16 << 20));
        assert_eq!(r.unwrap(), 1029);
        left.sort();
        assert_eq!(left, ["a.txt", "big.bin"]);
    }
}
