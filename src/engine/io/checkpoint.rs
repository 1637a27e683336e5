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

    let mut at = header_end;
    let mut tensors = Vec::with_capacity(entries.len());
    for (name, dtype, len) in entries {
        // Fits: the sizes were checked against the buffer above.
        let n = (len * dtype.size()) as usize;
        let raw = &bytes[at..at + n];
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
    Ok(Checkpoint { kind: header.kind, step: header.step, meta: header.meta, tensors })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use serde_json::json;

    fn sample() -> Checkpoint {
        let mut c = Checkpoint::new("instant", 12345);
        c.meta = json!({"config": {"levels": 16, "lr": 0.01}, "scene": {"scale": 0.33, "offset": [0.5, 0.5, 0.5]}, "note": "ünïcode"});
        c.insert(
            "params",
            vec![1.0f32, -2.5, 0.0, -0.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MIN_POSITIVE / 2.0],
        );
        c.insert("adam.m", vec![0.125f32; 5]);
        c.insert("grid", vec![0u8, 1, 255, 7]);
        c.insert("rng", vec![0u64, 1, u64::MAX, 0x0123_4567_89ab_cdef]);
        c.insert("empty", Vec::<f32>::new());
        c
    }

    /// Bitwise comparison (NaN payloads and signed zeros included).
    fn assert_same(a: &Checkpoint, b: &Checkpoint) {
        assert_eq!(a.kind, b.kind);
        assert_eq!(a.step, b.step);
        assert_eq!(a.meta, b.meta);
        assert_eq!(a.tensors.len(), b.tensors.len());
        for ((na, ta), (nb, tb)) in a.tensors.iter().zip(&b.tensors) {
            assert_eq!(na, nb);
            match (ta, tb) {
                (Tensor::F32(x), Tensor::F32(y)) => {
                    let xb: Vec<u32> = x.iter().map(|v| v.to_bits()).collect();
                    let yb: Vec<u32> = y.iter().map(|v| v.to_bits()).collect();
                    assert_eq!(xb, yb, "{na}");
                }
                _ => assert_eq!(ta, tb, "{na}"),
            }
        }
    }

    /// Builds a file with a hand-written header and a valid checksum.
    fn craft(version: u32, header: &[u8], payload: &[u8]) -> Vec<u8> {
        let mut v = MAGIC.to_vec();
        v.extend_from_slice(&version.to_le_bytes());
        v.extend_from_slice(&(header.len() as u32).to_le_bytes());
        v.extend_from_slice(header);
        v.extend_from_slice(payload);
        let crc = crc32fast::hash(&v);
        v.extend_from_slice(&crc.to_le_bytes());
        v
    }

    #[test]
    fn round_trip_all_tensor_types() {
        let c = sample();
        let bytes = c.to_bytes();
        let d = Checkpoint::from_bytes(&bytes).unwrap();
        assert_same(&c, &d);
        assert_eq!(d.to_bytes(), bytes, "re-encoding is byte-identical");
        assert!(d.f32("params").unwrap()[4].is_nan());
        assert_eq!(d.u8("grid").unwrap(), &[0, 1, 255, 7]);
        assert_eq!(d.u64("rng").unwrap()[2], u64::MAX);
        assert!(d.f32("empty").unwrap().is_empty());
    }

    #[test]
    fn round_trip_minimal_and_large() {
        let c = Checkpoint::new("", 0);
        assert_same(&c, &Checkpoint::from_bytes(&c.to_bytes()).unwrap());

        // Larger than one write chunk, so the chunked writer is exercised.
        let mut c = Checkpoint::new("nerf", u64::MAX);
        c.insert("params", (0..100_003).map(|i| i as f32 * 0.5 - 7.0).collect::<Vec<f32>>());
        c.insert("ids", (0..40_001u64).map(|i| i.wrapping_mul(0x9E37_79B9_7F4A_7C15)).collect::<Vec<u64>>());
        let bytes = c.to_bytes();
        let expected_len = 16 + c.header_json().len() + 100_003 * 4 + 40_001 * 8 + 4;
        assert_eq!(bytes.len(), expected_len);
        assert_same(&c, &Checkpoint::from_bytes(&bytes).unwrap());
    }

    #[test]
    fn layout_is_as_documented() {
        let mut c = Checkpoint::new("nerf", 7);
        c.meta = json!({"a": 1});
        c.insert("w", vec![1.0f32, 2.0]);
        c.insert("g", vec![9u8]);
        c.insert("s", vec![3u64]);
        let b = c.to_bytes();
        assert_eq!(&b[..8], b"RADIANCE");
        assert_eq!(read_u32(&b, 8), 1);
        let hl = read_u32(&b, 12) as usize;
        let header: serde_json::Value = serde_json::from_slice(&b[16..16 + hl]).unwrap();
        assert_eq!(
            header,
            json!({"kind": "nerf", "step": 7, "meta": {"a": 1}, "tensors": [
                {"name": "w", "dtype": "f32", "len": 2},
                {"name": "g", "dtype": "u8", "len": 1},
                {"name": "s", "dtype": "u64", "len": 1}]})
        );
        let mut payload = Vec::new();
        payload.extend_from_slice(&1.0f32.to_le_bytes());
        payload.extend_from_slice(&2.0f32.to_le_bytes());
        payload.push(9);
        payload.extend_from_slice(&3u64.to_le_bytes());
        assert_eq!(&b[16 + hl..b.len() - 4], &payload[..]);
        let crc = crc32fast::hash(&b[..b.len() - 4]);
        assert_eq!(&b[b.len() - 4..], &crc.to_le_bytes());
    }

    #[test]
    fn every_truncation_is_a_truncated_error() {
        let bytes = sample().to_bytes();
        let hl = read_u32(&bytes, 12) as u64;
        for cut in 0..bytes.len() {
            match Checkpoint::from_bytes(&bytes[..cut]) {
                Err(CheckpointError::Truncated { expected, found, path: None }) => {
                    assert_eq!(found, cut as u64);
                    assert!(expected > found, "cut {cut}: expected {expected}");
                    if cut as u64 >= 16 + hl + 4 {
                        assert_eq!(expected, bytes.len() as u64, "cut {cut}");
                    }
                }
                other => panic!("cut at {cut}: {other:?}"),
            }
        }
        let msg = Checkpoint::from_bytes(&bytes[..bytes.len() - 1]).unwrap_err().to_string();
        assert_eq!(msg, format!("truncated: expected {} bytes, found {}", bytes.len(), bytes.len() - 1));
    }

    #[test]
    fn every_single_bit_flip_is_an_error() {
        let bytes = sample().to_bytes();
        let mut corrupt = bytes.clone();
        for i in 0..bytes.len() {
            for bit in 0..8 {
                corrupt[i] ^= 1 << bit;
                let r = Checkpoint::from_bytes(&corrupt);
                assert!(r.is_err(), "flip of byte {i} bit {bit} went undetected");
                // Past the preamble every flip is caught by the checksum or
                // a size check.
                if i >= 16 {
                    assert!(
                        matches!(r, Err(CheckpointError::ChecksumMismatch { .. } | CheckpointError::Truncated { .. })),
                        "byte {i} bit {bit}: {r:?}"
                    );
                }
                corrupt[i] ^= 1 << bit;
            }
        }
        assert_eq!(corrupt, bytes);
        // A payload flip is a checksum error.
        let last_payload = bytes.len() - 5;
        corrupt[last_payload] ^= 0x10;
        assert_eq!(Checkpoint::from_bytes(&corrupt).unwrap_err().to_string(), "checksum mismatch: file is corrupted");
    }

    #[test]
    fn wrong_magic() {
        let mut bytes = sample().to_bytes();
        bytes[0] = b'X';
        let err = Checkpoint::from_bytes(&bytes).unwrap_err();
        assert!(matches!(err, CheckpointError::NotACheckpoint { .. }));
        assert_eq!(err.to_string(), "not a radiance checkpoint");
        assert!(matches!(Checkpoint::from_bytes(b"PK\x03\x04"), Err(CheckpointError::NotACheckpoint { .. })));
        assert!(matches!(
            Checkpoint::from_bytes(b"{\"kind\": \"nerf\", \"step\": 1}"),
            Err(CheckpointError::NotACheckpoint { .. })
        ));
    }

    #[test]
    fn future_and_past_versions() {
        let mut bytes = sample().to_bytes();
        bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
        let err = Checkpoint::from_bytes(&bytes).unwrap_err();
        assert!(matches!(err, CheckpointError::UnsupportedVersion { found: 7, .. }));
        assert_eq!(err.to_string(), "checkpoint format version 7 is newer than this build supports (1)");
        // Only the preamble is needed to tell.
        assert!(matches!(
            Checkpoint::from_bytes(&bytes[..12]),
            Err(CheckpointError::UnsupportedVersion { found: 7, .. })
        ));
        bytes[8..12].copy_from_slice(&0u32.to_le_bytes());
        let err = Checkpoint::from_bytes(&bytes).unwrap_err();
        assert_eq!(err.to_string(), "checkpoint format version 0 is not supported (this build reads version 1)");
    }

    #[test]
    fn absurd_header_length_is_truncated_not_allocated() {
        let mut bytes = sample().to_bytes();
        bytes[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        match Checkpoint::from_bytes(&bytes) {
            Err(CheckpointError::Truncated { expected, found, .. }) => {
                assert_eq!(expected, 16 + u32::MAX as u64 + 4);
                assert_eq!(found, bytes.len() as u64);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn absurd_tensor_lengths_are_truncated_not_allocated() {
        for (dtype, len) in [
            ("f32", 1u64 << 40),
            ("u64", 1u64 << 61),
            ("u64", u64::MAX),
            ("f32", u64::MAX / 4 + 1),
            ("u8", u64::MAX - 10),
        ] {
            let header = format!(
                r#"{{"kind":"x","step":0,"meta":null,"tensors":[{{"name":"a","dtype":"{dtype}","len":{len}}}]}}"#
            );
            let bytes = craft(1, header.as_bytes(), &[0u8; 64]);
            match Checkpoint::from_bytes(&bytes) {
                Err(CheckpointError::Truncated { expected, found, .. }) => {
                    assert!(expected > found, "{dtype} {len}");
                }
                other => panic!("{dtype} {len}: {other:?}"),
            }
        }
    }

    #[test]
    fn header_errors() {
        let cases: [(&[u8], &str); 6] = [
            (b"not json", "expected"),
            (b"{\"kind\":\"x\",\"step\":0,\"meta\":null}", "missing field `tensors`"),
            (b"{\"kind\":\"x\",\"step\":-1,\"meta\":null,\"tensors\":[]}", "invalid value"),
            (
                b"{\"kind\":\"x\",\"step\":0,\"meta\":null,\"tensors\":[{\"name\":\"a\",\"dtype\":\"f16\",\"len\":0}]}",
                "tensor \"a\" has unknown dtype \"f16\"",
            ),
            (b"{\"kind\":\"x\",\"step\":0,\"meta\":null,\"tensors\":[]} trailing", "trailing characters"),
            (b"\xff\xfe", "expected"),
        ];
        for (header, needle) in cases {
            let err = Checkpoint::from_bytes(&craft(1, header, &[])).unwrap_err();
            assert!(matches!(err, CheckpointError::Header { .. }), "{err:?}");
            let msg = err.to_string();
            assert!(msg.starts_with("invalid checkpoint header: "), "{msg}");
            assert!(msg.contains(needle), "{msg} lacks {needle}");
        }
        // Unknown extra header fields are tolerated (forward-compatible additions).
        let ok = craft(1, br#"{"kind":"x","step":3,"meta":{},"tensors":[],"extra":1}"#, &[]);
        assert_eq!(Checkpoint::from_bytes(&ok).unwrap().step, 3);
    }

    #[test]
    fn trailing_bytes() {
        let mut bytes = sample().to_bytes();
        bytes.extend_from_slice(b"junk");
        let err = Checkpoint::from_bytes(&bytes).unwrap_err();
        assert!(matches!(err, CheckpointError::TrailingBytes { extra: 4, .. }), "{err:?}");
        assert_eq!(err.to_string(), "4 unexpected bytes after the end of the checkpoint");
        // Two checkpoints back to back.
        let one = sample().to_bytes();
        let two = [one.clone(), one.clone()].concat();
        assert!(matches!(
            Checkpoint::from_bytes(&two),
            Err(CheckpointError::TrailingBytes { extra, .. }) if extra == one.len() as u64
        ));
    }

    #[test]
    fn accessors_and_errors() {
        let mut c = sample();
        assert_eq!(c.tensor("grid").map(Tensor::dtype), Some("u8"));
        assert!(c.tensor("nope").is_none());
        assert_eq!(c.f32("adam.m").unwrap(), &[0.125; 5]);
        let err = c.f32("nope").unwrap_err();
        assert!(matches!(&err, CheckpointError::MissingTensor { name, .. } if name == "nope"));
        assert_eq!(err.to_string(), "checkpoint has no tensor named \"nope\"");
        let err = c.u64("grid").unwrap_err();
        assert!(matches!(err, CheckpointError::WrongType { expected: "u64", found: "u8", .. }));
        assert_eq!(err.to_string(), "tensor \"grid\" has dtype u8, expected u64");
        assert!(matches!(c.u8("params"), Err(CheckpointError::WrongType { .. })));
        let err = c.u8("params").unwrap_err().with_path(Path::new("m.ckpt"));
        assert_eq!(err.to_string(), "m.ckpt: tensor \"params\" has dtype f32, expected u8");
        assert_eq!(err.path(), Some(Path::new("m.ckpt")));

        // take_f32 moves the buffer out without copying and removes the entry.
        let ptr = c.f32("adam.m").unwrap().as_ptr();
        let names_before: Vec<String> = c.tensors.iter().map(|(n, _)| n.clone()).collect();
        let m = c.take_f32("adam.m").unwrap();
        assert_eq!(m.as_ptr(), ptr);
        assert!(matches!(c.f32("adam.m"), Err(CheckpointError::MissingTensor { .. })));
        assert!(matches!(c.take_f32("adam.m"), Err(CheckpointError::MissingTensor { .. })));
        // A wrong-type take leaves the tensor where it was.
        assert!(matches!(c.take_f32("grid"), Err(CheckpointError::WrongType { .. })));
        let names_after: Vec<&str> = c.tensors.iter().map(|(n, _)| n.as_str()).collect();
        let expected: Vec<&str> = names_before.iter().map(String::as_str).filter(|n| *n != "adam.m").collect();
        assert_eq!(names_after, expected);
        assert_eq!(c.take_u8("grid").unwrap(), vec![0, 1, 255, 7]);
        assert_eq!(c.take_u64("rng").unwrap()[3], 0x0123_4567_89ab_cdef);

        // insert replaces in place.
        c.insert("params", vec![1u8]);
        assert_eq!(c.tensors[0].0, "params");
        assert_eq!(c.u8("params").unwrap(), &[1]);
        if let Some(Tensor::U8(v)) = c.tensor_mut("params") {
            v.push(2);
        }
        assert_eq!(c.tensor("params").unwrap().len(), 2);
        assert_eq!(Tensor::U64(vec![1, 2]).byte_len(), 16);
        assert!(Tensor::F32(vec![]).is_empty());
    }

    #[test]
    fn save_and_load_through_temp_dir() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.ckpt");
        let c = sample();
        c.save(&path).unwrap();
        assert_same(&c, &Checkpoint::load(&path).unwrap());
        assert_eq!(std::fs::read(&path).unwrap(), c.to_bytes());

        // Overwrite with a later step.
        let mut c2 = c.clone();
        c2.step += 1;
        c2.save(&path).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap().step, c.step + 1);

        let entries: Vec<_> =
            std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        assert_eq!(entries, vec!["model.ckpt"]);
    }

    #[test]
    fn load_errors_name_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model.ckpt");
        let mut bytes = sample().to_bytes();
        let n = bytes.len();
        bytes[n - 10] ^= 1;
        std::fs::write(&path, &bytes).unwrap();
        let err = Checkpoint::load(&path).unwrap_err();
        assert_eq!(err.path(), Some(path.as_path()));
        assert_eq!(err.to_string(), format!("{}: checksum mismatch: file is corrupted", path.display()));

        std::fs::write(&path, &bytes[..n - 3]).unwrap();
        let msg = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(msg.starts_with(&format!("{}: truncated: expected {n} bytes", path.display())), "{msg}");

        std::fs::write(&path, b"").unwrap();
        let msg = Checkpoint::load(&path).unwrap_err().to_string();
        assert_eq!(msg, format!("{}: truncated: expected 20 bytes, found 0", path.display()));

        let missing = dir.path().join("missing.ckpt");
        let err = Checkpoint::load(&missing).unwrap_err();
        assert!(matches!(&err, CheckpointError::Io { source, .. } if source.kind() == io::ErrorKind::NotFound));
        assert!(err.to_string().starts_with(&format!("{}: ", missing.display())));
    }

    #[test]
    fn save_into_missing_directory_fails_cleanly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no").join("model.ckpt");
        let err = sample().save(&path).unwrap_err();
        assert!(matches!(err, CheckpointError::Io { .. }));
        assert!(err.to_string().contains("model.ckpt"));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn loading_a_large_checkpoint_is_fast() {
        // 64 MB of f32 payload; decoding should be bulk conversion, far from
        // the time limit even on a loaded machine.
        let mut c = Checkpoint::new("instant", 1);
        c.insert("params", vec![0.5f32; 16 << 20]);
        let bytes = c.to_bytes();
        let t = std::time::Instant::now();
        let d = Checkpoint::from_bytes(&bytes).unwrap();
        let elapsed = t.elapsed();
        assert_eq!(d.f32("params").unwrap().len(), 16 << 20);
        eprintln!("decoded a 64 MiB checkpoint in {elapsed:?}");
        assert!(elapsed.as_secs_f64() < 5.0, "{elapsed:?}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = Checkpoint::from_bytes(&bytes);
        }

        #[test]
        fn random_bytes_after_valid_preamble_never_panic(
            header_len in any::<u32>(),
            rest in proptest::collection::vec(any::<u8>(), 0..512),
        ) {
            let mut bytes = MAGIC.to_vec();
            bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
            bytes.extend_from_slice(&(header_len % 600).to_le_bytes());
            bytes.extend_from_slice(&rest);
            let _ = Checkpoint::from_bytes(&bytes);
        }

        #[test]
        fn round_trip_random(
            kind in ".{0,12}",
            step in any::<u64>(),
            f in proptest::collection::vec(any::<u32>(), 0..64),
            b in proptest::collection::vec(any::<u8>(), 0..64),
            u in proptest::collection::vec(any::<u64>(), 0..64),
        ) {
            let mut c = Checkpoint::new(kind, step);
            c.meta = json!({"n": f.len()});
            c.insert("f", f.iter().map(|&x| f32::from_bits(x)).collect::<Vec<f32>>());
            c.insert("b", b);
            c.insert("u", u);
            let bytes = c.to_bytes();
            let d = Checkpoint::from_bytes(&bytes).unwrap();
            assert_same(&c, &d);
        }
    }
}
