//! Multiresolution hash encoding (Müller et al. 2022): `L` levels of
//! `F = 2` features, level `l` a grid of resolution `N_l = floor(N_min b^l)`,
//! stored densely when `(N_l + 1)^3` fits the table and hashed otherwise;
//! trilinear interpolation of the 8 corners. The backward pass scatters
//! gradients into a (per-thread) gradient buffer, or is recorded and
//! scattered later for all threads at once, level by level
//! (`hashgrid_scatter.rs`); `input_grad` gives the
//! gradient with respect to the points, for position gradients (camera
//! pose refinement) through the encoding.
//!
//! Inputs are points in the unit cube `[0, 1]^3`; points outside are clamped
//! to it (the caller only samples inside the scene box).

/// Features per level (fixed: two f32s make one 8-byte gather).
pub const FEATURES: usize = 2;

/// Shape of the encoding. `Default` is Instant-NGP's, with a table size
/// chosen for CPU caches.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HashGridConfig {
    pub levels: usize,
    /// log2 of the entries per level.
    pub log2_table: u32,
    pub base_resolution: u32,
    pub finest_resolution: u32,
}

impl Default for HashGridConfig {
    fn default() -> Self {
        Self { levels: 16, log2_table: 15, base_resolution: 16, finest_resolution: 512 }
    }
}

/// One level's layout.
#[derive(Clone, Copy, Debug)]
struct Level {
    res: u32,
    /// Offset of the level's table in the parameter range.
    offset: usize,
    /// Entries in the level's table.
    size: usize,
    dense: bool,
}

/// The encoding; its parameters are a range of a flat buffer.
#[derive(Clone, Debug)]
pub struct HashGrid {
    pub config: HashGridConfig,
    levels: Vec<Level>,
    pub params: std::ops::Range<usize>,
}

/// A grid's table in half precision, for rendering: each entry's two
/// features as IEEE binary16 in one 32-bit word (feature 0 in the low half),
/// so one 8-wide gather reads the entries of 8 points (the f32 table needs
/// two 4-wide gathers of 8-byte pairs) from a table half the size. Built
/// from the parameters by [`HashGrid::half_table`], it does not follow them:
/// whoever holds one drops it when the parameters change. Values round to
/// the nearest binary16 (a relative error below 2^-11), beyond +-65504 to
/// +-65504.
#[derive(Debug)]
pub struct HalfTable {
    words: Vec<u32>,
}

/// Whether this CPU has what [`HalfTable`]s need (AVX2, FMA and F16C).
pub fn half_tables_supported() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        crate::engine::nn::gemm::has_avx2_fma() && is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

impl HashGrid {
    pub fn new(layout: &mut crate::engine::nn::linear::ParamLayout, config: HashGridConfig) -> Self {
        Self::with_name(layout, "hashgrid", config)
    }

    /// [`Self::new`] with its parameter range named `name` in `layout`
    /// (a model with several grids names each).
    pub fn with_name(layout: &mut crate::engine::nn::linear::ParamLayout, name: &str, config: HashGridConfig) -> Self {
        let t = 1usize << config.log2_table;
        let l = config.levels.max(1);
        let b = if l > 1 {
            ((config.finest_resolution as f64).ln() - (config.base_resolution as f64).ln()) / (l - 1) as f64
        } else {
            0.0
        };
        let mut levels = Vec::with_capacity(l);
        let mut offset = 0;
        for i in 0..l {
            let res = ((config.base_resolution as f64) * (b * i as f64).exp()).floor() as u32;
            let res = res.max(1);
            let dense_size = (res as usize + 1).pow(3);
            let (size, dense) = if dense_size <= t { (dense_size, true) } else { (t, false) };
            levels.push(Level { res, offset, size, dense });
            offset += size * FEATURES;
        }
        let params = layout.add(name, offset);
        Self { config, levels, params }
    }

    /// Output width: levels x features.
    pub fn width(&self) -> usize {
        self.levels.len() * FEATURES
    }

    /// Small uniform initial values, as in Instant-NGP.
    pub fn init(&self, params: &mut [f32], rng: &mut crate::engine::rng::Rng) {
        for p in &mut params[self.params.clone()] {
            *p = (rng.f32() * 2.0 - 1.0) * 1e-4;
        }
    }

    /// The table index of a vertex (the reference for `corners_of`, which
    /// computes the same indices a term per axis).
    #[cfg(test)]
    fn index(level: &Level, x: u32, y: u32, z: u32) -> usize {
        if level.dense {
            let r = level.res as usize + 1;
            (x as usize * r + y as usize) * r + z as usize
        } else {
            let h = x.wrapping_mul(1) ^ y.wrapping_mul(2_654_435_761) ^ z.wrapping_mul(805_459_861);
            (h as usize) & (level.size - 1)
        }
    }

    /// The 8 corner indices (into the parameter buffer, first feature) and
    /// trilinear weights of point `p` at `level`.
    #[cfg(test)]
    fn corners(&self, level: &Level, p: [f32; 3]) -> ([usize; 8], [f32; 8]) {
        let p = p.map(sanitize);
        if level.dense { self.corners_of::<true>(level, p) } else { self.corners_of::<false>(level, p) }
    }

    /// [`Self::corners`] for a level known to be dense or hashed: the index
    /// is a sum (dense) or an xor (hashed) of one term per axis, so the six
    /// terms are computed once and combined for the eight corners. `p` is in
    /// the unit cube (see [`sanitize`]); every index is inside the level's
    /// table.
    #[inline(always)]
    fn corners_of<const DENSE: bool>(&self, level: &Level, p: [f32; 3]) -> ([usize; 8], [f32; 8]) {
        let r = level.res as f32;
        let mut base = [0u32; 3];
        let mut frac = [0f32; 3];
        for d in 0..3 {
            let v = p[d] * r;
            // v >= 0, so truncation is floor (and avoids a libm call).
            let f = (v as u32).min(level.res - 1);
            base[d] = f;
            frac[d] = v - f as f32;
        }
        let [x, y, z] = base;
        let terms: [[usize; 2]; 3] = if DENSE {
            let n = level.res as usize + 1;
            let (x, y, z) = (x as usize, y as usize, z as usize);
            [[x * n * n, (x + 1) * n * n], [y * n, (y + 1) * n], [z, z + 1]]
        } else {
            let h = |v: u32, prime: u32| [v.wrapping_mul(prime) as usize, (v + 1).wrapping_mul(prime) as usize];
            [h(x, 1), h(y, 2_654_435_761), h(z, 805_459_861)]
        };
        let start = self.params.start + level.offset;
        let mask = level.size - 1;
        let ws = [[1.0 - frac[0], frac[0]], [1.0 - frac[1], frac[1]], [1.0 - frac[2], frac[2]]];
        let mut idx = [0usize; 8];
        let mut w = [0f32; 8];
        for c in 0..8 {
            let (dx, dy, dz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
            let i = if DENSE {
                terms[0][dx] + terms[1][dy] + terms[2][dz]
            } else {
                // The hash keeps 32 bits, as the reference's uint32 arithmetic.
                ((terms[0][dx] ^ terms[1][dy] ^ terms[2][dz]) as u32 as usize) & mask
            };
            idx[c] = start + FEATURES * i;
            w[c] = ws[0][dx] * ws[1][dy] * ws[2][dz];
        }
        (idx, w)
    }

    /// Encodes `n` points (`pts` is `[n x 3]` in the unit cube) into the
    /// first `n` rows of `out` (`[>= n x width]`).
    ///
    /// Level by level, so that one level's table stays in cache while all
    /// points visit it.
    pub fn forward(&self, params: &[f32], pts: &[f32], out: &mut [f32]) {
        let out = &mut out[..pts.len() / 3 * self.width()];
        assert!(params.len() >= self.params.end, "hash grid: parameter buffer too short");
        let pts: Vec<f32> = pts.iter().map(|&v| sanitize(v)).collect();
        // Whole groups of 8 points go through the AVX2 path when the CPU has
        // it; the rest (and other CPUs) through the scalar one.
        let done = self.forward_simd(params, &pts, out);
        let (pts, out) = (&pts[3 * done..], &mut out[done * self.width()..]);
        for (l, level) in self.levels.iter().enumerate() {
            if level.dense {
                self.forward_level::<true>(l, level, params, pts, out);
            } else {
                self.forward_level::<false>(l, level, params, pts, out);
            }
        }
    }

    /// This grid's table of `params` in half precision, for
    /// [`Self::forward_half`]; `None` on a CPU without AVX2, FMA and F16C
    /// (use [`Self::forward`] there).
    pub fn half_table(&self, params: &[f32]) -> Option<HalfTable> {
        if !half_tables_supported() {
            return None;
        }
        // Every level's table is whole entries (pairs) from the range's
        // start, so entry `i` of a level at `offset` is word `offset / 2 + i`.
        let table = &params[self.params.clone()];
        let mut words = vec![0u32; table.len() / FEATURES];
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `half_tables_supported` checked F16C and AVX; `words` holds
        // one word per pair of `table`.
        unsafe {
            simd::pack_half(table, &mut words);
        }
        Some(HalfTable { words })
    }

    /// [`Self::forward`] from a [`HalfTable`] of this grid (the table's
    /// features in half precision, the interpolation in f32).
    pub fn forward_half(&self, table: &HalfTable, pts: &[f32], out: &mut [f32]) {
        let n = pts.len() / 3;
        let out = &mut out[..n * self.width()];
        assert_eq!(table.words.len() * FEATURES, self.params.len(), "hash grid: a half table of another grid");
        #[cfg(target_arch = "x86_64")]
        {
            // Padded to whole groups of 8 (the padding's rows are not written).
            let mut padded: Vec<f32> = pts.iter().map(|&v| sanitize(v)).collect();
            padded.resize(3 * n.div_ceil(8) * 8, 0.0);
            let soa = simd::Soa::new(&padded);
            for (l, level) in self.levels.iter().enumerate() {
                let start = level.offset / FEATURES;
                // SAFETY: a `HalfTable` exists only where AVX2, FMA and F16C
                // do; it has this grid's size (asserted); `out` has `n` rows.
                unsafe {
                    if level.dense {
                        simd::forward_level_half::<true>(level, start, l, &table.words, &soa, n, out, self.width());
                    } else {
                        simd::forward_level_half::<false>(level, start, l, &table.words, &soa, n, out, self.width());
                    }
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (table, pts, out);
            unreachable!("half tables are built on x86_64 only");
        }
    }

    /// Levels of the encoding (its width is twice that).
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// The encoding of 8 points (coordinates `x`, `y`, `z`, each already
    /// in `[0, 1]`) from a [`HalfTable`] of this grid, into `out` (`2 l`
    /// and `2 l + 1`: level `l`'s features, the layout of
    /// [`Self::forward_half`]'s rows): for fused render kernels that go on
    /// with the features in registers.
    ///
    /// # Safety
    /// AVX2, FMA and F16C must be available (they are wherever a
    /// `HalfTable` exists), enabled in the caller, into which this is
    /// inlined.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub unsafe fn encode8_half(
        &self,
        table: &HalfTable,
        x: std::arch::x86_64::__m256,
        y: std::arch::x86_64::__m256,
        z: std::arch::x86_64::__m256,
        out: &mut [std::arch::x86_64::__m256],
    ) {
        assert_eq!(table.words.len() * FEATURES, self.params.len(), "hash grid: a half table of another grid");
        // SAFETY: the caller's guarantee; the table is this grid's (asserted).
        unsafe { simd::encode8_half(&self.levels, &table.words, x, y, z, out) }
    }

    /// The AVX2 forward pass over the first `n / 8 * 8` points; returns how
    /// many points it encoded (0 without AVX2/FMA).
    fn forward_simd(&self, params: &[f32], pts: &[f32], out: &mut [f32]) -> usize {
        #[cfg(target_arch = "x86_64")]
        if crate::engine::nn::gemm::has_avx2_fma() {
            let n = pts.len() / 3 / 8 * 8;
            let soa = simd::Soa::new(&pts[..3 * n]);
            for (l, level) in self.levels.iter().enumerate() {
                let start = self.params.start + level.offset;
                // SAFETY: AVX2 and FMA are available; `forward` asserted that
                // `params` holds the table, and `out` has `n` rows.
                unsafe {
                    if level.dense {
                        simd::forward_level::<true>(level, start, l, params, &soa, out, self.width());
                    } else {
                        simd::forward_level::<false>(level, start, l, params, &soa, out, self.width());
                    }
                }
            }
            return n;
        }
        let _ = (params, pts, out);
        0
    }

    #[inline(always)]
    fn forward_level<const DENSE: bool>(&self, l: usize, level: &Level, params: &[f32], pts: &[f32], out: &mut [f32]) {
        // In groups: the corners of every point of a group first, with a
        // prefetch of each, then the gathers. The table lookups are cache
        // misses (the profile blames the loads), and this keeps many of them
        // in flight instead of the few an out-of-order window holds.
        let mut idx = [[0usize; 8]; GROUP];
        let mut wts = [[0f32; 8]; GROUP];
        for (p, o) in pts.chunks(3 * GROUP).zip(out.chunks_mut(GROUP * self.width())) {
            let m = p.len() / 3;
            for j in 0..m {
                let (i, w) = self.corners_of::<DENSE>(level, [p[3 * j], p[3 * j + 1], p[3 * j + 2]]);
                for &k in &i {
                    prefetch(params, k);
                }
                idx[j] = i;
                wts[j] = w;
            }
            for (j, o) in o.chunks_exact_mut(self.width()).take(m).enumerate() {
                let (i, w) = (&idx[j], &wts[j]);
                let (mut f0, mut f1) = (0.0f32, 0.0f32);
                for c in 0..8 {
                    debug_assert!(i[c] + 1 < self.params.end);
                    // SAFETY: corner indices lie in the level's table, inside
                    // `self.params`, and `forward` asserted the buffer holds it.
                    let (a, b) = unsafe { (*params.get_unchecked(i[c]), *params.get_unchecked(i[c] + 1)) };
                    f0 += w[c] * a;
                    f1 += w[c] * b;
                }
                o[FEATURES * l] = f0;
                o[FEATURES * l + 1] = f1;
            }
        }
    }

    /// Scatters the first `n` rows of `dout` (`[>= n x width]`) into the
    /// table gradients.
    pub fn backward(&self, pts: &[f32], dout: &[f32], grads: &mut [f32]) {
        let dout = &dout[..pts.len() / 3 * self.width()];
        assert!(grads.len() >= self.params.end, "hash grid: gradient buffer too short");
        let pts: Vec<f32> = pts.iter().map(|&v| sanitize(v)).collect();
        let done = self.backward_simd(&pts, dout, grads);
        let (pts, dout) = (&pts[3 * done..], &dout[done * self.width()..]);
        for (l, level) in self.levels.iter().enumerate() {
            if level.dense {
                self.backward_level::<true>(l, level, pts, dout, grads, 0);
            } else {
                self.backward_level::<false>(l, level, pts, dout, grads, 0);
            }
        }
    }

    /// The backward pass over the first `n / 8 * 8` points with the corners
    /// computed by AVX2 (the scatter stays scalar); returns how many points
    /// it handled (0 without AVX2/FMA).
    fn backward_simd(&self, pts: &[f32], dout: &[f32], grads: &mut [f32]) -> usize {
        #[cfg(target_arch = "x86_64")]
        if crate::engine::nn::gemm::has_avx2_fma() {
            let n = pts.len() / 3 / 8 * 8;
            let soa = simd::Soa::new(&pts[..3 * n]);
            for (l, level) in self.levels.iter().enumerate() {
                let start = self.params.start + level.offset;
                // SAFETY: as in `forward_simd`, for `grads` and `dout`.
                unsafe {
                    if level.dense {
                        simd::backward_level::<true>(level, start, l, &soa, dout, grads, self.width());
                    } else {
                        simd::backward_level::<false>(level, start, l, &soa, dout, grads, self.width());
                    }
                }
            }
            return n;
        }
        let _ = (pts, dout, grads);
        0
    }

    /// Scatters level `l`'s gradients of `pts` into `grads`, which holds the
    /// parameters from index `base` on (0: the whole buffer).
    #[inline(always)]
    fn backward_level<const DENSE: bool>(
        &self,
        l: usize,
        level: &Level,
        pts: &[f32],
        dout: &[f32],
        grads: &mut [f32],
        base: usize,
    ) {
        // Grouped with prefetches, as the forward pass.
        let mut idx = [[0usize; 8]; GROUP];
        let mut wts = [[0f32; 8]; GROUP];
        let mut gs = [[0f32; 2]; GROUP];
        for (p, g) in pts.chunks(3 * GROUP).zip(dout.chunks(GROUP * self.width())) {
            let mut m = 0;
            for (j, g) in g.chunks_exact(self.width()).enumerate() {
                let (g0, g1) = (g[FEATURES * l], g[FEATURES * l + 1]);
                if g0 == 0.0 && g1 == 0.0 {
                    continue;
                }
                let (i, w) = self.corners_of::<DENSE>(level, [p[3 * j], p[3 * j + 1], p[3 * j + 2]]);
                for &k in &i {
                    prefetch(grads, k - base);
                }
                idx[m] = i;
                wts[m] = w;
                gs[m] = [g0, g1];
                m += 1;
            }
            for j in 0..m {
                let (i, w, [g0, g1]) = (&idx[j], &wts[j], gs[j]);
                for c in 0..8 {
                    let k = i[c] - base;
                    debug_assert!(i[c] + 1 < self.params.end && k + 1 < grads.len());
                    // SAFETY: as in `forward_level`; the callers assert that
                    // the gradient buffer holds the level's table from `base`.
                    unsafe {
                        *grads.get_unchecked_mut(k) += w[c] * g0;
                        *grads.get_unchecked_mut(k + 1) += w[c] * g1;
                    }
                }
            }
        }
    }

    /// [`Self::backward`] (the same table gradients, bit for bit: it is
    /// that call), and also the gradient with respect to the input points:
    /// `dpts` (`[>= n x 3]`; its first `n` rows are overwritten) gets dL/du
    /// of each point, as [`Self::input_grad`] computes it.
    pub fn backward_with_input_grad(
        &self,
        params: &[f32],
        pts: &[f32],
        dout: &[f32],
        grads: &mut [f32],
        dpts: &mut [f32],
    ) {
        self.backward(pts, dout, grads);
        self.input_grad(params, pts, dout, dpts);
    }

    /// Writes into the first `n` rows of `dpts` (`[>= n x 3]`) the gradient
    /// dL/du of each of the `n` points `pts` (`[n x 3]`), given dL/d(encoding)
    /// `dout` (`[>= n x width]`).
    ///
    /// At level `l` of resolution `N_l` a point sits in its cell at
    /// fractions `φ_a = N_l u_a - floor(N_l u_a)`; the corner weights are
    /// `w_c = Π_a ω_a(c_a)` with `ω(0) = 1 - φ`, `ω(1) = φ`, so
    /// `dL/du_a = Σ_l N_l Σ_c (2 c_a - 1) Π_{b≠a} ω_b(c_b) (g_l · θ_c)`,
    /// with `g_l` the level's two output gradients and `θ_c` the corner's
    /// features (read again from `params`). The encoding is continuous but
    /// only piecewise smooth: on a cell face this is the derivative inside
    /// the cell the forward pass reads (the one above, except at `u = 1`).
    /// A coordinate the forward pass clamps (below 0, above 1, NaN) gets 0.
    ///
    /// Scalar code on every CPU (the forward pass has an AVX2 path; the
    /// values agree to rounding, as the two forward paths do).
    pub fn input_grad(&self, params: &[f32], pts: &[f32], dout: &[f32], dpts: &mut [f32]) {
        let n = pts.len() / 3;
        assert!(params.len() >= self.params.end, "hash grid: parameter buffer too short");
        assert!(dout.len() >= n * self.width() && dpts.len() >= 3 * n, "hash grid: gradient rows too short");
        let (pts, dout, dpts) = (&pts[..3 * n], &dout[..n * self.width()], &mut dpts[..3 * n]);
        dpts.fill(0.0);
        for (l, level) in self.levels.iter().enumerate() {
            if level.dense {
                self.input_grad_level::<true>(l, level, params, pts, dout, dpts);
            } else {
                self.input_grad_level::<false>(l, level, params, pts, dout, dpts);
            }
        }
    }

    /// Level `l`'s term of [`Self::input_grad`], added to `dpts`.
    fn input_grad_level<const DENSE: bool>(
        &self,
        l: usize,
        level: &Level,
        params: &[f32],
        pts: &[f32],
        dout: &[f32],
        dpts: &mut [f32],
    ) {
        let r = level.res as f32;
        for ((raw, g), d) in pts.chunks_exact(3).zip(dout.chunks_exact(self.width())).zip(dpts.chunks_exact_mut(3)) {
            let (g0, g1) = (g[FEATURES * l], g[FEATURES * l + 1]);
            if g0 == 0.0 && g1 == 0.0 {
                continue;
            }
            let p = [sanitize(raw[0]), sanitize(raw[1]), sanitize(raw[2])];
            let (idx, _) = self.corners_of::<DENSE>(level, p);
            // The fractions as `corners_of` computes them.
            let w: [[f32; 2]; 3] = std::array::from_fn(|a| {
                let v = p[a] * r;
                let f = v - (v as u32).min(level.res - 1) as f32;
                [1.0 - f, f]
            });
            let mut dphi = [0.0f32; 3];
            for (c, &i) in idx.iter().enumerate() {
                let (cx, cy, cz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
                let gt = g0 * params[i] + g1 * params[i + 1];
                let sign = |bit: usize| if bit == 1 { gt } else { -gt };
                dphi[0] += sign(cx) * w[1][cy] * w[2][cz];
                dphi[1] += sign(cy) * w[0][cx] * w[2][cz];
                dphi[2] += sign(cz) * w[0][cx] * w[1][cy];
            }
            for a in 0..3 {
                // The clamp's derivative: 0 outside [0, 1] and for NaN.
                if (0.0..=1.0).contains(&raw[a]) {
                    d[a] += r * dphi[a];
                }
            }
        }
    }
}

/// Points per group of the grouped lookups (8 corners each in flight).
const GROUP: usize = 16;

/// A hint to bring the cache line of `v[k]` into L1; no effect on results.
#[inline(always)]
fn prefetch(v: &[f32], k: usize) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is a hint that cannot fault, whatever the address;
    // `wrapping_add` computes it without bounds checks or overflow UB.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(v.as_ptr().wrapping_add(k).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (v, k);
}

/// A coordinate clamped to the unit interval, NaN mapped to 0.
#[inline(always)]
pub(crate) fn sanitize(v: f32) -> f32 {
    // `clamp` keeps NaN; the test first turns it into 0.
    if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) }
}

/// The AVX2/FMA paths: eight points at a time, their corner indices and
/// weights computed in vector registers, the table read with gathers.
#[cfg(target_arch = "x86_64")]
mod simd;

mod scatter;
pub use scatter::{GridRecord, Scatter};

#[cfg(test)]
mod tests;
