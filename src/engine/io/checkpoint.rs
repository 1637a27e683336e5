//! A versioned binary checkpoint container, generic over models.
//!
//! A checkpoint holds a model kind, the training step, free-form JSON
//! metadata (model config, scene normalisation, trainer state) and a list of
//! named flat tensors (parameters, optimiser moments, occupancy grids, ...).
//!
//! # Layout (all integers little-endian)
//!
//! | bytes            | content                                              |
//! |------------------|------------------------------------------------------|
//! | 8                | magic `RADIANCE`                                     |
//! | 4                | format version, `u32` ([`FORMAT_VERSION`])           |
//! | 4                | header length `H`, `u32`                             |
//! | `H`              | header, UTF-8 JSON: `{"kind", "step", "meta", "tensors": [{"name", "dtype": "f32"\|"u8"\|"u64", "len"}]}` |
//! | sum of payloads  | each tensor's elements in header order, no padding   |
//! | 4                | CRC-32 (IEEE, as `crc32fast`) of every preceding byte |
//!
//! Reading validates everything before allocating: a header length or tensor
//! length that points past the end of the data is a [`CheckpointError::Truncated`]
//! error, never a huge allocation. Non-finite `f32` values are stored bit-exactly;
//! guarding against them is the trainer's job.
//!
//! Tensor names should be unique ([`Checkpoint::insert`] keeps them so); the
//! lookups return the first tensor of a given name.

use std::fmt;
use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::engine::io::fsio;

/// The first eight bytes of every checkpoint.
pub const MAGIC: [u8; 8] = *b"RADIANCE";
/// The container version written by this build, and the newest it reads.
pub const FORMAT_VERSION: u32 = 1;

/// Magic, version and header length.
const PREAMBLE: u64 = 16;
/// The smallest possible file: preamble and checksum around an empty header.
const MIN_LEN: u64 = PREAMBLE + 4;
/// Elements converted per chunk when writing.
const WRITE_CHUNK: usize = 16 * 1024;

/// A named flat parameter buffer.
#[derive(Clone, Debug, PartialEq)]
pub enum Tensor {
    F32(Vec<f32>),
    U8(Vec<u8>),
    U64(Vec<u64>),
}

impl Tensor {
    /// The dtype as stored in the header: `"f32"`, `"u8"` or `"u64"`.
    pub fn dtype(&self) -> &'static str {
        self.dtype_enum().name()
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            Tensor::F32(v) => v.len(),
            Tensor::U8(v) => v.len(),
            Tensor::U64(v) => v.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Size of the payload in bytes.
    pub fn byte_len(&self) -> u64 {
        self.len() as u64 * self.dtype_enum().size()
    }

    fn dtype_enum(&self) -> DType {
        match self {
            Tensor::F32(_) => DType::F32,
            Tensor::U8(_) => DType::U8,
            Tensor::U64(_) => DType::U64,
        }
    }
}

impl From<Vec<f32>> for Tensor {
    fn from(v: Vec<f32>) -> Self {
        Tensor::F32(v)
    }
}

impl From<Vec<u8>> for Tensor {
    fn from(v: Vec<u8>) -> Self {
        Tensor::U8(v)
    }
}

impl From<Vec<u64>> for Tensor {
    fn from(v: Vec<u64>) -> Self {
        Tensor::U64(v)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum DType {
    F32,
    U8,
    U64,
}

impl DType {
    fn name(self) -> &'static str {
        match self {
            DType::F32 => "f32",
            DType::U8 => "u8",
            DType::U64 => "u64",
        }
    }

    fn size(self) -> u64 {
        match self {
            DType::F32 => 4,
            DType::U8 => 1,
            DType::U64 => 8,
        }
    }

    fn parse(s: &str) -> Option<DType> {
        match s {
            "f32" => Some(DType::F32),
            "u8" => Some(DType::U8),
            "u64" => Some(DType::U64),
            _ => None,
        }
    }
}

/// Element types that can be read out of a [`Tensor`].
trait Element: Sized {
    const DTYPE: DType;
    fn view(t: &Tensor) -> Option<&[Self]>;
    fn into_vec(t: Tensor) -> Result<Vec<Self>, Tensor>;
}

macro_rules! element {
    ($ty:ty, $variant:ident) => {
        impl Element for $ty {
            const DTYPE: DType = DType::$variant;
            fn view(t: &Tensor) -> Option<&[Self]> {
                match t {
                    Tensor::$variant(v) => Some(v),
                    _ => None,
                }
            }
            fn into_vec(t: Tensor) -> Result<Vec<Self>, Tensor> {
                match t {
                    Tensor::$variant(v) => Ok(v),
                    other => Err(other),
                }
            }
        }
    };
}

element!(f32, F32);
element!(u8, U8);
element!(u64, U64);

/// A model checkpoint: see the module documentation for the file layout.
#[derive(Clone, Debug, PartialEq)]
pub struct Checkpoint {
    /// Model kind, e.g. "nerf" or "instant".
    pub kind: String,
    /// Training step.
    pub step: u64,
    /// Model config, scene normalisation, trainer state.
    pub meta: serde_json::Value,
    /// Named parameter buffers: "params", "adam.m", "adam.v", ...
    pub tensors: Vec<(String, Tensor)>,
}

/// Why a checkpoint could not be read, written or queried. Variants carry the
/// file's path when it is known, and their `Display` starts with it
/// (`"model.ckpt: checksum mismatch: file is corrupted"`).
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{}: {source}", .path.display())]
    Io { path: PathBuf, source: io::Error },
    #[error("{}not a radiance checkpoint", Prefix(.path))]
    NotACheckpoint { path: Option<PathBuf> },
    #[error("{}{}", Prefix(.path), version_message(*.found))]
    UnsupportedVersion { path: Option<PathBuf>, found: u32 },
    /// `expected` is the size implied by what could be read; when the cut
    /// falls inside the preamble or header it is a lower bound.
    #[error("{}truncated: expected {expected} bytes, found {found}", Prefix(.path))]
    Truncated { path: Option<PathBuf>, expected: u64, found: u64 },
    #[error("{}checksum mismatch: file is corrupted", Prefix(.path))]
    ChecksumMismatch { path: Option<PathBuf> },
    #[error("{}invalid checkpoint header: {message}", Prefix(.path))]
    Header { path: Option<PathBuf>, message: String },
    #[error("{}{extra} unexpected bytes after the end of the checkpoint", Prefix(.path))]
    TrailingBytes { path: Option<PathBuf>, extra: u64 },
    #[error("{}checkpoint has no tensor named {name:?}", Prefix(.path))]
    MissingTensor { path: Option<PathBuf>, name: String },
    #[error("{}tensor {name:?} has dtype {found}, expected {expected}", Prefix(.path))]
    WrongType { path: Option<PathBuf>, name: String, expected: &'static str, found: &'static str },
}

impl CheckpointError {
    /// The file the error is about, when known.
    pub fn path(&self) -> Option<&Path> {
        match self {
            CheckpointError::Io { path, .. } => Some(path),
            CheckpointError::NotACheckpoint { path }
            | CheckpointError::UnsupportedVersion { path, .. }
            | CheckpointError::Truncated { path, .. }
            | CheckpointError::ChecksumMismatch { path }
            | CheckpointError::Header { path, .. }
            | CheckpointError::TrailingBytes { path, .. }
            | CheckpointError::MissingTensor { path, .. }
            | CheckpointError::WrongType { path, .. } => path.as_deref(),
        }
    }

    /// Attaches `path` if the error does not name a file yet, e.g.
    /// `ckpt.f32("params").map_err(|e| e.with_path(file))`.
    pub fn with_path(mut self, file: &Path) -> Self {
        match &mut self {
            CheckpointError::Io { .. } => {}
            CheckpointError::NotACheckpoint { path }
            | CheckpointError::UnsupportedVersion { path, .. }
            | CheckpointError::Truncated { path, .. }
            | CheckpointError::ChecksumMismatch { path }
            | CheckpointError::Header { path, .. }
            | CheckpointError::TrailingBytes { path, .. }
            | CheckpointError::MissingTensor { path, .. }
            | CheckpointError::WrongType { path, .. } => {
                if path.is_none() {
                    *path = Some(file.to_path_buf());
                }
            }
        }
        self
    }
}

/// Displays `"<path>: "` or nothing.
struct Prefix<'a>(&'a Option<PathBuf>);

impl fmt::Display for Prefix<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(p) => write!(f, "{}: ", p.display()),
            None => Ok(()),
        }
    }
}

fn version_message(found: u32) -> String {
    if found > FORMAT_VERSION {
        format!("checkpoint format version {found} is newer than this build supports ({FORMAT_VERSION})")
    } else {
        format!("checkpoint format version {found} is not supported (this build reads version {FORMAT_VERSION})")
    }
}

#[derive(Serialize)]
struct HeaderOut<'a> {
    kind: &'a str,
    step: u64,
    meta: &'a serde_json::Value,
    tensors: Vec<EntryOut<'a>>,
}

#[derive(Serialize)]
struct EntryOut<'a> {
    name: &'a str,
    dtype: &'static str,
    len: u64,
}

#[derive(Deserialize)]
struct HeaderIn {
    kind: String,
    step: u64,
    meta: serde_json::Value,
    tensors: Vec<EntryIn>,
}

#[derive(Deserialize)]
struct EntryIn {
    name: String,
    dtype: String,
    len: u64,
}

/// Forwards writes and hashes exactly the bytes that were accepted.
struct CrcWriter<W: Write> {
    inner: W,
    hasher: crc32fast::Hasher,
}

impl<W: Write> Write for CrcWriter<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// Writes `values` little-endian through a bounded scratch buffer.
fn write_le<T: Copy, const N: usize>(w: &mut impl Write, values: &[T], to_le: impl Fn(T) -> [u8; N]) -> io::Result<()> {
    let mut buf = Vec::with_capacity(WRITE_CHUNK.min(values.len()) * N);
    for chunk in values.chunks(WRITE_CHUNK) {
        buf.clear();
        for &v in chunk {
            buf.extend_from_slice(&to_le(v));
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

impl Checkpoint {
    /// An empty checkpoint with `null` metadata.
    pub fn new(kind: impl Into<String>, step: u64) -> Self {
        Checkpoint { kind: kind.into(), step, meta: serde_json::Value::Null, tensors: Vec::new() }
    }

    /// Adds a tensor, replacing any tensor of the same name in place.
    pub fn insert(&mut self, name: impl Into<String>, tensor: impl Into<Tensor>) {
        let name = name.into();
        let tensor = tensor.into();
        match self.tensors.iter_mut().find(|(n, _)| *n == name) {
            Some(slot) => slot.1 = tensor,
            None => self.tensors.push((name, tensor)),
        }
    }

    fn header_json(&self) -> Vec<u8> {
        let header = HeaderOut {
            kind: &self.kind,
            step: self.step,
            meta: &self.meta,
            tensors: self
                .tensors
                .iter()
                .map(|(name, t)| EntryOut { name, dtype: t.dtype(), len: t.len() as u64 })
                .collect(),
        };
        // Serialising strings, integers and a `Value` cannot fail.
        serde_json::to_vec(&header).expect("checkpoint header serialises")
    }

    /// Streams the encoded checkpoint into `w` (no copy of the whole file is
    /// made). Fails with `InvalidInput` if the JSON header exceeds 4 GiB.
    pub fn write_to<W: Write>(&self, w: W) -> io::Result<()> {
        let header = self.header_json();
        let header_len = u32::try_from(header.len())
            .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "checkpoint header exceeds 4 GiB"))?;
        let mut w = CrcWriter { inner: w, hasher: crc32fast::Hasher::new() };
        w.write_all(&MAGIC)?;
        w.write_all(&FORMAT_VERSION.to_le_bytes())?;
        w.write_all(&header_len.to_le_bytes())?;
        w.write_all(&header)?;
        for (_, t) in &self.tensors {
            match t {
                Tensor::F32(v) => write_le(&mut w, v, f32::to_le_bytes)?,
                Tensor::U8(v) => w.write_all(v)?,
                Tensor::U64(v) => write_le(&mut w, v, u64::to_le_bytes)?,
            }
        }
        let crc = w.hasher.finalize();
        w.inner.write_all(&crc.to_le_bytes())
    }

    /// The encoded checkpoint.
    ///
    /// # Panics
    /// If the JSON header exceeds 4 GiB (use [`Checkpoint::save`] or
    /// [`Checkpoint::write_to`] to get an error instead).
    pub fn to_bytes(&self) -> Vec<u8> {
        let payload: u64 = self.tensors.iter().map(|(_, t)| t.byte_len()).sum();
        let mut out = Vec::with_capacity(usize::try_from(payload + 4096).unwrap_or(0));
        self.write_to(&mut out).expect("checkpoint header exceeds 4 GiB");
        out
    }

    /// Decodes a checkpoint, validating magic, version, sizes and checksum.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, CheckpointError> {
        parse(bytes, None)
    }

    /// Writes the checkpoint atomically (temporary file, fsync, rename), so
    /// a crash never leaves a half-written checkpoint at `path`.
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        fsio::write_atomic_with(path, |w| self.write_to(w))
            .map_err(|source| CheckpointError::Io { path: path.to_path_buf(), source })
    }

    /// Reads and validates a checkpoint; every error names `path`.
    pub fn load(path: &Path) -> Result<Self, CheckpointError> {
        let bytes = fs::read(path).map_err(|source| CheckpointError::Io { path: path.to_path_buf(), source })?;
        parse(&bytes, Some(path))
    }

    /// The first tensor named `name`.
    pub fn tensor(&self, name: &str) -> Option<&Tensor> {
        self.tensors.iter().find(|(n, _)| n == name).map(|(_, t)| t)
    }

    /// Mutable access to the first tensor named `name`.
    pub fn tensor_mut(&mut self, name: &str) -> Option<&mut Tensor> {
        self.tensors.iter_mut().find(|(n, _)| n == name).map(|(_, t)| t)
    }

    fn missing(name: &str) -> CheckpointError {
        CheckpointError::MissingTensor { path: None, name: name.to_string() }
    }

    fn wrong_type<T: Element>(name: &str, t: &Tensor) -> CheckpointError {
        CheckpointError::WrongType { path: None, name: name.to_string(), expected: T::DTYPE.name(), found: t.dtype() }
    }

    fn view<T: Element>(&self, name: &str) -> Result<&[T], CheckpointError> {
        let t = self.tensor(name).ok_or_else(|| Self::missing(name))?;
        T::view(t).ok_or_else(|| Self::wrong_type::<T>(name, t))
    }

    fn take<T: Element>(&mut self, name: &str) -> Result<Vec<T>, CheckpointError> {
        let i = self.tensors.iter().position(|(n, _)| n == name).ok_or_else(|| Self::missing(name))?;
        let (n, t) = self.tensors.remove(i);
        match T::into_vec(t) {
            Ok(v) => Ok(v),
            Err(t) => {
                let err = Self::wrong_type::<T>(name, &t);
                self.tensors.insert(i, (n, t));
                Err(err)
            }
        }
    }

    /// The `f32` tensor `name` (`MissingTensor` / `WrongType` otherwise).
    pub fn f32(&self, name: &str) -> Result<&[f32], CheckpointError> {
        self.view(name)
    }

    /// The `u8` tensor `name` (`MissingTensor` / `WrongType` otherwise).
    pub fn u8(&self, name: &str) -> Result<&[u8], CheckpointError> {
        self.view(name)
    }

    /// The `u64` tensor `name` (`MissingTensor` / `WrongType` otherwise).
    pub fn u64(&self, name: &str) -> Result<&[u64], CheckpointError> {
        self.view(name)
    }

    /// Removes the `f32` tensor `name` from the checkpoint and returns its
    /// buffer without copying. On a type mismatch the tensor stays in place.
    pub fn take_f32(&mut self, name: &str) -> Result<Vec<f32>, CheckpointError> {
        self.take(name)
    }

    /// Like [`Checkpoint::take_f32`], for `u8` tensors.
    pub fn take_u8(&mut self, name: &str) -> Result<Vec<u8>, CheckpointError> {
        self.take(name)
    }

    /// Like [`Checkpoint::take_f32`], for `u64` tensors.
    pub fn take_u64(&mut self, name: &str) -> Result<Vec<u64>, CheckpointError> {
        self.take(name)
    }
}

fn crc_ok(data_and_crc: &[u8]) -> bool {
    let (data, crc) = data_and_crc.split_at(data_and_crc.len() - 4);
    crc32fast::hash(data).to_le_bytes() == crc
}

fn read_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

fn parse(bytes: &[u8], path: Option<&Path>) -> Result<Checkpoint, CheckpointError> {
    use CheckpointError as E;
    let p = || path.map(Path::to_path_buf);
    let found = bytes.len() as u64;
    let truncated = |expected: u64| E::Truncated { path: p(), expected, found };

    if bytes.len() < MAGIC.len() {
        // A prefix of the magic (including an empty file) is a cut-off checkpoint.
        return Err(if MAGIC.starts_with(bytes) { truncated(MIN_LEN) } else { E::NotACheckpoint { path: p() } });
    }
    if bytes[..8] != MAGIC {
        return Err(E::NotACheckpoint { path: p() });
    }
    if bytes.len() < 12 {
        return Err(truncated(MIN_LEN));
    }
    let version = read_u32(bytes, 8);
    if version != FORMAT_VERSION {
        return Err(E::UnsupportedVersion { path: p(), found: version });
    }
    if bytes.len() < PREAMBLE as usize {
        return Err(truncated(MIN_LEN));
    }
    let header_end = PREAMBLE + read_u32(bytes, 12) as u64;
    if header_end + 4 > found {
        return Err(truncated(header_end + 4));
    }
    let header_end = header_end as usize;

    // A header that does not make sense is most likely corruption: report it
    // as such unless the whole file's checksum is intact.
    let bad_header = |message: String| {
        if crc_ok(bytes) { E::Header { path: p(), message } } else { E::ChecksumMismatch { path: p() } }
    };
    let header: HeaderIn =
        serde_json::from_slice(&bytes[PREAMBLE as usize..header_end]).map_err(|e| bad_header(e.to_string()))?;

    let mut entries = Vec::with_capacity(header.tensors.len());
    let mut total = header_end as u64;
    for e in header.tensors {
        let dtype = DType::parse(&e.dtype)
            .ok_or_else(|| bad_header(format!("tensor {:?} has unknown dtype {:?}", e.name, e.dtype)))?;
        total = total.saturating_add(e.len.saturating_mul(dtype.size()));
        entries.push((e.name, dtype, e.len));
    }
    let total = total.saturating_add(4);
    if total > found {
        return Err(truncated(total));
    }
    if total < found {
        return Err(if crc_ok(&bytes[..total as usize]) {
            E::TrailingBytes { path: p(), extra: found - total }
        } else {
            E::ChecksumMismatch { path: p() }
        });
    }
    if !crc_ok(bytes) {
        return Err(E::ChecksumMismatch { path: p() });
    }

    let tensors = read_tensors(&bytes[header_end..], entries);
    Ok(Checkpoint { kind: header.kind, step: header.step, meta: header.meta, tensors })
}

/// The tensors `entries` (name, type, length) laid one after the other in
/// `payload`, whose size [`parse`] has checked against them.
fn read_tensors(payload: &[u8], entries: Vec<(String, DType, u64)>) -> Vec<(String, Tensor)> {
    let mut at = 0;
    let mut tensors = Vec::with_capacity(entries.len());
    for (name, dtype, len) in entries {
        // Fits: the sizes were checked against the buffer.
        let n = (len * dtype.size()) as usize;
        let raw = &payload[at..at + n];
        at += n;
        let tensor = match dtype {
            DType::F32 => {
                Tensor::F32(raw.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
            }
            DType::U8 => Tensor::U8(raw.to_vec()),
            DType::U64 => Tensor::U64(
                raw.chunks_exact(8)
                    .map(|c| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
                    .collect(),
            ),
        };
        tensors.push((name, tensor));
    }
    tensors
}

#[cfg(test)]
#[path = "checkpoint_tests.rs"]
mod tests;
