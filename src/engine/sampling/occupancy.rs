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
mod tests {
    use super::*;

    #[test]
    fn separable_dilation_equals_the_27_neighbour_rule() {
        let r = 7isize;
        let mut rng = Rng::new(9);
        let raw: Vec<bool> = (0..r * r * r).map(|_| rng.f32() < 0.04).collect();
        let fast = dilate(&raw, r as usize);
        let idx = |x: isize, y: isize, z: isize| ((x * r + y) * r + z) as usize;
        for x in 0..r {
            for y in 0..r {
                for z in 0..r {
                    let mut any = false;
                    for (dx, dy, dz) in (0..27).map(|k| (k / 9 - 1, (k / 3) % 3 - 1, k % 3 - 1)) {
                        let (a, b, c) = (x + dx, y + dy, z + dz);
                        any |= (0..r).contains(&a) && (0..r).contains(&b) && (0..r).contains(&c) && raw[idx(a, b, c)];
                    }
                    assert_eq!(fast[idx(x, y, z)], any, "cell {x},{y},{z}");
                }
            }
        }
        assert!(fast.iter().filter(|&&b| b).count() > raw.iter().filter(|&&b| b).count());
    }

    /// A grid of two small dense spots in a box of 32^3 cells.
    fn spots(dilate: bool) -> OccupancyGrid {
        let r = 32;
        let cfg = OccupancyConfig {
            resolution: r,
            warmup_steps: 0,
            update_every: 1,
            sweep: 1,
            dilate: Some(dilate),
            ..Default::default()
        };
        let mut g = OccupancyGrid::new(cfg, unit());
        let (cells, pts) = g.update_points(1, 3);
        let sigma: Vec<f32> = pts
            .chunks(3)
            .map(|p| {
                let q = Vec3::new(p[0], p[1], p[2]);
                let near = |c: Vec3| (q - c).norm() < 0.08;
                if near(Vec3::new(0.3, -0.2, 0.1)) || near(Vec3::new(-0.7, 0.6, -0.5)) { 100.0 } else { 0.0 }
            })
            .collect();
        g.apply(1, &cells, &sigma);
        g
    }

    /// A random ray from outside the unit box through a random point of
    /// the two-spot grid's box (aimed at a spot half of the time).
    fn random_ray(rng: &mut Rng, k: usize) -> Ray {
        let target = match k % 4 {
            0 => Vec3::new(0.3, -0.2, 0.1),
            1 => Vec3::new(-0.7, 0.6, -0.5),
            _ => Vec3::new(rng.f32() * 2.0 - 1.0, rng.f32() * 2.0 - 1.0, rng.f32() * 2.0 - 1.0),
        } + Vec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.03;
        let origin = Vec3::new(rng.normal(), rng.normal(), rng.normal()).normalized().unwrap() * 3.0;
        Ray { origin, dir: (target - origin).normalized().unwrap() }
    }

    /// Distance in cells from `p` to the nearest face of the cell holding it.
    fn to_face(g: &OccupancyGrid, p: Vec3) -> f32 {
        let c = (p - g.aabb.min) * (g.config.resolution as f32 / 2.0);
        [c.x, c.y, c.z].iter().map(|v| (v - v.round()).abs()).fold(f32::INFINITY, f32::min)
    }

    /// Each mip level's cell is set exactly when a cell inside it is, also
    /// for a resolution that is not a power of two.
    #[test]
    fn mip_levels_are_the_or_of_their_cells() {
        for (res, levels) in [(32, 5), (24, 4), (20, 4), (3, 1)] {
            let cfg =
                OccupancyConfig { resolution: res, warmup_steps: 0, update_every: 1, sweep: 1, ..Default::default() };
            let mut g = OccupancyGrid::new(cfg, unit());
            let (cells, pts) = g.update_points(1, 3);
            let mut rng = Rng::new(res as u64);
            let sigma: Vec<f32> = pts.chunks(3).map(|_| if rng.f32() < 0.0005 { 100.0 } else { 0.0 }).collect();
            g.apply(1, &cells, &sigma);
            assert_eq!(g.mips.len() + 1, OccupancyGrid::levels(res));
            assert_eq!(OccupancyGrid::levels(res), levels);
            for l in 1..=g.mips.len() {
                let mut set = 0;
                for x in 0..res {
                    for y in 0..res {
                        for z in 0..res {
                            let any = (0..res).filter(|i| i >> l == x >> l).any(|i| {
                                (0..res).filter(|j| j >> l == y >> l).any(|j| {
                                    (0..res).filter(|k| k >> l == z >> l).any(|k| g.bits[(i * res + j) * res + k])
                                })
                            });
                            assert_eq!(g.mip_bit(l, [x, y, z]), any, "res {res} level {l} at {x} {y} {z}");
                            set += any as usize;
                        }
                    }
                }
                assert!(set > 0 && (l > 2 || set < res * res * res), "level {l}: {set} set");
            }
        }
    }

    /// What an empty probe steps over (up to its exit) holds no occupied
    /// cell, and most steps leave a whole empty block.
    #[test]
    fn empty_probes_hold_no_occupied_cell() {
        let g = spots(true);
        let r = g.config.resolution;
        let occupied = g.bits.iter().filter(|&&b| b).count();
        assert!((0..r * r * r).all(|c| g.bit(c) == g.bits[c]), "the packed bits are the bits");
        assert!(occupied > 0 && occupied < r * r * r / 10, "{occupied}");
        let mut rng = Rng::new(11);
        let (mut empty, mut long) = (0, 0);
        for k in 0..400 {
            let ray = random_ray(&mut rng, k);
            let gr = g.grid_ray(&ray);
            let t = 2.0 + 2.0 * rng.f32();
            match g.probe(&gr, t) {
                Probe::Empty { exit } => {
                    assert!(exit >= t, "exit {exit} before t {t}");
                    assert!(!g.occupied(ray.at(t)));
                    empty += 1;
                    long += (exit - t > 4.0 / r as f32) as usize;
                    for i in 0..64 {
                        let p = ray.at(t + (exit - t) * i as f32 / 64.0);
                        assert!(
                            !g.occupied(p) || to_face(&g, p) < 1e-3,
                            "ray {k}: occupied cell at {p:?} before {exit}"
                        );
                    }
                }
                Probe::Occupied { exit } => {
                    assert!(g.occupied(ray.at(t)) && exit >= t);
                    let mid = ray.at(0.5 * (t + exit));
                    assert!(g.occupied(mid) || to_face(&g, mid) < 1e-3);
                }
                Probe::Outside => assert!(g.cell_of(ray.at(t)).is_none()),
            }
        }
        assert!(empty > 200 && long > empty / 2, "{empty} empty probes, {long} leave a block");
    }

    /// Marching takes exactly the lattice points that lie in occupied cells
    /// (but for points within rounding of a cell face), whatever `limit`
    /// splits the march into.
    #[test]
    fn marching_takes_every_occupied_lattice_point() {
        for dilate in [true, false] {
            marching_matches_brute_force(&spots(dilate));
        }
    }

    fn marching_matches_brute_force(g: &OccupancyGrid) {
        let mut rng = Rng::new(12);
        let dt = 0.013;
        let mut total = 0;
        for k in 0..300 {
            let ray = random_ray(&mut rng, k);
            let (t0, t1) = (1.5 + 0.5 * rng.f32(), 4.5);
            let brute: Vec<i64> = (0..)
                .map(|i| (i, t0 + i as f32 * dt))
                .take_while(|&(_, t)| t < t1)
                .filter(|&(_, t)| g.occupied(ray.at(t)) && g.cell_of(ray.at(t)).is_some())
                .map(|(i, _)| i)
                .collect();
            let gr = g.grid_ray(&ray);
            let limit = 1 + k % 20;
            let mut got = Vec::new();
            let mut t = t0;
            loop {
                let before = got.len();
                let (n, _) = g.march(&gr, &mut t, t1, dt, limit, |s| got.push(s));
                assert_eq!(n, got.len() - before);
                assert!(n <= limit);
                if n == 0 {
                    break;
                }
            }
            assert!(t >= t1);
            let got: Vec<i64> = got.iter().map(|&s| ((s - t0) / dt).round() as i64).collect();
            assert!(got.windows(2).all(|w| w[0] < w[1]), "ray {k}: samples in order");
            let near_face = |i: i64| to_face(g, ray.at(t0 + i as f32 * dt)) < 2e-3;
            for i in &brute {
                assert!(got.contains(i) || near_face(*i), "ray {k}: occupied lattice point {i} skipped");
            }
            for i in &got {
                assert!(brute.contains(i) || near_face(*i), "ray {k}: lattice point {i} is empty");
            }
            total += brute.len();
        }
        assert!(total > 500, "the rays cross the spots: {total} occupied points");
    }

    /// Far along a ray, where the step is below f32 resolution, marching
    /// ends instead of looping or repeating a point.
    #[test]
    fn marching_far_along_a_ray_terminates() {
        let mut g = spots(true);
        let ray = Ray { origin: Vec3::new(0.3, -0.2, 4e7), dir: Vec3::new(0.0, 0.0, -1.0) };
        let gr = g.grid_ray(&ray);
        for active in [true, false] {
            g.active = active;
            // 4e7 is the only f32 in the box along this ray (the next one
            // is 4e7 + 4), and 4e7 + 0.01 == 4e7.
            let (t0, t1) = (4e7f32, 4e7f32 + 4.0);
            assert!(t0 < t1 && t0 + 0.01 == t0 && g.cell_of(ray.at(t0)).is_some());
            let mut t = t0;
            let mut got = Vec::new();
            let (n, _) = g.march(&gr, &mut t, t1, 0.01, 1000, |s| got.push(s));
            assert!(n == got.len() && n <= 1 && t >= t1, "{n} samples, t {t}");
            assert!(active || n == 1, "before warm-up the point is sampled");
            // Outside the box the whole way.
            let mut t = 1e8;
            let (n, _) = g.march(&gr, &mut t, 1e8 + 100.0, 0.01, 1000, |_| {});
            assert_eq!((n, t), (0, 1e8 + 100.0));
        }
    }

    /// Before the warm-up every lattice point in the box is a sample.
    #[test]
    fn marching_before_warm_up_takes_every_point() {
        let g = OccupancyGrid::new(OccupancyConfig::default(), unit());
        let ray = Ray { origin: Vec3::new(-3.0, 0.1, 0.2), dir: Vec3::new(1.0, 0.0, 0.0) };
        let mut t = 1.0;
        let mut got = Vec::new();
        let (n, skipped) = g.march(&g.grid_ray(&ray), &mut t, 5.0, 0.01, 10_000, |s| got.push(s));
        assert_eq!(skipped, 0);
        // Inside the box: t in [2, 4).
        assert!((199..=201).contains(&n), "{n}");
        assert!(got.iter().all(|&s| (1.99..4.0).contains(&s)));
    }

    fn unit() -> Aabb {
        Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }
    }

    #[test]
    fn segments_map_occupied_length_to_distance() {
        let mut s = Segments::default();
        s.push(1.0, 2.0);
        s.push(2.0, 2.5); // merges
        s.push(4.0, 5.0);
        assert_eq!(s.spans, vec![(1.0, 2.5), (4.0, 5.0)]);
        assert!((s.length() - 2.5).abs() < 1e-6);
        assert_eq!(s.to_t(0.0), 1.0);
        assert!((s.to_t(1.0) - 2.0).abs() < 1e-6);
        assert!((s.to_t(2.0) - 4.5).abs() < 1e-6);
        assert_eq!(s.to_t(9.0), 5.0);
    }

    #[test]
    fn a_dense_ball_is_never_skipped() {
        let cfg = OccupancyConfig { resolution: 16, warmup_steps: 0, update_every: 1, sweep: 1, ..Default::default() };
        let mut g = OccupancyGrid::new(cfg, unit());
        let (cells, pts) = g.update_points(1, 3);
        let sigma: Vec<f32> =
            pts.chunks(3).map(|p| if Vec3::new(p[0], p[1], p[2]).norm() < 0.3 { 50.0 } else { 0.0 }).collect();
        g.apply(1, &cells, &sigma);
        assert!(g.active);
        assert!(g.occupancy() < 0.2, "most cells are empty: {}", g.occupancy());
        // Every point of the ball is in an occupied cell...
        let mut rng = Rng::new(5);
        for _ in 0..2000 {
            let p = Vec3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5) * 0.6;
            if p.norm() < 0.3 {
                assert!(g.occupied(p), "{p:?}");
            }
        }
        // ... and a ray through the ball keeps the ball's whole chord.
        let ray = Ray { origin: Vec3::new(-3.0, 0.05, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
        let s = g.segments(&ray, 2.0, 4.0);
        let chord = (0.3f32 * 0.3 - 0.05 * 0.05).sqrt();
        assert!(s.spans.iter().any(|&(a, b)| a <= 3.0 - chord && b >= 3.0 + chord), "{:?}", s.spans);
        assert!(s.length() < 1.5, "empty space skipped: {}", s.length());
        // A ray that misses the ball by far has nothing to sample.
        let miss = Ray { origin: Vec3::new(-3.0, 0.9, 0.9), dir: Vec3::new(1.0, 0.0, 0.0) };
        assert_eq!(g.segments(&miss, 2.0, 4.0).length(), 0.0);
    }

    #[test]
    fn rays_from_far_away_terminate() {
        let cfg = OccupancyConfig { resolution: 32, warmup_steps: 0, ..Default::default() };
        let mut g = OccupancyGrid::new(cfg, unit());
        g.apply(1, &[], &[]);
        // At t = 4e6 an f32 step is 0.25 or 0.5, more than twice the marching step.
        let ray = Ray { origin: Vec3::new(0.0, 0.0, 4e6), dir: Vec3::new(0.0, 0.0, -1.0) };
        let s = g.segments(&ray, 4e6 - 1.0, 4e6 + 1.0);
        assert!(s.length() > 0.0 && s.length() <= 2.0, "{s:?}");
    }

    #[test]
    fn before_warm_up_everything_is_sampled() {
        let g = OccupancyGrid::new(OccupancyConfig::default(), unit());
        let ray = Ray { origin: Vec3::new(-3.0, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
        assert_eq!(g.segments(&ray, 2.0, 4.0), Segments::single(2.0, 4.0));
    }
}
