//! The AVX2/FMA paths of the hash grid: eight points at a time, their
//! corner indices and weights computed in vector registers, the table read
//! with gathers.

use std::arch::x86_64::*;

use super::{FEATURES, Level, prefetch};

/// Points as three coordinate arrays (a multiple of 8 long).
pub struct Soa {
    x: Vec<f32>,
    y: Vec<f32>,
    z: Vec<f32>,
}

impl Soa {
    pub fn new(pts: &[f32]) -> Self {
        let n = pts.len() / 3;
        let mut s = Soa { x: Vec::with_capacity(n), y: Vec::with_capacity(n), z: Vec::with_capacity(n) };
        for p in pts.chunks_exact(3) {
            s.x.push(p[0]);
            s.y.push(p[1]);
            s.z.push(p[2]);
        }
        s
    }
}

/// Table entry indices (relative to the level) and weights of the 8
/// corners of points `g..g + 8`, corner-major; the same formulas as
/// `HashGrid::corners_of`.
#[inline(always)]
unsafe fn corners8<const DENSE: bool>(level: &Level, soa: &Soa, g: usize) -> ([__m256i; 8], [__m256; 8]) {
    // SAFETY: the caller guarantees AVX2 and `g + 8 <= n`.
    unsafe {
        let (x, y, z) = (
            _mm256_loadu_ps(soa.x.as_ptr().add(g)),
            _mm256_loadu_ps(soa.y.as_ptr().add(g)),
            _mm256_loadu_ps(soa.z.as_ptr().add(g)),
        );
        corners8_of::<DENSE>(level, x, y, z)
    }
}

/// [`corners8`] of the points with coordinates `x`, `y`, `z` (each in
/// `[0, 1]`: sanitised).
#[inline(always)]
unsafe fn corners8_of<const DENSE: bool>(
    level: &Level,
    x: __m256,
    y: __m256,
    z: __m256,
) -> ([__m256i; 8], [__m256; 8]) {
    // SAFETY: the caller guarantees AVX2.
    unsafe {
        let resf = _mm256_set1_ps(level.res as f32);
        let resm1 = _mm256_set1_epi32(level.res as i32 - 1);
        let one = _mm256_set1_epi32(1);
        let axis = |p: __m256| {
            let v = _mm256_mul_ps(p, resf);
            let f = _mm256_min_epi32(_mm256_cvttps_epi32(v), resm1);
            (f, _mm256_sub_ps(v, _mm256_cvtepi32_ps(f)))
        };
        let (fx, rx) = axis(x);
        let (fy, ry) = axis(y);
        let (fz, rz) = axis(z);
        let t: [[__m256i; 2]; 3] = if DENSE {
            let n = level.res as i32 + 1;
            let (nn, n1) = (_mm256_set1_epi32(n * n), _mm256_set1_epi32(n));
            let (x0, y0) = (_mm256_mullo_epi32(fx, nn), _mm256_mullo_epi32(fy, n1));
            [[x0, _mm256_add_epi32(x0, nn)], [y0, _mm256_add_epi32(y0, n1)], [fz, _mm256_add_epi32(fz, one)]]
        } else {
            let h = |v: __m256i, prime: u32| {
                let p = _mm256_set1_epi32(prime as i32);
                [_mm256_mullo_epi32(v, p), _mm256_mullo_epi32(_mm256_add_epi32(v, one), p)]
            };
            [h(fx, 1), h(fy, 2_654_435_761), h(fz, 805_459_861)]
        };
        let onef = _mm256_set1_ps(1.0);
        let w = [[_mm256_sub_ps(onef, rx), rx], [_mm256_sub_ps(onef, ry), ry], [_mm256_sub_ps(onef, rz), rz]];
        let mask = _mm256_set1_epi32((level.size - 1) as i32);
        let mut idx = [_mm256_setzero_si256(); 8];
        let mut wt = [_mm256_setzero_ps(); 8];
        for c in 0..8 {
            let (dx, dy, dz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
            idx[c] = if DENSE {
                _mm256_add_epi32(_mm256_add_epi32(t[0][dx], t[1][dy]), t[2][dz])
            } else {
                _mm256_and_si256(_mm256_xor_si256(_mm256_xor_si256(t[0][dx], t[1][dy]), t[2][dz]), mask)
            };
            wt[c] = _mm256_mul_ps(_mm256_mul_ps(w[0][dx], w[1][dy]), w[2][dz]);
        }
        (idx, wt)
    }
}

/// Level `l` of every point of `soa` into `out` (`[n x width]`).
///
/// # Safety
/// AVX2 and FMA must be available, `params` must hold the level's table
/// at `start`, and `out` must have `soa`'s number of rows.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn forward_level<const DENSE: bool>(
    level: &Level,
    start: usize,
    l: usize,
    params: &[f32],
    soa: &Soa,
    out: &mut [f32],
    width: usize,
) {
    let n = soa.x.len();
    assert!(out.len() >= n * width && params.len() >= start + FEATURES * level.size);
    // SAFETY (whole body): indices are below `level.size` (dense ones by
    // construction, hashed ones masked), so every gathered pair lies in
    // the level's table; rows `g..g + 8` are below `n`.
    unsafe {
        // A table entry (2 features) is one 8-byte element.
        let base = params.as_ptr().add(start) as *const i64;
        let lo_pairs = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
        let hi_pairs = _mm256_setr_epi32(4, 4, 5, 5, 6, 6, 7, 7);
        let mut tmp = [0f32; 16];
        for g in (0..n).step_by(8) {
            let (idx, wt) = corners8::<DENSE>(level, soa, g);
            let (mut lo, mut hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
            for c in 0..8 {
                let glo = _mm256_i32gather_epi64::<8>(base, _mm256_castsi256_si128(idx[c]));
                let ghi = _mm256_i32gather_epi64::<8>(base, _mm256_extracti128_si256::<1>(idx[c]));
                lo = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(wt[c], lo_pairs), _mm256_castsi256_ps(glo), lo);
                hi = _mm256_fmadd_ps(_mm256_permutevar8x32_ps(wt[c], hi_pairs), _mm256_castsi256_ps(ghi), hi);
            }
            _mm256_storeu_ps(tmp.as_mut_ptr(), lo);
            _mm256_storeu_ps(tmp.as_mut_ptr().add(8), hi);
            for j in 0..8 {
                let o = (g + j) * width + FEATURES * l;
                *out.get_unchecked_mut(o) = tmp[2 * j];
                *out.get_unchecked_mut(o + 1) = tmp[2 * j + 1];
            }
        }
    }
}

/// [`forward_level`] from a half table (`words`, the level's entries
/// from `start`), for the first `n` points of `soa` (whose length is a
/// multiple of 8 at least `n`).
///
/// # Safety
/// AVX2, FMA and F16C must be available, `words` must hold the level's
/// table at `start`, and `out` must have `n` rows.
#[target_feature(enable = "avx2,fma,f16c")]
#[allow(clippy::too_many_arguments)]
pub unsafe fn forward_level_half<const DENSE: bool>(
    level: &Level,
    start: usize,
    l: usize,
    words: &[u32],
    soa: &Soa,
    n: usize,
    out: &mut [f32],
    width: usize,
) {
    assert!(soa.x.len() >= n && soa.x.len().is_multiple_of(8));
    assert!(out.len() >= n * width && words.len() >= start + level.size);
    // SAFETY (whole body): indices are below `level.size` (as in
    // `forward_level`), so every gathered word lies in the level's
    // table; only rows below `n` are written.
    unsafe {
        let base = words.as_ptr().add(start) as *const i32;
        let mut tmp = [0f32; 16];
        for g in (0..soa.x.len()).step_by(8) {
            let (idx, wt) = corners8::<DENSE>(level, soa, g);
            let (f0, f1) = interpolate8_half(base, &idx, &wt);
            _mm256_storeu_ps(tmp.as_mut_ptr(), f0);
            _mm256_storeu_ps(tmp.as_mut_ptr().add(8), f1);
            for j in 0..8.min(n.saturating_sub(g)) {
                let o = (g + j) * width + FEATURES * l;
                *out.get_unchecked_mut(o) = tmp[j];
                *out.get_unchecked_mut(o + 1) = tmp[8 + j];
            }
        }
    }
}

/// The two features of 8 points at their corners `idx` (weights `wt`)
/// from a half table at `base`.
#[inline(always)]
unsafe fn interpolate8_half(base: *const i32, idx: &[__m256i; 8], wt: &[__m256; 8]) -> (__m256, __m256) {
    // SAFETY: the caller guarantees AVX2, FMA and F16C and that every
    // index lies in the table at `base`.
    unsafe {
        let low = _mm256_set1_epi32(0xffff);
        let (mut f0, mut f1) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        for c in 0..8 {
            let v = _mm256_i32gather_epi32::<4>(base, idx[c]);
            // Per 128-bit lane: four feature-0 halves, then four
            // feature-1 halves; the permute puts the 8 of each together.
            let halves = _mm256_packus_epi32(_mm256_and_si256(v, low), _mm256_srli_epi32::<16>(v));
            let halves = _mm256_permute4x64_epi64::<0b11_01_10_00>(halves);
            f0 = _mm256_fmadd_ps(wt[c], _mm256_cvtph_ps(_mm256_castsi256_si128(halves)), f0);
            f1 = _mm256_fmadd_ps(wt[c], _mm256_cvtph_ps(_mm256_extracti128_si256::<1>(halves)), f1);
        }
        (f0, f1)
    }
}

/// Every level's two features of the 8 points `x`, `y`, `z` (each in
/// `[0, 1]`) from the half table `words`, into `out[2 l]` and
/// `out[2 l + 1]`: [`forward_level_half`] for 8 points, for kernels that
/// go on with the features in registers.
///
/// # Safety
/// AVX2, FMA and F16C must be available (the caller's target features:
/// this is inlined into it), and `words` must be `levels`' half table.
#[inline(always)]
pub unsafe fn encode8_half(levels: &[Level], words: &[u32], x: __m256, y: __m256, z: __m256, out: &mut [__m256]) {
    assert!(out.len() >= FEATURES * levels.len());
    for (l, level) in levels.iter().enumerate() {
        let start = level.offset / FEATURES;
        assert!(words.len() >= start + level.size);
        // SAFETY: as in `forward_level_half`: indices lie in the level's
        // table, which lies in `words` (asserted).
        unsafe {
            let base = words.as_ptr().add(start) as *const i32;
            let (idx, wt) =
                if level.dense { corners8_of::<true>(level, x, y, z) } else { corners8_of::<false>(level, x, y, z) };
            let (f0, f1) = interpolate8_half(base, &idx, &wt);
            out[FEATURES * l] = f0;
            out[FEATURES * l + 1] = f1;
        }
    }
}

/// Packs `table` (`[2 x words.len()]` f32) into binary16 pairs, rounded
/// to nearest even, clamped to +-65504 (NaN stays NaN).
///
/// # Safety
/// AVX and F16C must be available.
#[target_feature(enable = "avx2,f16c")]
pub unsafe fn pack_half(table: &[f32], words: &mut [u32]) {
    assert_eq!(table.len(), 2 * words.len());
    let (lo, hi) = (_mm256_set1_ps(-65504.0), _mm256_set1_ps(65504.0));
    let mut chunk = [0f32; 8];
    for (t, w) in table.chunks(8).zip(words.chunks_mut(4)) {
        chunk[..t.len()].copy_from_slice(t);
        chunk[t.len()..].fill(0.0);
        // SAFETY: `chunk` holds 8 floats; `packed` 4 words.
        unsafe {
            // min/max return their second operand for NaN: the clamp
            // keeps NaN as it is.
            let v = _mm256_max_ps(lo, _mm256_min_ps(hi, _mm256_loadu_ps(chunk.as_ptr())));
            let h = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(v);
            let mut packed = [0u32; 4];
            _mm_storeu_si128(packed.as_mut_ptr().cast(), h);
            w.copy_from_slice(&packed[..w.len()]);
        }
    }
}

/// Scatters level `l` of `dout` (`[n x width]`) into `grads`.
///
/// # Safety
/// As [`forward_level`], for `grads` and `dout`.
#[target_feature(enable = "avx2,fma")]
pub unsafe fn backward_level<const DENSE: bool>(
    level: &Level,
    start: usize,
    l: usize,
    soa: &Soa,
    dout: &[f32],
    grads: &mut [f32],
    width: usize,
) {
    let n = soa.x.len();
    assert!(dout.len() >= n * width && grads.len() >= start + FEATURES * level.size);
    // Software-pipelined: the corners of the next group of 8 points are
    // computed and prefetched before the current group's adds, so that
    // its cache misses overlap this group's work. The adds happen in
    // the same order as without the pipeline.
    let prep = |g: usize| -> Option<Group> {
        let gs: [[f32; 2]; 8] = std::array::from_fn(|j| {
            let o = (g + j) * width + FEATURES * l;
            [dout[o], dout[o + 1]]
        });
        if gs.iter().all(|v| v[0] == 0.0 && v[1] == 0.0) {
            return None;
        }
        let mut ix = [[0u32; 8]; 8];
        let mut ws = [[0f32; 8]; 8];
        // SAFETY: AVX2 (caller); stores into local arrays of 8 lanes.
        unsafe {
            let (idx, wt) = corners8::<DENSE>(level, soa, g);
            for c in 0..8 {
                _mm256_storeu_si256(ix[c].as_mut_ptr().cast(), idx[c]);
                _mm256_storeu_ps(ws[c].as_mut_ptr(), wt[c]);
            }
        }
        Some(Group { ix, ws, gs })
    };
    let fetch = |grads: &[f32], group: &Option<Group>| {
        for row in group.iter().flat_map(|g| &g.ix) {
            for &i in row {
                prefetch(grads, start + FEATURES * i as usize);
            }
        }
    };
    let mut cur = if n > 0 { prep(0) } else { None };
    fetch(grads, &cur);
    for g in (0..n).step_by(8) {
        let next = if g + 8 < n { prep(g + 8) } else { None };
        fetch(grads, &next);
        if let Some(Group { ix, ws, gs }) = &cur {
            for c in 0..8 {
                for j in 0..8 {
                    let k = start + FEATURES * ix[c][j] as usize;
                    // SAFETY: indices lie in the level's table, asserted to
                    // be inside `grads`.
                    unsafe {
                        *grads.get_unchecked_mut(k) += ws[c][j] * gs[j][0];
                        *grads.get_unchecked_mut(k + 1) += ws[c][j] * gs[j][1];
                    }
                }
            }
        }
        cur = next;
    }
}

/// One group of 8 points of [`backward_level`]: each corner's entry
/// indices and weights, and the points' two output gradients.
struct Group {
    ix: [[u32; 8]; 8],
    ws: [[f32; 8]; 8],
    gs: [[f32; 2]; 8],
}
