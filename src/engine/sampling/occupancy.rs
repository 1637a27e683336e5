//! An occupancy grid over the scene box: which cells may hold density.
//! Rays sample only the occupied parts of their interval, so empty space
//! costs nothing.
//!
//! The update is a few named steps, as in instant-ngp: evaluate the density
//! at a random point in a share of the cells, decay the running value and
//! take the maximum (an EMA of maxima), threshold to bits, then (unless
//! configured not to) dilate the bits by one cell so that a ray stepping
//! half a cell at a time can never step over a cell it crosses. The
//! marcher ([`OccupancyGrid::march`]) tests each lattice point's own cell
//! and leaves empty space through mip levels of the bits.

use rayon::prelude::*;

use crate::engine::geometry::math::{Aabb, Ray, Vec3};
use crate::engine::rng::Rng;

/// Grid settings. `Default` suits the classic model.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OccupancyConfig {
    /// Cells per side.
    pub resolution: usize,
    /// Density (per model unit) below which a cell counts as empty (or the
    /// grid's mean density, when that is lower).
    pub threshold: f32,
    /// Decay of the running density at each update of a cell.
    pub decay: f32,
    /// Update every this many training steps...
    pub update_every: u64,
    /// ... a `1 / sweep` share of the cells, so a full sweep takes
    /// `update_every * sweep` steps.
    pub sweep: usize,
    /// Cells currently empty are visited at this (larger) period instead:
    /// empty space rarely fills in, while occupied cells must be freed soon
    /// to save samples (0: the same as `sweep`).
    #[serde(default)]
    pub empty_sweep: usize,
    /// No skipping before this many steps (the field is still noise).
    pub warmup_steps: u64,
    /// Update steps up to this one that are powers of two refresh every
    /// cell, not a `1 / sweep` share, so that skipping starts right after the
    /// warm-up instead of a full sweep later (0: never).
    #[serde(default)]
    pub full_updates_until: u64,
    /// Whether the bits are dilated by one cell (`true`, which a sampler
    /// that steps half a cell at a time needs: [`OccupancyGrid::segments`]),
    /// or `null` for the model to decide from its scene when it is built
    /// (the fast model stores its choice). A configuration without the
    /// field, as written before it existed, is dilated.
    #[serde(default = "dilated")]
    pub dilate: Option<bool>,
}

fn dilated() -> Option<bool> {
    Some(true)
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        Self {
            resolution: 64,
            threshold: 0.5,
            decay: 0.95,
            update_every: 8,
            sweep: 8,
            warmup_steps: 32,
            full_updates_until: 0,
            empty_sweep: 0,
            dilate: Some(true),
        }
    }
}

/// The grid: running densities and occupancy bits (dilated unless
/// configured otherwise).
#[derive(Clone, Debug)]
pub struct OccupancyGrid {
    pub config: OccupancyConfig,
    pub aabb: Aabb,
    pub density: Vec<f32>,
    pub bits: Vec<bool>,
    /// `bits` packed 64 to a word (256 KiB at 128^3, where the bools take
    /// 2 MiB): the marcher's lookups stay in L2.
    packed: Vec<u64>,
    /// The occupancy mip levels 1, 2, ...: level `l` has cells of `2^l`
    /// cells a side (`ceil(resolution / 2^l)` of them a side), each set when
    /// any cell inside it is, packed like `packed`. A marcher leaves the
    /// largest empty one around a point in one step.
    mips: Vec<Vec<u64>>,
    /// Whether skipping is active (after warm-up).
    pub active: bool,
    /// The density below which the last rebuild called a cell empty (the
    /// configured threshold or the mean density, whichever was lower; 0
    /// before the first).
    pub cutoff: f32,
    /// Cells per world unit along each axis.
    inv_cell: Vec3,
}

/// Occupied parts of a ray, and a map between distance along the ray `t`
/// and occupied length `s` (the distance counted only inside segments).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Segments {
    pub spans: Vec<(f32, f32)>,
    /// Occupied length before each span.
    cum: Vec<f32>,
}

impl Segments {
    pub fn single(t0: f32, t1: f32) -> Self {
        Self { spans: vec![(t0, t1)], cum: vec![0.0] }
    }
    fn push(&mut self, t0: f32, t1: f32) {
        if t1 <= t0 {
            return;
        }
        if let Some(last) = self.spans.last_mut()
            && last.1 >= t0
        {
            last.1 = last.1.max(t1);
            return;
        }
        let before = self.length();
        self.spans.push((t0, t1));
        self.cum.push(before);
    }
    /// Total occupied length.
    pub fn length(&self) -> f32 {
        match (self.spans.last(), self.cum.last()) {
            (Some(&(a, b)), Some(&c)) => c + (b - a),
            _ => 0.0,
        }
    }
    /// Distance along the ray of occupied length `s` (clamped to the spans).
    pub fn to_t(&self, s: f32) -> f32 {
        if self.spans.is_empty() {
            return 0.0;
        }
        let k = self.cum.partition_point(|&c| c <= s).saturating_sub(1);
        let (a, b) = self.spans[k];
        (a + (s - self.cum[k])).clamp(a, b)
    }
}

impl OccupancyGrid {
    pub fn new(config: OccupancyConfig, aabb: Aabb) -> Self {
        let n = config.resolution.pow(3);
        let ext = aabb.max - aabb.min;
        let r = config.resolution as f32;
        let inv_cell = Vec3::new(r / ext.x, r / ext.y, r / ext.z);
        let packed = vec![u64::MAX; n.div_ceil(64)];
        let mips = (1..Self::levels(config.resolution))
            .map(|l| vec![u64::MAX; Self::level_res(config.resolution, l).pow(3).div_ceil(64)])
            .collect();
        Self {
            config,
            aabb,
            density: vec![f32::INFINITY; n],
            bits: vec![true; n],
            packed,
            mips,
            active: false,
            cutoff: 0.0,
            inv_cell,
        }
    }

    fn cell_size(&self) -> Vec3 {
        (self.aabb.max - self.aabb.min) * (1.0 / self.config.resolution as f32)
    }

    /// Index of the cell holding `p`, if inside the box.
    #[inline]
    pub fn cell_of(&self, p: Vec3) -> Option<usize> {
        let r = self.config.resolution;
        let rel = p - self.aabb.min;
        // Truncation is floor for v >= 0 (and needs no libm call); NaN fails
        // the comparison.
        let f = |v: f32| (v >= 0.0 && v < r as f32).then_some(v as usize);
        let (x, y, z) = (f(rel.x * self.inv_cell.x)?, f(rel.y * self.inv_cell.y)?, f(rel.z * self.inv_cell.z)?);
        // Rounding of a point just below the box's far faces.
        (x < r && y < r && z < r).then_some((x * r + y) * r + z)
    }

    pub fn occupied(&self, p: Vec3) -> bool {
        !self.active || self.cell_of(p).is_some_and(|c| self.bit(c))
    }

    /// Share of occupied cells.
    pub fn occupancy(&self) -> f64 {
        self.bits.iter().filter(|&&b| b).count() as f64 / self.bits.len() as f64
    }

    /// Whether `step` is an update step. With full refreshes that reach the
    /// end of the warm-up, updates before it are skipped: the first full
    /// refresh after it overwrites them.
    pub fn due(&self, step: u64) -> bool {
        let c = &self.config;
        step > 0
            && step.is_multiple_of(c.update_every.max(1))
            && (c.full_updates_until < self.first_active_update() || step >= c.warmup_steps)
    }

    /// The first update step at or after the warm-up.
    fn first_active_update(&self) -> u64 {
        let every = self.config.update_every.max(1);
        self.config.warmup_steps.max(1).div_ceil(every) * every
    }

    /// Whether the update at `step` refreshes every cell: the first one after
    /// the warm-up and those at powers of two up to `full_updates_until`.
    fn full_update(&self, step: u64) -> bool {
        step <= self.config.full_updates_until && (step.is_power_of_two() || step == self.first_active_update())
    }

    /// The cells updated at `step` and a random point in each (model space):
    /// a `1 / sweep` share of the occupied cells and a `1 / empty_sweep`
    /// share of the empty ones, or all of them at a full update.
    pub fn update_points(&self, step: u64, seed: u64) -> (Vec<usize>, Vec<f32>) {
        let r = self.config.resolution;
        let full = self.full_update(step);
        let sweep = if full { 1 } else { self.config.sweep.max(1) };
        let empty_sweep = match self.config.empty_sweep {
            _ if full => 1,
            0 => sweep,
            e => e,
        };
        let k = step / self.config.update_every.max(1);
        let (phase, empty_phase) = ((k % sweep as u64) as usize, (k % empty_sweep as u64) as usize);
        let mut rng = Rng::stream(seed, step, 0x0CC0);
        let cs = self.cell_size();
        let n = r * r * r;
        let mut cells = Vec::with_capacity(n / sweep.min(empty_sweep) + 1);
        let mut pts = Vec::with_capacity(3 * cells.capacity());
        let mut visit = |c: usize| {
            let (x, y, z) = (c / (r * r), (c / r) % r, c % r);
            let p = self.aabb.min
                + Vec3::new(
                    (x as f32 + rng.f32()) * cs.x,
                    (y as f32 + rng.f32()) * cs.y,
                    (z as f32 + rng.f32()) * cs.z,
                );
            cells.push(c);
            pts.extend_from_slice(&[p.x, p.y, p.z]);
        };
        if sweep == empty_sweep {
            (phase..n).step_by(sweep).for_each(&mut visit);
        } else {
            // Two passes in cell order: occupied cells of this phase, then
            // empty cells of the empty phase (a cell is in one of them only).
            (phase..n).step_by(sweep).filter(|&c| self.bits[c]).for_each(&mut visit);
            (empty_phase..n).step_by(empty_sweep).filter(|&c| !self.bits[c]).for_each(&mut visit);
        }
        (cells, pts)
    }

    /// Folds the densities measured at `update_points` into the grid and
    /// rebuilds the bits. Non-finite densities count as occupied.
    pub fn apply(&mut self, step: u64, cells: &[usize], sigma: &[f32]) {
        for (&c, &s) in cells.iter().zip(sigma) {
            let s = if s.is_nan() { f32::INFINITY } else { s };
            let old = if self.density[c].is_finite() { self.density[c] * self.config.decay } else { 0.0 };
            self.density[c] = old.max(s);
        }
        self.active = step >= self.config.warmup_steps;
        self.rebuild_bits();
    }

    fn rebuild_bits(&mut self) {
        let r = self.config.resolution;
        // As in Instant-NGP: never stricter than the mean density, so a young
        // field whose densities are all still low is not emptied wholesale.
        let (sum, count) = self
            .density
            .par_iter()
            .filter(|d| d.is_finite())
            .fold(|| (0.0f64, 0usize), |(s, c), &d| (s + d as f64, c + 1))
            .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        let mean = if count > 0 { (sum / count as f64) as f32 } else { f32::INFINITY };
        let thr = self.config.threshold.min(mean);
        self.cutoff = thr;
        let raw: Vec<bool> = self.density.par_iter().map(|&d| d >= thr || d.is_nan()).collect();
        self.bits = if self.config.dilate.unwrap_or(true) { dilate(&raw, r) } else { raw };
        self.packed = self
            .bits
            .chunks(64)
            .map(|w| w.iter().enumerate().fold(0u64, |acc, (i, &b)| acc | ((b as u64) << i)))
            .collect();
        self.rebuild_mips();
    }

    /// `bits[c]`, from the packed copy.
    #[inline]
    pub fn bit(&self, c: usize) -> bool {
        packed_bit(&self.packed, c)
    }

    /// Mip levels, the cells themselves included: up to cells of half the
    /// grid a side.
    fn levels(res: usize) -> usize {
        let mut l = 1;
        while (2usize << l) <= res {
            l += 1;
        }
        l
    }

    /// Cells a side at mip level `l`.
    #[inline]
    fn level_res(res: usize, l: usize) -> usize {
        // Shifts, not `div_ceil`: a division by a variable is slow.
        (res + (1 << l) - 1) >> l
    }

    /// Each mip level from the one below it (level 1 from the cells).
    fn rebuild_mips(&mut self) {
        let res = self.config.resolution;
        for l in 1..=self.mips.len() {
            let (below, this) = self.mips.split_at_mut(l - 1);
            let fine = below.last().unwrap_or(&self.packed);
            let (r0, r) = (Self::level_res(res, l - 1), Self::level_res(res, l));
            let mip = &mut this[0];
            mip.fill(0);
            for x in 0..r0 {
                for y in 0..r0 {
                    for z in 0..r0 {
                        if packed_bit(fine, (x * r0 + y) * r0 + z) {
                            let p = ((x / 2) * r + y / 2) * r + z / 2;
                            mip[p >> 6] |= 1 << (p & 63);
                        }
                    }
                }
            }
        }
    }

    /// Whether mip level `l` (0: the cells) is set around cell `at`.
    #[inline]
    fn mip_bit(&self, l: usize, at: [usize; 3]) -> bool {
        let words = if l == 0 { &self.packed } else { &self.mips[l - 1] };
        let r = Self::level_res(self.config.resolution, l);
        packed_bit(words, ((at[0] >> l) * r + (at[1] >> l)) * r + (at[2] >> l))
    }

    /// `ray` in cell coordinates, for [`OccupancyGrid::march`].
    pub fn grid_ray(&self, ray: &Ray) -> GridRay {
        let o = ray.origin - self.aabb.min;
        let o = [o.x * self.inv_cell.x, o.y * self.inv_cell.y, o.z * self.inv_cell.z];
        let d = [ray.dir.x * self.inv_cell.x, ray.dir.y * self.inv_cell.y, ray.dir.z * self.inv_cell.z];
        GridRay { o, d, inv: d.map(|v| if v != 0.0 { 1.0 / v } else { f32::INFINITY }) }
    }

    /// What lies at distance `t` along `r`: the box's outside, an occupied
    /// cell and where the ray leaves it, or the largest empty mip cell
    /// around the point and where the ray leaves that. Every cell counts as
    /// occupied before the warm-up ends.
    #[inline]
    pub fn probe(&self, r: &GridRay, t: f32) -> Probe {
        let res = self.config.resolution;
        let rf = res as f32;
        let mut at = [0usize; 3];
        for (a, i) in at.iter_mut().enumerate() {
            let v = r.o[a] + t * r.d[a];
            // Truncation is floor for v >= 0 (no libm call); NaN fails the test.
            if !(v >= 0.0 && v < rf) {
                return Probe::Outside;
            }
            *i = (v as usize).min(res - 1);
        }
        if !self.active {
            // The whole box is one occupied region.
            return Probe::Occupied { exit: r.exit([0; 3], res, t) };
        }
        if self.mip_bit(0, at) {
            return Probe::Occupied { exit: r.exit(at, 1, t) };
        }
        // The coarsest empty level around the point.
        let mut l = 0;
        while l < self.mips.len() && !self.mip_bit(l + 1, at) {
            l += 1;
        }
        Probe::Empty { exit: r.exit(at.map(|i| i >> l << l), 1 << l, t) }
    }

    /// Marches `ray` from `*t` to `t1` on the lattice `*t + k * dt`: calls
    /// `sample(t)` for each lattice point in an occupied cell (at most
    /// `limit` of them), steps over empty regions to the first
    /// lattice point past them, and leaves `*t` at the next lattice point
    /// to visit. Returns the samples taken and the lattice points skipped.
    #[inline]
    pub fn march(
        &self,
        ray: &GridRay,
        t: &mut f32,
        t1: f32,
        dt: f32,
        limit: usize,
        mut sample: impl FnMut(f32),
    ) -> (usize, u64) {
        let inv_dt = 1.0 / dt;
        let (mut count, mut skipped) = (0, 0u64);
        while *t < t1 && count < limit {
            match self.probe(ray, *t) {
                Probe::Occupied { exit } => {
                    // Every lattice point up to the cell's exit (at least the
                    // one that found it, so rounding at a face cannot stall).
                    let end = exit.min(t1);
                    loop {
                        sample(*t);
                        count += 1;
                        let next = *t + dt;
                        if next <= *t {
                            // dt is below f32 resolution this far along the
                            // ray: stop rather than repeat the point.
                            *t = t1;
                            break;
                        }
                        *t = next;
                        if *t >= end || count >= limit {
                            break;
                        }
                    }
                }
                Probe::Empty { exit } => {
                    // ceil without a libm call: steps are whole and >= 1.
                    let q = (exit - *t) * inv_dt;
                    let k = if q.is_finite() && q > 1.0 {
                        let f = q as u32 as f32;
                        if f < q { f + 1.0 } else { f }
                    } else {
                        1.0
                    };
                    skipped += k as u64;
                    let next = *t + k * dt;
                    *t = if next > *t { next } else { t1 };
                }
                Probe::Outside => {
                    let next = *t + dt;
                    *t = if next > *t { next } else { t1 };
                }
            }
        }
        (count, skipped)
    }

    /// The occupied parts of `[t0, t1]` along `ray`, found by stepping half a
    /// cell at a time (the dilated bits make this conservative).
    pub fn segments(&self, ray: &Ray, t0: f32, t1: f32) -> Segments {
        if !self.active {
            return Segments::single(t0, t1);
        }
        let cs = self.cell_size();
        let step = 0.5 * cs.x.min(cs.y).min(cs.z);
        let mut segs = Segments::default();
        let mut t = t0;
        while t < t1 {
            let next = (t + step).min(t1);
            if next <= t {
                // The step is below f32 resolution this far along the ray:
                // keep the rest rather than loop forever.
                segs.push(t, t1);
                break;
            }
            if self.occupied(ray.at(0.5 * (t + next))) {
                segs.push(t, next);
            }
            t = next;
        }
        segs
    }
}

/// Bit `c` of bits packed 64 to a word.
#[inline]
fn packed_bit(words: &[u64], c: usize) -> bool {
    (words[c >> 6] >> (c & 63)) & 1 != 0
}

/// A ray in the grid's cell coordinates (cell `(x, y, z)` spans `[x, x+1)`
/// along the first axis, and so on), with its inverse direction.
#[derive(Clone, Copy, Debug)]
pub struct GridRay {
    o: [f32; 3],
    d: [f32; 3],
    inv: [f32; 3],
}

impl GridRay {
    /// Where the ray leaves the cube of `size` cells a side whose lowest
    /// cell is `lo` (not before `t`).
    #[inline]
    fn exit(&self, lo: [usize; 3], size: usize, t: f32) -> f32 {
        let mut exit = f32::INFINITY;
        for a in 0..3 {
            let d = self.d[a];
            let face = if d > 0.0 {
                (lo[a] + size) as f32
            } else if d < 0.0 {
                lo[a] as f32
            } else {
                continue;
            };
            exit = exit.min((face - self.o[a]) * self.inv[a]);
        }
        exit.max(t)
    }
}

/// What a marcher finds at one point of its ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Probe {
    /// Outside the grid's box.
    Outside,
    /// In an occupied cell, which the ray leaves at `exit`.
    Occupied { exit: f32 },
    /// In an empty cell (or an empty block), which the ray leaves at `exit`.
    Empty { exit: f32 },
}

/// Marks every cell with an occupied cell among its 27 neighbours (itself
/// included): a 3x3x3 maximum, done as three passes of 3 along each axis.
fn dilate(raw: &[bool], r: usize) -> Vec<bool> {
    let slab = r * r;
    let mut a = vec![false; raw.len()];
    a.par_chunks_mut(r).zip(raw.par_chunks(r)).for_each(|(o, i)| {
        for z in 0..r {
            o[z] = i[z] || (z > 0 && i[z - 1]) || (z + 1 < r && i[z + 1]);
        }
    });
    let mut b = vec![false; raw.len()];
    b.par_chunks_mut(slab).zip(a.par_chunks(slab)).for_each(|(o, i)| {
        for k in 0..slab {
            let y = k / r;
            o[k] = i[k] || (y > 0 && i[k - r]) || (y + 1 < r && i[k + r]);
        }
    });
    let mut out = vec![false; raw.len()];
    out.par_chunks_mut(slab).enumerate().for_each(|(x, o)| {
        let mid = &b[x * slab..(x + 1) * slab];
        let lo = (x > 0).then(|| &b[(x - 1) * slab..x * slab]);
        let hi = (x + 1 < r).then(|| &b[(x + 1) * slab..(x + 2) * slab]);
        for k in 0..slab {
            o[k] = mid[k] || lo.is_some_and(|l| l[k]) || hi.is_some_and(|h| h[k]);
        }
    });
    out
}

#[cfg(test)]
#[path = "occupancy_tests.rs"]
mod tests;
