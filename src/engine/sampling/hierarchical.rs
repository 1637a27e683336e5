//! The classic model's samples, placed along the occupied part of each ray:
//! a ray's occupied segments are laid end to end as "occupied length" `s` in
//! `[0, length]`, stratified coarse samples and inverse-CDF fine samples are
//! drawn in `s`, and each is mapped back to a distance `t` along the ray.
//! Every sample stands for its interval in `s` (`stratified::deltas`), so
//! skipped empty space counts for nothing.

use super::occupancy::{OccupancyGrid, Segments};
use super::stratified::{deltas, edges, merge_sorted, sample_pdf, stratified};
use super::{RaySampler, Samples};
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::rng::Rng;

/// A ray with something to sample: its occupied segments.
pub struct SegmentRay {
    pub ray: Ray,
    segs: Segments,
    /// Occupied length.
    length: f32,
}

impl SegmentRay {
    /// The occupied part of model-space `ray` inside the scene box (all of
    /// it without a grid), or `None` when it has nothing to sample.
    pub fn new(scene: &Scene, grid: Option<&OccupancyGrid>, ray: &Ray) -> Option<Self> {
        let (t0, t1) = scene.clip(ray)?;
        let segs = match grid {
            Some(g) => g.segments(ray, t0, t1),
            None => Segments::single(t0, t1),
        };
        let length = segs.length();
        (length > 0.0).then_some(Self { ray: *ray, segs, length })
    }
}

/// `n` stratified occupied lengths per ray (jittered with the ray's `rngs`
/// entry, at bin centres without one).
pub fn coarse(rays: &[SegmentRay], n: usize, rngs: &mut [Option<Rng>]) -> Vec<Vec<f32>> {
    rays.iter()
        .zip(rngs.iter_mut())
        .map(|(h, r)| {
            let mut s = Vec::new();
            stratified(0.0, h.length, n, r.as_mut(), &mut s);
            s
        })
        .collect()
}

/// Each ray's samples `s` merged with `n` more drawn from the compositing
/// `weights` of those samples (packed, one span per ray in `spans`).
pub fn fine(
    rays: &[SegmentRay],
    s: &[Vec<f32>],
    spans: &[(usize, usize)],
    weights: &[f32],
    n: usize,
    rngs: &mut [Option<Rng>],
) -> Vec<Vec<f32>> {
    let (mut ed, mut drawn) = (Vec::new(), Vec::new());
    rays.iter()
        .zip(s)
        .zip(spans)
        .zip(rngs.iter_mut())
        .map(|(((h, s), &(o, k)), rng)| {
            edges(s, 0.0, h.length, &mut ed);
            drawn.clear();
            sample_pdf(&ed, &weights[o..o + k], n, rng.as_mut(), &mut drawn);
            let mut merged = Vec::new();
            merge_sorted(s, &drawn, &mut merged);
            merged
        })
        .collect()
}

/// Packs samples `s` of each ray into `out`, one span per ray.
pub fn pack(rays: &[SegmentRay], s: &[Vec<f32>], out: &mut Samples) {
    out.clear();
    let mut delta = Vec::new();
    for (h, s) in rays.iter().zip(s) {
        let start = out.len();
        deltas(s, 0.0, h.length, &mut delta);
        for (&si, &d) in s.iter().zip(&delta) {
            out.push(&h.ray, h.segs.to_t(si), d);
        }
        out.end_span(start);
    }
}

/// Samples already drawn, handed out in rounds (for rendering).
pub struct Drawn<'a> {
    rays: &'a [SegmentRay],
    s: &'a [Vec<f32>],
    delta: Vec<Vec<f32>>,
    next: Vec<usize>,
}

impl<'a> Drawn<'a> {
    pub fn new(rays: &'a [SegmentRay], s: &'a [Vec<f32>]) -> Self {
        let delta = rays
            .iter()
            .zip(s)
            .map(|(h, s)| {
                let mut d = Vec::new();
                deltas(s, 0.0, h.length, &mut d);
                d
            })
            .collect();
        Self { rays, s, delta, next: vec![0; s.len()] }
    }
}

impl RaySampler for Drawn<'_> {
    fn has_samples(&self, r: usize) -> bool {
        !self.s[r].is_empty()
    }

    fn next(&mut self, r: usize, limit: usize, out: &mut Samples) -> bool {
        let (h, s) = (&self.rays[r], &self.s[r]);
        let end = (self.next[r] + limit).min(s.len());
        for j in self.next[r]..end {
            out.push(&h.ray, h.segs.to_t(s[j]), self.delta[r][j]);
        }
        self.next[r] = end;
        end < s.len()
    }
}
