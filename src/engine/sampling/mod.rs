//! Where along a ray to evaluate a field. Every sampler writes the same
//! packed layout, [`Samples`]: the samples of many rays in one flat list,
//! each ray's run of them named by a span (nerfacc's packed samples).
//!
//! - [`stratified`]: stratified samples and inverse-CDF samples of a
//!   piecewise-constant density (the classic model's coarse and fine passes),
//! - [`hierarchical`]: those placed along the occupied part of each ray and
//!   handed out in rounds,
//! - [`occupancy`]: the grid of cells that may hold density,
//! - [`marcher`]: constant steps through the occupied cells (the fast model),
//! - [`proposal`]: the ray-distance warp, stratified and inverse-CDF interval
//!   edges and the final samples of proposal sampling (unbounded scenes).

pub mod hierarchical;
pub mod marcher;
pub mod occupancy;
pub mod proposal;
pub mod stratified;

use crate::engine::geometry::math::Ray;
use crate::engine::nn::gather_rows;

/// Samples of a batch of rays, packed flat: `n` samples in all.
#[derive(Default, Debug)]
pub struct Samples {
    /// Per ray that has samples: its first sample and their count. Which ray
    /// a span belongs to is the caller's (the render loop keeps owners).
    pub spans: Vec<(usize, usize)>,
    /// Distance along the ray, `[n]`, increasing within a span.
    pub t: Vec<f32>,
    /// Length of the interval the sample stands for, `[n]`.
    pub delta: Vec<f32>,
    /// Position in model space, `[n x 3]`.
    pub pos: Vec<f32>,
    /// The ray's direction, `[n x 3]`.
    pub dirs: Vec<f32>,
    /// Samples a dense sampler would have taken that this one skipped.
    pub skipped: u64,
}

impl Samples {
    pub fn clear(&mut self) {
        self.spans.clear();
        self.t.clear();
        self.delta.clear();
        self.pos.clear();
        self.dirs.clear();
        self.skipped = 0;
    }

    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// Appends the sample of `ray` at `t` standing for an interval `delta`.
    #[inline]
    pub fn push(&mut self, ray: &Ray, t: f32, delta: f32) {
        let p = ray.at(t);
        self.t.push(t);
        self.delta.push(delta);
        self.pos.extend_from_slice(&[p.x, p.y, p.z]);
        self.dirs.extend_from_slice(&[ray.dir.x, ray.dir.y, ray.dir.z]);
    }

    /// Closes the span of the samples pushed since `start`.
    pub fn end_span(&mut self, start: usize) {
        self.spans.push((start, self.len() - start));
    }

    /// Keeps samples `keep` (sorted indices), updating each span.
    pub fn compact(&mut self, keep: &[usize]) {
        let mut j = 0;
        for span in &mut self.spans {
            let (o, k) = *span;
            let start = j;
            while j < keep.len() && keep[j] < o + k {
                j += 1;
            }
            *span = (start, j - start);
        }
        gather_rows(&mut self.t, 1, keep);
        gather_rows(&mut self.delta, 1, keep);
        gather_rows(&mut self.pos, 3, keep);
        gather_rows(&mut self.dirs, 3, keep);
    }
}

/// A sampler that hands out each ray's samples in order, a few at a time, so
/// the render loop can stop a ray once it is opaque.
pub trait RaySampler {
    /// Whether ray `r` has any sample.
    fn has_samples(&self, r: usize) -> bool;
    /// Appends up to `limit` further samples of ray `r` to `out`; returns
    /// whether the ray may have more after them.
    fn next(&mut self, r: usize, limit: usize, out: &mut Samples) -> bool;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::math::Vec3;

    #[test]
    fn compact_keeps_rows_and_spans_together() {
        let ray = Ray { origin: Vec3::new(0.0, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
        let mut s = Samples::default();
        for r in 0..3 {
            let start = s.len();
            for k in 0..3 {
                s.push(&ray, (10 * r + k) as f32, 0.5);
            }
            s.end_span(start);
        }
        s.compact(&[1, 2, 6, 8]);
        assert_eq!(s.spans, vec![(0, 2), (2, 0), (2, 2)]);
        assert_eq!(s.t, vec![1.0, 2.0, 20.0, 22.0]);
        assert_eq!(s.pos, vec![1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 20.0, 0.0, 0.0, 22.0, 0.0, 0.0]);
        assert_eq!(s.dirs.len(), 12);
    }
}
