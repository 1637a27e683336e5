//! Niantic's SPZ, version 3: the splats quantised to about 29 bytes a
//! Gaussian (at SH degree 1) and gzipped, a tenth or less of the `.ply`.
//!
//! Version 3 because it is what the readers in use take: Spark (the web
//! app's viewer), Babylon.js and PlayCanvas's `splat-transform` read 2
//! and 3; version 4 (zstd streams, a 32-byte header) is newer than most.
//! Version 3 differs from 2 in the rotation alone: "smallest three", 4
//! bytes, where version 2 had `x y z` in 3 bytes.
//!
//! The layout (all little-endian), gzipped as one stream:
//! - a 16-byte header: magic `NGSP` (`0x5053474e`), version, count,
//!   SH degree, fractional bits of the positions, flags (0), a zero byte;
//! - positions: 3 signed 24-bit fixed-point values a Gaussian;
//! - opacities: `sigmoid(logit) * 255`;
//! - colours: the SH DC terms as `(dc * 0.15 + 0.5) * 255`;
//! - scales: the log scales as `(ln s + 10) * 16`;
//! - rotations: the unit quaternion's index of its largest component
//!   (`x y z w` order) in the top 2 bits, then the other three, each a sign
//!   bit and 9 bits of magnitude over `sqrt(1/2)`, first component highest;
//! - the other SH coefficients, coefficient by coefficient with the three
//!   channels inner, as `x * 128 + 128` rounded to 5 bits (degree 1) or 4
//!   (higher).
//!
//! The axes are the `.ply`'s, unchanged. SPZ's documents name its axes
//! right, up, back, but Niantic's own `ply_to_spz` converts nothing by
//! default, and Spark, `splat-transform` and Babylon read the values raw:
//! an SPZ made from a `.ply` by any of them holds the `.ply`'s axes, and
//! every viewer turns the two alike.
//!
//! Gaussians are written in Morton order of their positions, so neighbours
//! share their leading bytes and gzip finds them.

use std::io::{self, Read, Write};

use super::{World, world_all};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::splats::gaussians::{Layout, sh_coeffs, sigmoid, unit_quat};
use crate::engine::models::splats::{SplatsConfig, SplatsModel};

pub const MAGIC: u32 = 0x5053_474e;
pub const VERSION: u32 = 3;
const HEADER: usize = 16;
/// The colours' scale: Niantic's, not the SH basis' constant.
pub const COLOR_SCALE: f32 = 0.15;
/// The most fractional bits a position gets (1/65536 of a unit).
const MAX_FRACTIONAL_BITS: u32 = 16;
/// The significant bits the farthest position keeps: a step of 1/131072
/// of the scene's reach, far below a pixel of any view of all of it, and
/// no finer, since the bits below that are noise gzip cannot shrink
/// (Niantic's fixed 12 fractional bits, for a scene of a few units).
const SIGNIFICANT_BITS: i32 = 17;
const FIXED_MAX: f64 = ((1 << 23) - 1) as f64;

/// Writes `model` as SPZ version 3.
pub fn write_spz(model: &SplatsModel, out: impl Write) -> io::Result<()> {
    let l = model.layout();
    let all = world_all(model);
    for w in &all {
        if w.mean.iter().chain(&w.log_scale).any(|v| !v.is_finite()) {
            return Err(io::Error::new(io::ErrorKind::InvalidData, "a Gaussian's position or scale is not finite"));
        }
    }
    let max_abs = all.iter().flat_map(|w| w.mean).fold(0.0f32, |m, v| m.max(v.abs())) as f64;
    let bits = fractional_bits(max_abs).ok_or_else(|| {
        io::Error::new(io::ErrorKind::InvalidData, format!("positions reach {max_abs}: beyond SPZ's 24-bit range"))
    })?;
    let order = morton_order(&all);
    let degree = (l.k as f64).sqrt() as u32 - 1;
    let rest = l.k - 1;
    let n = l.n;
    let mut raw = Vec::with_capacity(HEADER + n * (14 + 3 * rest));
    raw.extend_from_slice(&MAGIC.to_le_bytes());
    raw.extend_from_slice(&VERSION.to_le_bytes());
    raw.extend_from_slice(&(n as u32).to_le_bytes());
    raw.extend_from_slice(&[degree as u8, bits as u8, 0, 0]);
    let unit = (1u64 << bits) as f64;
    for &i in &order {
        let m = all[i].mean;
        for v in m {
            let q = (v as f64 * unit).round().clamp(-FIXED_MAX, FIXED_MAX) as i32;
            raw.extend_from_slice(&q.to_le_bytes()[..3]);
        }
    }
    raw.extend(order.iter().map(|&i| byte(sigmoid(all[i].opacity_logit) * 255.0)));
    for &i in &order {
        raw.extend(all[i].sh_dc.map(|c| byte((c * COLOR_SCALE + 0.5) * 255.0)));
    }
    for &i in &order {
        raw.extend(all[i].log_scale.map(|s| byte((s + 10.0) * 16.0)));
    }
    for &i in &order {
        raw.extend_from_slice(&smallest_three(all[i].rotation).to_le_bytes());
    }
    for &i in &order {
        for j in 1..l.k {
            let bucket = if j < 4 { 8 } else { 16 };
            for c in 0..3 {
                raw.push(quantise_sh(all[i].sh_rest[3 * (j - 1) + c], bucket));
            }
        }
    }
    let mut gz = flate2::write::GzEncoder::new(out, flate2::Compression::best());
    gz.write_all(&raw)?;
    gz.finish()?.flush()
}

/// The fractional bits for positions up to `max_abs`: `SIGNIFICANT_BITS`
/// over the range, at most 16, and so that `max_abs` fits in 24 bits.
fn fractional_bits(max_abs: f64) -> Option<u32> {
    let want = (SIGNIFICANT_BITS - max_abs.max(1e-9).log2().ceil() as i32).clamp(0, MAX_FRACTIONAL_BITS as i32) as u32;
    (0..=want).rev().find(|&b| max_abs * (1u64 << b) as f64 <= FIXED_MAX)
}

fn byte(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// `x * 128 + 128` to the nearest multiple of `bucket`, as a byte.
fn quantise_sh(x: f32, bucket: i32) -> u8 {
    let q = (x * 128.0).round() as i32 + 128;
    ((q + bucket / 2) / bucket * bucket).clamp(0, 255) as u8
}

/// The quaternion `w x y z`, normalised, as SPZ's smallest three.
fn smallest_three(q: [f32; 4]) -> u32 {
    // SPZ's component order: x y z w.
    let [w, x, y, z] = unit_quat(q);
    let q = [x, y, z, w];
    let largest = (0..4).fold(0, |b, i| if q[i].abs() > q[b].abs() { i } else { b });
    let sign = if q[largest] < 0.0 { -1.0 } else { 1.0 };
    let mask = (1u32 << 9) - 1;
    let mut packed = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i != largest {
            let v = v * sign;
            let mag = ((mask as f32) * v.abs() / std::f32::consts::FRAC_1_SQRT_2).round().min(mask as f32) as u32;
            packed = (packed << 10) | (u32::from(v < 0.0) << 9) | mag;
        }
    }
    packed
}

/// The indices of `all` in Morton (Z-curve) order of their positions.
fn morton_order(all: &[World]) -> Vec<usize> {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for w in all {
        for c in 0..3 {
            lo[c] = lo[c].min(w.mean[c]);
            hi[c] = hi[c].max(w.mean[c]);
        }
    }
    let cell = |w: &World, c: usize| {
        let span = (hi[c] - lo[c]).max(f32::MIN_POSITIVE);
        (((w.mean[c] - lo[c]) / span) * 1023.0).round() as u32
    };
    let key = |w: &World| -> u32 {
        let mut k = 0u32;
        for b in (0..10).rev() {
            for c in 0..3 {
                k = (k << 1) | ((cell(w, c) >> b) & 1);
            }
        }
        k
    };
    let keys: Vec<u32> = all.iter().map(key).collect();
    let mut order: Vec<usize> = (0..all.len()).collect();
    order.sort_by_key(|&i| (keys[i], i));
    order
}

/// Why an SPZ file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum SpzError {
    #[error("not a gzipped SPZ file: {0}")]
    Gzip(#[from] io::Error),
    #[error("not an SPZ file (magic {0:#x})")]
    Magic(u32),
    #[error("SPZ version {0}: only 2 and 3 are read")]
    Version(u32),
    #[error("SPZ SH degree {0}: at most 3")]
    Degree(u8),
    #[error("SPZ file of {got} bytes unpacked, where its header says {want}")]
    Length { got: usize, want: usize },
    #[error("SPZ file of {0} Gaussians, over the {1} read")]
    TooMany(usize, usize),
}

/// A decoded SPZ file, in world units.
#[derive(Clone, Debug, PartialEq)]
pub struct Decoded {
    pub degree: u32,
    pub means: Vec<[f32; 3]>,
    pub log_scales: Vec<[f32; 3]>,
    /// Unit quaternions `w x y z`.
    pub rotations: Vec<[f32; 4]>,
    pub opacities: Vec<f32>,
    pub sh_dc: Vec<[f32; 3]>,
    /// `[(k-1) x 3]` a Gaussian, as [`Layout`] has them.
    pub sh_rest: Vec<f32>,
}

/// Reads an SPZ file (version 2 or 3) of at most `max_gaussians`.
pub fn read_spz(bytes: &[u8], max_gaussians: usize) -> Result<Decoded, SpzError> {
    let mut gz = flate2::read::GzDecoder::new(bytes);
    let mut head = [0u8; HEADER];
    gz.read_exact(&mut head)?;
    let u32_at = |o: usize| u32::from_le_bytes(head[o..o + 4].try_into().unwrap());
    if u32_at(0) != MAGIC {
        return Err(SpzError::Magic(u32_at(0)));
    }
    let version = u32_at(4);
    if !(2..=3).contains(&version) {
        return Err(SpzError::Version(version));
    }
    let n = u32_at(8) as usize;
    if head[12] > 3 {
        return Err(SpzError::Degree(head[12]));
    }
    let degree = head[12] as u32;
    let bits = head[13] as i32;
    let rest = sh_coeffs(degree) - 1;
    let rot = if version == 2 { 3 } else { 4 };
    let per = 9 + 1 + 3 + 3 + rot + 3 * rest;
    if n > max_gaussians {
        return Err(SpzError::TooMany(n, max_gaussians));
    }
    let mut body = Vec::with_capacity(n * per);
    gz.take((n * per + 1) as u64).read_to_end(&mut body)?;
    if body.len() != n * per {
        return Err(SpzError::Length { got: body.len(), want: n * per });
    }
    let (pos, tail) = body.split_at(9 * n);
    let (alpha, tail) = tail.split_at(n);
    let (colour, tail) = tail.split_at(3 * n);
    let (scale, tail) = tail.split_at(3 * n);
    let (rots, sh) = tail.split_at(rot * n);
    let unit = 2f32.powi(-bits);
    let fixed = |b: &[u8]| ((i32::from_le_bytes([b[0], b[1], b[2], 0]) << 8) >> 8) as f32 * unit;
    let mut d = Decoded {
        degree,
        means: pos.chunks_exact(9).map(|p| [fixed(&p[0..3]), fixed(&p[3..6]), fixed(&p[6..9])]).collect(),
        log_scales: scale.chunks_exact(3).map(|s| [0, 1, 2].map(|c| s[c] as f32 / 16.0 - 10.0)).collect(),
        rotations: rots.chunks_exact(rot).map(unpack_rotation).collect(),
        opacities: alpha.iter().map(|&a| a as f32 / 255.0).collect(),
        sh_dc: colour.chunks_exact(3).map(|c| [0, 1, 2].map(|i| (c[i] as f32 / 255.0 - 0.5) / COLOR_SCALE)).collect(),
        sh_rest: Vec::with_capacity(3 * rest * n),
    };
    for &b in sh {
        d.sh_rest.push((b as f32 - 128.0) / 128.0);
    }
    Ok(d)
}

/// SPZ's rotation (version 2's 3 bytes or 3's 4) as `w x y z`.
fn unpack_rotation(r: &[u8]) -> [f32; 4] {
    let mut q = [0f32; 4]; // x y z w
    if r.len() == 3 {
        let v = [0, 1, 2].map(|i| r[i] as f32 / 127.5 - 1.0);
        q = [v[0], v[1], v[2], (1.0 - v.iter().map(|x| x * x).sum::<f32>()).max(0.0).sqrt()];
    } else {
        let mut packed = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
        let largest = (packed >> 30) as usize;
        let mask = (1u32 << 9) - 1;
        let mut sum = 0.0;
        for j in (0..4).rev().filter(|&j| j != largest) {
            let mag = std::f32::consts::FRAC_1_SQRT_2 * (packed & mask) as f32 / mask as f32;
            q[j] = if (packed >> 9) & 1 == 1 { -mag } else { mag };
            sum += q[j] * q[j];
            packed >>= 10;
        }
        q[largest] = (1.0 - sum).max(0.0).sqrt();
    }
    [q[3], q[0], q[1], q[2]]
}

impl Decoded {
    /// The decoded Gaussians as a splats model in `scene`'s model space.
    pub fn into_model(self, scene: Scene) -> Result<SplatsModel, crate::engine::models::ModelError> {
        let n = self.means.len();
        let l = Layout::new(n, self.degree);
        let mut p = vec![0.0f32; l.len()];
        let ln = scene.scale.ln();
        for i in 0..n {
            p[3 * i..3 * i + 3].copy_from_slice(&scene.point_to_model(self.means[i]));
            for c in 0..3 {
                p[3 * n + 3 * i + c] = self.log_scales[i][c] + ln;
                p[11 * n + 3 * i + c] = self.sh_dc[i][c];
            }
            p[6 * n + 4 * i..6 * n + 4 * i + 4].copy_from_slice(&self.rotations[i]);
            let a = self.opacities[i].clamp(1e-6, 1.0 - 1e-6);
            p[10 * n + i] = (a / (1.0 - a)).ln();
        }
        p[l.sh_rest()].copy_from_slice(&self.sh_rest);
        SplatsModel::from_parts(SplatsConfig { sh_degree: self.degree, ..Default::default() }, scene, p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::math::{Aabb, Vec3};
    use crate::engine::models::Model;

    /// 200 Gaussians of SH degree 2 with values spread over what a bake
    /// makes, in a scene whose model space is shifted and scaled.
    fn model(n: usize, degree: u32) -> SplatsModel {
        let scene =
            Scene::from_bounds(Aabb { min: Vec3::new(-2.0, 0.0, 1.0), max: Vec3::new(2.0, 4.0, 3.0) }, 0.0, 10.0);
        let l = Layout::new(n, degree);
        let mut p: Vec<f32> = (0..l.len()).map(|i| (i as f32 * 0.37).sin()).collect();
        for v in &mut p[l.log_scales()] {
            *v = *v * 3.0 - 4.0;
        }
        for v in &mut p[l.opacities()] {
            *v *= 5.0;
        }
        for v in &mut p[l.sh_rest()] {
            *v *= 0.5;
        }
        SplatsModel::from_parts(SplatsConfig { sh_degree: degree, ..Default::default() }, scene, p).unwrap()
    }

    fn encode(m: &SplatsModel) -> Vec<u8> {
        let mut bytes = Vec::new();
        write_spz(m, &mut bytes).unwrap();
        bytes
    }

    #[test]
    fn every_value_reads_back_within_its_quantisation() {
        let m = model(200, 2);
        let bytes = encode(&m);
        let d = read_spz(&bytes, 1000).unwrap();
        assert_eq!((d.degree, d.means.len()), (2, 200));
        let all = world_all(&m);
        let order = morton_order(&all);
        let max_abs = all.iter().flat_map(|w| w.mean).fold(0.0f32, |a, v| a.max(v.abs()));
        let bits = fractional_bits(max_abs as f64).unwrap();
        assert!(max_abs * 2f32.powi(bits as i32) <= FIXED_MAX as f32);
        assert_eq!(fractional_bits(19.4), Some(12), "Niantic's 12 bits for a scene of 20 units");
        assert_eq!(fractional_bits(0.01), Some(16));
        assert_eq!(fractional_bits(1e6), Some(0));
        assert_eq!(fractional_bits(1e8), None);
        for (j, &i) in order.iter().enumerate() {
            let w = &all[i];
            for c in 0..3 {
                assert!((d.means[j][c] - w.mean[c]).abs() <= 0.5 / 2f32.powi(bits as i32) + 1e-6, "position");
                let s = w.log_scale[c].clamp(-10.0, 255.0 / 16.0 - 10.0);
                assert!((d.log_scales[j][c] - s).abs() <= 1.0 / 32.0 + 1e-5, "{} {}", d.log_scales[j][c], s);
                let dc = w.sh_dc[c].clamp(-0.5 / COLOR_SCALE, 0.5 / COLOR_SCALE);
                assert!((d.sh_dc[j][c] - dc).abs() <= 0.5 / (255.0 * COLOR_SCALE) + 1e-5, "colour");
            }
            assert!((d.opacities[j] - sigmoid(w.opacity_logit)).abs() <= 0.5 / 255.0 + 1e-6, "opacity");
            // The same rotation up to sign: |<q, q'>| near 1.
            let q = unit_quat(w.rotation);
            let dot: f32 = (0..4).map(|c| q[c] * d.rotations[j][c]).sum();
            assert!(dot.abs() > 0.9995, "rotation {q:?} {:?}", d.rotations[j]);
            for t in 0..3 * 8 {
                let bucket = if t < 9 { 8.0 } else { 16.0 };
                let v = w.sh_rest[t].clamp(-1.0, 127.0 / 128.0);
                let got = d.sh_rest[24 * j + t];
                assert!((got - v).abs() <= bucket / 2.0 / 128.0 + 1.0 / 256.0, "sh {t}: {got} for {v}");
            }
        }
    }

    #[test]
    fn the_header_and_layout_are_version_3() {
        let m = model(5, 1);
        let bytes = encode(&m);
        assert_eq!(&bytes[..2], &[0x1f, 0x8b], "gzipped");
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(&bytes[..]).read_to_end(&mut raw).unwrap();
        assert_eq!(&raw[0..4], b"NGSP");
        assert_eq!(u32::from_le_bytes(raw[4..8].try_into().unwrap()), 3);
        assert_eq!(u32::from_le_bytes(raw[8..12].try_into().unwrap()), 5);
        assert_eq!((raw[12], raw[14], raw[15]), (1, 0, 0));
        assert_eq!(raw.len(), 16 + 5 * (9 + 1 + 3 + 3 + 4 + 9));
    }

    #[test]
    fn smallest_three_packs_as_niantic_describes() {
        // The identity: w largest (index 3), the rest zero.
        assert_eq!(smallest_three([1.0, 0.0, 0.0, 0.0]), 3 << 30);
        // x largest and negative: the whole quaternion is negated, so w's
        // positive 0.6 is stored negative: x's index 0, then y, z (0), w.
        let p = smallest_three([0.6, -0.8, 0.0, 0.0]);
        assert_eq!(p >> 30, 0);
        assert_eq!(p & 0x3ff, (1 << 9) | (511.0f32 * 0.6 / std::f32::consts::FRAC_1_SQRT_2).round() as u32);
        assert_eq!((p >> 10) & 0xfffff, 0);
        let q = unpack_rotation(&p.to_le_bytes());
        for (a, b) in q.iter().zip([-0.6, 0.8, 0.0, 0.0]) {
            assert!((a - b).abs() < 2e-3, "{q:?}");
        }
    }

    #[test]
    fn bad_files_are_errors_not_allocations() {
        assert!(matches!(read_spz(b"not gzip at all", 10), Err(SpzError::Gzip(_))));
        let m = model(5, 1);
        let bytes = encode(&m);
        assert!(matches!(read_spz(&bytes, 4), Err(SpzError::TooMany(5, 4))), "over the limit");
        let mut raw = Vec::new();
        flate2::read::GzDecoder::new(&bytes[..]).read_to_end(&mut raw).unwrap();
        let gz = |raw: &[u8]| {
            let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
            e.write_all(raw).unwrap();
            e.finish().unwrap()
        };
        assert!(matches!(read_spz(&gz(&raw[..raw.len() - 1]), 10), Err(SpzError::Length { .. })), "truncated");
        let mut v4 = raw.clone();
        v4[4] = 4;
        assert!(matches!(read_spz(&gz(&v4), 10), Err(SpzError::Version(4))));
        let mut huge = raw.clone();
        huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(
            matches!(read_spz(&gz(&huge), 1_000_000), Err(SpzError::TooMany(n, 1_000_000)) if n == u32::MAX as usize)
        );
        // A position beyond 24 bits at any precision is refused.
        let mut far = model(2, 0);
        let scale = far.scene().scale;
        far.params_mut()[0] = 1e8 * scale;
        assert!(write_spz(&far, Vec::new()).is_err());
    }

    #[test]
    fn decoded_into_a_model_it_holds_the_decoded_values() {
        let m = model(50, 1);
        let d = read_spz(&encode(&m), 100).unwrap();
        let back = d.clone().into_model(m.scene().clone()).unwrap();
        assert_eq!(back.layout(), m.layout());
        // Written again, the model decodes to the same values: each is a
        // fixed point of the quantisation (to rounding of the space's shift).
        let again = read_spz(&encode(&back), 100).unwrap();
        for i in 0..50 {
            for c in 0..3 {
                assert!((again.means[i][c] - d.means[i][c]).abs() < 1e-3);
                assert!((again.log_scales[i][c] - d.log_scales[i][c]).abs() < 1e-4);
            }
            assert_eq!(again.opacities[i], d.opacities[i]);
            assert_eq!(again.sh_dc[i], d.sh_dc[i]);
        }
        assert_eq!(again.sh_rest, d.sh_rest);
    }
}
