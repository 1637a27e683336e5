//! The grid's backward pass deferred and split by level. A training step
//! runs its rays on every thread, each thread adding its gradients into a
//! buffer of its own, and the buffers are then summed. The main grid's
//! table is most of the parameters (capture-360: 6.9M of 7.2M), so most of
//! that sum is its table. Instead, each thread *records* the points and
//! output gradients of its grid backward passes ([`HashGrid::record`]);
//! after the threads are done, [`HashGrid::scatter`] adds every record into
//! one buffer, one level per task (the levels' tables do not overlap), and
//! the other threads' buffers stay zero over the table. The trainer goes
//! one step further ([`HashGrid::prepare_scatter`], [`Scatter::level`]):
//! each level's gradient goes into a buffer of the thread's, small enough
//! to stay in cache, and into that level's Adam update at once.
//!
//! Each recorded pass is scattered exactly as [`HashGrid::backward`] would
//! have (its whole groups of 8 points by the AVX2 path, the rest by the
//! scalar one), in the order recorded: one thread's records give its
//! buffer bit for bit. Across threads the table's sums are taken in
//! another order than a sum of per-thread buffers (a rounding difference).

use rayon::prelude::*;

use super::{FEATURES, HashGrid, sanitize};

/// The inputs of grid backward passes whose scatter is deferred: the
/// points (clamped as [`HashGrid::backward`] clamps them) and the output
/// gradients, pass after pass.
#[derive(Debug, Default, Clone)]
pub struct GridRecord {
    pts: Vec<f32>,
    dout: Vec<f32>,
    /// Points of each recorded pass.
    passes: Vec<usize>,
}

impl GridRecord {
    /// Forgets every pass (the buffers keep their capacity).
    pub fn clear(&mut self) {
        self.pts.clear();
        self.dout.clear();
        self.passes.clear();
    }

    /// Points recorded, over all passes.
    pub fn points(&self) -> usize {
        self.passes.iter().sum()
    }

    /// Whether every recorded output gradient is finite (the points are
    /// clamped when recorded, so they are): the table gradients they
    /// scatter into are then finite too, short of an overflow.
    pub fn finite(&self) -> bool {
        crate::engine::nn::all_finite(&self.dout)
    }
}

impl HashGrid {
    /// Records the backward pass of `pts` (`[n x 3]`) with output gradients
    /// `dout` (`[>= n x width]`, its first `n` rows read) into `record`,
    /// for [`HashGrid::scatter`] to add into the table's gradient.
    pub fn record(&self, pts: &[f32], dout: &[f32], record: &mut GridRecord) {
        let n = pts.len() / 3;
        record.pts.extend(pts[..3 * n].iter().map(|&v| sanitize(v)));
        record.dout.extend_from_slice(&dout[..n * self.width()]);
        record.passes.push(n);
    }

    /// Adds the table gradients of every pass of `records` into `grads`
    /// (which must hold the grid's parameter range), the levels in
    /// parallel. The same as calling [`HashGrid::backward`] on each pass in
    /// order, up to the order in which an entry's terms are summed (none:
    /// the same bits, with one record).
    pub fn scatter(&self, records: &[GridRecord], grads: &mut [f32]) {
        assert!(grads.len() >= self.params.end, "hash grid: gradient buffer too short");
        // Each level's slice of the table's gradient, in layout order.
        let mut rest = &mut grads[self.params.clone()];
        let mut tables = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            let (table, tail) = rest.split_at_mut(FEATURES * level.size);
            tables.push(table);
            rest = tail;
        }
        let scatter = self.prepare_scatter(records);
        tables.into_par_iter().enumerate().for_each(|(l, table)| scatter.level(l, table));
    }

    /// `records` ready to be scattered one level at a time
    /// ([`Scatter::level`]), for a caller that uses each level's gradient
    /// as soon as it is complete (the trainer's Adam update).
    pub fn prepare_scatter<'a>(&'a self, records: &'a [GridRecord]) -> Scatter<'a> {
        let width = self.width();
        // Every pass's slices, and its points in vector form once for all levels.
        let mut passes = Vec::new();
        for r in records {
            let mut at = 0;
            for &n in &r.passes {
                let pts = &r.pts[3 * at..3 * (at + n)];
                let dout = &r.dout[at * width..(at + n) * width];
                passes.push(Pass::new(pts, dout));
                at += n;
            }
        }
        Scatter { grid: self, passes }
    }

    /// Each level's range of the parameter buffer, in layout order (they
    /// tile [`HashGrid::params`]).
    pub fn level_ranges(&self) -> Vec<std::ops::Range<usize>> {
        self.levels
            .iter()
            .map(|l| self.params.start + l.offset..self.params.start + l.offset + FEATURES * l.size)
            .collect()
    }
}

/// Records prepared by [`HashGrid::prepare_scatter`].
pub struct Scatter<'a> {
    grid: &'a HashGrid,
    passes: Vec<Pass<'a>>,
}

impl Scatter<'_> {
    /// Adds level `l`'s gradient from every recorded pass, in order, into
    /// `table`: the level's slice of a gradient buffer
    /// ([`HashGrid::level_ranges`]`[l]`'s length).
    pub fn level(&self, l: usize, table: &mut [f32]) {
        let grid = self.grid;
        let (level, width) = (&grid.levels[l], grid.width());
        assert_eq!(table.len(), FEATURES * level.size, "hash grid: a level's gradient of another size");
        let base = grid.params.start + level.offset;
        for p in &self.passes {
            let done = p.scatter_simd(level, l, table, width);
            let (pts, dout) = (&p.pts[3 * done..], &p.dout[done * width..]);
            if level.dense {
                grid.backward_level::<true>(l, level, pts, dout, table, base);
            } else {
                grid.backward_level::<false>(l, level, pts, dout, table, base);
            }
        }
    }
}

/// One recorded pass, with its whole groups of 8 points as coordinate
/// arrays when the CPU has AVX2 and FMA.
struct Pass<'a> {
    pts: &'a [f32],
    dout: &'a [f32],
    #[cfg(target_arch = "x86_64")]
    soa: Option<super::simd::Soa>,
}

impl<'a> Pass<'a> {
    fn new(pts: &'a [f32], dout: &'a [f32]) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            let soa =
                crate::engine::nn::gemm::has_avx2_fma().then(|| super::simd::Soa::new(&pts[..pts.len() / 24 * 24]));
            Pass { pts, dout, soa }
        }
        #[cfg(not(target_arch = "x86_64"))]
        Pass { pts, dout }
    }

    /// The AVX2 scatter of the whole groups of 8 points into `table` (level
    /// `l`'s slice); returns how many points it handled (0 without AVX2).
    fn scatter_simd(&self, level: &super::Level, l: usize, table: &mut [f32], width: usize) -> usize {
        #[cfg(target_arch = "x86_64")]
        if let Some(soa) = &self.soa {
            // SAFETY: AVX2 and FMA are available (`soa` exists only then);
            // `table` is the level's whole table (index 0 its first entry),
            // and `dout` has a row per point.
            unsafe {
                if level.dense {
                    super::simd::backward_level::<true>(level, 0, l, soa, self.dout, table, width);
                } else {
                    super::simd::backward_level::<false>(level, 0, l, soa, self.dout, table, width);
                }
            }
            return self.pts.len() / 24 * 8;
        }
        let _ = (level, l, table, width);
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::nn::hashgrid::HashGridConfig;
    use crate::engine::nn::linear::ParamLayout;
    use crate::engine::rng::Rng;

    /// Dense coarse levels and hashed fine ones, after other parameters.
    fn grid() -> (HashGrid, usize) {
        let mut layout = ParamLayout::default();
        layout.add("before", 5);
        let g = HashGrid::new(
            &mut layout,
            HashGridConfig { levels: 5, log2_table: 8, base_resolution: 2, finest_resolution: 40 },
        );
        layout.add("after", 3);
        (g, layout.len)
    }

    /// `n` points (some outside the cube, one NaN) and their output
    /// gradients (every third row zero, as a culled sample's).
    fn pass(g: &HashGrid, rng: &mut Rng, n: usize) -> (Vec<f32>, Vec<f32>) {
        let mut pts: Vec<f32> = (0..3 * n).map(|_| rng.f32() * 1.2 - 0.1).collect();
        if n > 5 {
            pts[7] = f32::NAN;
        }
        let dout = (0..n * g.width()).map(|i| if (i / g.width()) % 3 == 2 { 0.0 } else { rng.f32() - 0.5 }).collect();
        (pts, dout)
    }

    #[test]
    fn one_record_gives_the_backward_passes_bit_for_bit() {
        let (g, len) = grid();
        let mut rng = Rng::new(3);
        // Whole groups of 8 and tails, and an empty pass.
        let passes: Vec<_> = [37, 8, 3, 64, 0, 21].iter().map(|&n| pass(&g, &mut rng, n)).collect();
        let mut direct = vec![0.0f32; len];
        let mut record = GridRecord::default();
        for (pts, dout) in &passes {
            g.backward(pts, dout, &mut direct);
            g.record(pts, dout, &mut record);
        }
        assert_eq!(record.points(), 37 + 8 + 3 + 64 + 21);
        let mut deferred = vec![0.0f32; len];
        g.scatter(std::slice::from_ref(&record), &mut deferred);
        assert!(direct.iter().filter(|v| **v != 0.0).count() > 100, "the passes reach many entries");
        for (i, (a, b)) in direct.iter().zip(&deferred).enumerate() {
            assert_eq!(a.to_bits(), b.to_bits(), "entry {i}");
        }
        assert!(deferred[..g.params.start].iter().chain(&deferred[g.params.end..]).all(|v| *v == 0.0));
        record.clear();
        assert_eq!(record.points(), 0);
        let mut none = vec![0.0f32; len];
        g.scatter(&[record], &mut none);
        assert!(none.iter().all(|v| *v == 0.0), "a cleared record adds nothing");
    }

    #[test]
    fn records_of_several_parts_add_what_their_buffers_sum_to() {
        let (g, len) = grid();
        let mut rng = Rng::new(8);
        let mut records = vec![GridRecord::default(); 3];
        let mut buffers = vec![vec![0.0f32; len]; 3];
        for (record, buffer) in records.iter_mut().zip(&mut buffers) {
            for n in [29, 16] {
                let (pts, dout) = pass(&g, &mut rng, n);
                g.backward(&pts, &dout, buffer);
                g.record(&pts, &dout, record);
            }
        }
        // Added to what the buffer holds already (the other parameters').
        let start: Vec<f32> = (0..len).map(|i| (i % 7) as f32 * 0.25).collect();
        let mut deferred = start.clone();
        g.scatter(&records, &mut deferred);
        let scale = buffers.iter().flatten().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(scale > 0.1);
        for i in 0..len {
            let sum = start[i] + buffers[0][i] + buffers[1][i] + buffers[2][i];
            assert!((deferred[i] - sum).abs() <= 1e-5 * scale, "entry {i}: {} against {sum}", deferred[i]);
        }
    }

    #[test]
    fn level_ranges_tile_the_table_and_each_level_scatters_its_slice() {
        let (g, len) = grid();
        let ranges = g.level_ranges();
        assert_eq!(ranges.first().unwrap().start, g.params.start);
        assert_eq!(ranges.last().unwrap().end, g.params.end);
        assert!(ranges.windows(2).all(|w| w[0].end == w[1].start));
        let mut rng = Rng::new(4);
        let mut record = GridRecord::default();
        for n in [37, 8, 21] {
            let (pts, dout) = pass(&g, &mut rng, n);
            g.record(&pts, &dout, &mut record);
        }
        let records = [record];
        let mut whole = vec![0.0f32; len];
        g.scatter(&records, &mut whole);
        let scatter = g.prepare_scatter(&records);
        for (l, r) in ranges.iter().enumerate() {
            // Into a buffer of the level's own: the same bits; one holding
            // values already: added to them.
            let mut own = vec![0.0f32; r.len()];
            scatter.level(l, &mut own);
            let mut held = vec![0.5f32; r.len()];
            scatter.level(l, &mut held);
            for (i, ((a, h), b)) in own.iter().zip(&held).zip(&whole[r.clone()]).enumerate() {
                assert_eq!(a.to_bits(), b.to_bits(), "level {l} entry {i}");
                assert!((h - 0.5 - b).abs() <= 1e-6, "level {l} entry {i}: {h} against 0.5 + {b}");
            }
        }
    }

    #[test]
    fn a_record_is_finite_when_its_output_gradients_are() {
        let (g, _) = grid();
        let mut rng = Rng::new(6);
        // `pass` puts a NaN among the points: clamped, it does not count.
        let (pts, dout) = pass(&g, &mut rng, 19);
        assert!(pts.iter().any(|v| v.is_nan()));
        let mut record = GridRecord::default();
        g.record(&pts, &dout, &mut record);
        assert!(record.finite());
        for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            for at in [0, 7 * g.width() + 3, 19 * g.width() - 1] {
                let mut d = dout.clone();
                d[at] = bad;
                let mut r = record.clone();
                g.record(&pts, &d, &mut r);
                assert!(!r.finite(), "{bad} at {at}");
            }
        }
        assert!(GridRecord::default().finite());
    }
}
