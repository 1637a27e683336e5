//! The parts of proposal sampling (mip-NeRF 360, nerfacto; design
//! `real-captures.md` 2.4), for rays through unbounded scenes:
//!
//! - [`Warp`]: the normalised ray distance `s` in `[0, 1]`, linear in `t`
//!   inside the unit cube (where the scene's focus is) and linear in
//!   disparity `1/t` beyond it, so samples spread evenly over both;
//! - [`stratified_edges`]: the first level's intervals, equal in `s`;
//! - [`EdgeSampler::pdf_edges`]: the next level's intervals, drawn from the
//!   weights a proposal field gave the previous ones;
//! - [`Anneal`]: how sharply those weights are followed as training goes;
//! - [`RayEdges`], [`ProposalRays`], [`pack`]: the final intervals of a batch
//!   of rays, turned into samples for the render loop or a training pass.
//!
//! A ray's intervals are given by their edges: `n + 1` sorted values for
//! `n` intervals, sharing edges, so they tile the ray. Each interval is
//! sampled at its midpoint in `t`, standing for its length `t_{j+1} - t_j`.
//! Both random draws take one value per ray and level ("single jitter"),
//! from the ray's stream `Rng::stream(seed, step, ray index)` as the other
//! samplers' draws do; without a generator they sit at bin centres (for
//! rendering).

use super::stratified::{invert_cdf, pdf_cdf};
use super::{RaySampler, Samples};
use crate::engine::geometry::math::{Aabb, Ray, Vec3};
use crate::engine::rng::Rng;

/// Why a proposal-sampling part refused its inputs.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ProposalError {
    #[error("ray interval near {near}, knee {knee}, far {far}: need finite 0 < near < far and a knee that is a number")]
    Bounds { near: f32, knee: f32, far: f32 },
    #[error("at least one interval is needed")]
    NoIntervals,
    #[error("{what} has {got} values, expected {expected}")]
    Length { what: &'static str, expected: usize, got: usize },
    #[error("{what}: value {index} ({value}) is not finite or is below the one before it")]
    Unsorted { what: &'static str, index: usize, value: f32 },
    #[error("resampling exponent {exponent} and padding {padding} must be finite and non-negative")]
    Resampling { exponent: f32, padding: f32 },
    #[error("anneal slope {0} must be finite and positive")]
    Slope(f32),
}

fn check_sorted(what: &'static str, v: &[f32]) -> Result<(), ProposalError> {
    let mut prev = f32::NEG_INFINITY;
    for (index, &value) in v.iter().enumerate() {
        if !(value.is_finite() && value >= prev) {
            return Err(ProposalError::Unsorted { what, index, value });
        }
        prev = value;
    }
    Ok(())
}

/// The ray-distance warp of one ray: `s(t)` in `[0, 1]` for `t` in
/// `[near, far]`, from nerfstudio's `UniformLinDispPiecewiseSampler` and
/// multinerf's piecewise warp, with the knee where the ray leaves the unit
/// cube `[-1, 1]^3` (where a scene contraction starts compressing):
/// `g(t) = (t - near) / (2 (knee - near))` up to the knee, then
/// `g(t) = 1 - knee / (2t)` (linear in disparity); both are 1/2 at the knee,
/// so `g` is continuous and increasing. `s = (g(t) - g(near)) / (g(far) -
/// g(near))`, so `s(near) = 0` and `s(far) = 1`. A ray that misses the cube
/// has its knee at `near`: all of it is linear in disparity. Computed in
/// f64.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Warp {
    near: f64,
    knee: f64,
    far: f64,
    g_near: f64,
    g_far: f64,
}

impl Warp {
    /// The warp of `[near, far]` with its knee at `knee` (clamped into
    /// `[near, far]`); `near` must be positive, since `1/t` beyond the knee
    /// needs `t > 0`.
    pub fn new(near: f32, knee: f32, far: f32) -> Result<Self, ProposalError> {
        let ok = near.is_finite() && far.is_finite() && near > 0.0 && near < far && !knee.is_nan();
        if !ok {
            return Err(ProposalError::Bounds { near, knee, far });
        }
        let (near, far) = (near as f64, far as f64);
        let knee = (knee as f64).clamp(near, far);
        let mut w = Self { near, knee, far, g_near: 0.0, g_far: 1.0 };
        w.g_near = w.g(near);
        w.g_far = w.g(far);
        Ok(w)
    }

    /// The warp of model-space `ray` over `[near, far]`, its knee where the
    /// ray leaves the unit cube (at `near` when it misses the cube or is not
    /// finite).
    pub fn for_ray(ray: &Ray, near: f32, far: f32) -> Result<Self, ProposalError> {
        let cube = Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) };
        let finite = ray.origin.is_finite() && ray.dir.is_finite();
        let knee = if finite { cube.clip(ray, near, far).map_or(near, |(_, exit)| exit) } else { near };
        Self::new(near, knee, far)
    }

    /// Where the warp turns from linear in distance to linear in disparity.
    pub fn knee(&self) -> f32 {
        self.knee as f32
    }

    fn g(&self, t: f64) -> f64 {
        if t <= self.knee && self.knee > self.near {
            (0.5 * (t - self.near) / (self.knee - self.near)).min(0.5)
        } else {
            (1.0 - 0.5 * self.knee / t).max(0.5)
        }
    }

    /// `s(t)`; `t` is clamped into `[near, far]` first (NaN stays NaN).
    pub fn to_s(&self, t: f32) -> f32 {
        if t.is_nan() {
            return f32::NAN;
        }
        let t = (t as f64).clamp(self.near, self.far);
        ((self.g(t) - self.g_near) / (self.g_far - self.g_near)).clamp(0.0, 1.0) as f32
    }

    /// The inverse, `t(s)`; `s` is clamped into `[0, 1]` first (NaN stays
    /// NaN).
    pub fn to_t(&self, s: f32) -> f32 {
        if s.is_nan() {
            return f32::NAN;
        }
        if s <= 0.0 {
            return self.near as f32;
        }
        if s >= 1.0 {
            return self.far as f32;
        }
        let v = self.g_near + s as f64 * (self.g_far - self.g_near);
        let t = if v <= 0.5 && self.knee > self.near {
            (self.near + 2.0 * v * (self.knee - self.near)).min(self.knee)
        } else {
            (0.5 * self.knee / (1.0 - v)).max(self.knee)
        };
        t.clamp(self.near, self.far) as f32
    }

    /// Appends `t(s)` of each of `s` to `out`.
    pub fn t_edges(&self, s: &[f32], out: &mut Vec<f32>) {
        out.extend(s.iter().map(|&s| self.to_t(s)));
    }
}

/// Appends the `n + 1` edges of `n` stratified intervals of `[0, 1]`: 0,
/// then `(k - 1/2 + r) / n` for `k = 1 .. n - 1`, then 1, with one jitter
/// `r` in `[0, 1)` for the whole ray drawn from `rng` (`r = 1/2` without
/// one: `n` equal intervals). The inner intervals are `1/n` long; the first
/// and last share the rest.
pub fn stratified_edges(n: usize, rng: Option<&mut Rng>, out: &mut Vec<f32>) -> Result<(), ProposalError> {
    if n == 0 {
        return Err(ProposalError::NoIntervals);
    }
    let r = rng.map_or(0.5, |r| r.f32());
    out.push(0.0);
    out.extend((1..n).map(|k| (k as f32 - 0.5 + r) / n as f32));
    out.push(1.0);
    Ok(())
}

/// How a histogram's weights become the density that new edges are drawn
/// from: bin `j` gets mass `w_j^exponent + padding` (nerfacto's annealed
/// weights and `histogram_padding`). The exponent ([`Anneal`]) flattens the
/// weights early in training (0: every bin alike); the padding keeps every
/// bin reachable, so a proposal that missed a surface can still find it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Resampling {
    exponent: f32,
    padding: f32,
}

impl Resampling {
    pub fn new(exponent: f32, padding: f32) -> Result<Self, ProposalError> {
        let ok = exponent.is_finite() && exponent >= 0.0 && padding.is_finite() && padding >= 0.0;
        ok.then_some(Self { exponent, padding }).ok_or(ProposalError::Resampling { exponent, padding })
    }
}

/// Draws interval edges from a histogram, keeping its CDF buffer from ray
/// to ray (one per thread).
#[derive(Debug, Default)]
pub struct EdgeSampler {
    cdf: Vec<f32>,
}

impl EdgeSampler {
    /// Appends `n + 1` sorted edges drawn from the histogram with sorted
    /// `edges` (`[m + 1]`) and `weights` (`[m]`, negative or non-finite
    /// ones count as 0), weighted as `how` says: the first and last are
    /// `edges[0]` and `edges[m]`, the others the points where the CDF
    /// reaches `(k - 1/2 + r) / n` for `k = 1 .. n - 1`, one jitter `r` for
    /// the ray from `rng` (1/2 without one: the quantiles `k / n`). On a
    /// uniform histogram of `[0, 1]` these are [`stratified_edges`].
    pub fn pdf_edges(
        &mut self,
        edges: &[f32],
        weights: &[f32],
        n: usize,
        how: Resampling,
        rng: Option<&mut Rng>,
        out: &mut Vec<f32>,
    ) -> Result<(), ProposalError> {
        let m = weights.len();
        if m == 0 || n == 0 {
            return Err(ProposalError::NoIntervals);
        }
        if edges.len() != m + 1 {
            return Err(ProposalError::Length { what: "edges", expected: m + 1, got: edges.len() });
        }
        check_sorted("edges", edges)?;
        let r = rng.map_or(0.5, |r| r.f32());
        pdf_cdf(weights, how.exponent, how.padding, &mut self.cdf);
        out.push(edges[0]);
        invert_cdf(edges, &self.cdf, (1..n).map(|k| (k as f32 - 0.5 + r) / n as f32), out);
        out.push(edges[m]);
        Ok(())
    }
}

/// The annealing of the resampling exponent (nerfacto's proposal weights
/// annealing): with `x = min(1, step / steps)`, the exponent is
/// `b x / ((b - 1) x + 1)` for slope `b`, rising from 0 (the proposals'
/// untrained weights are ignored) to 1 at `steps`, fast at first for
/// `b > 1`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anneal {
    steps: u64,
    slope: f32,
}

impl Anneal {
    /// `steps = 0` anneals nothing (the exponent is always 1).
    pub fn new(steps: u64, slope: f32) -> Result<Self, ProposalError> {
        (slope.is_finite() && slope > 0.0).then_some(Self { steps, slope }).ok_or(ProposalError::Slope(slope))
    }

    /// The exponent at training step `step`.
    pub fn exponent(&self, step: u64) -> f32 {
        if step >= self.steps {
            return 1.0;
        }
        let x = step as f64 / self.steps as f64;
        let b = self.slope as f64;
        (b * x / ((b - 1.0) * x + 1.0)) as f32
    }
}

/// The interval edges in `t` of a batch of rays, packed: ray `r`'s are
/// `t[o..o + k]` for `spans[r] = (o, k)`. A ray with fewer than two edges
/// has no interval.
#[derive(Clone, Debug, Default)]
pub struct RayEdges {
    spans: Vec<(usize, usize)>,
    t: Vec<f32>,
}

impl RayEdges {
    pub fn clear(&mut self) {
        self.spans.clear();
        self.t.clear();
    }

    /// Adds the next ray's edges, which must be finite and sorted.
    pub fn push(&mut self, edges: &[f32]) -> Result<(), ProposalError> {
        check_sorted("ray edges", edges)?;
        self.spans.push((self.t.len(), edges.len()));
        self.t.extend_from_slice(edges);
        Ok(())
    }

    /// Number of rays.
    pub fn rays(&self) -> usize {
        self.spans.len()
    }

    /// Ray `r`'s edges (empty for a ray out of range).
    pub fn ray(&self, r: usize) -> &[f32] {
        self.spans.get(r).map_or(&[], |&(o, k)| &self.t[o..o + k])
    }

    /// Number of intervals of ray `r`.
    fn intervals(&self, r: usize) -> usize {
        self.ray(r).len().saturating_sub(1)
    }
}

/// Appends the sample of interval `[a, b]` of `ray`: at its midpoint,
/// standing for its length (or for `delta` when given).
#[inline]
fn push_interval(ray: &Ray, a: f32, b: f32, delta: Option<f32>, out: &mut Samples) {
    out.push(ray, 0.5 * (a + b), delta.unwrap_or(b - a));
}

fn check_rays(rays: &[Ray], edges: &RayEdges) -> Result<(), ProposalError> {
    if rays.len() == edges.rays() {
        Ok(())
    } else {
        Err(ProposalError::Length { what: "ray edges", expected: rays.len(), got: edges.rays() })
    }
}

/// Packs one sample per interval of every ray into `out` (cleared), one
/// span per ray in order (empty for a ray without intervals), as a training
/// pass takes them. Lengths are the intervals' own; an opaque last interval
/// is the compositor's option (`composite::CompositeOptions::opaque_last`).
pub fn pack(rays: &[Ray], edges: &RayEdges, out: &mut Samples) -> Result<(), ProposalError> {
    check_rays(rays, edges)?;
    out.clear();
    for (r, ray) in rays.iter().enumerate() {
        let start = out.len();
        for w in edges.ray(r).windows(2) {
            push_interval(ray, w[0], w[1], None, out);
        }
        out.end_span(start);
    }
    Ok(())
}

/// The final samples of a batch of rays, handed to the render loop
/// (`render::rounds::render_in_rounds`) a few at a time, so rays stop once
/// they are opaque.
pub struct ProposalRays<'a> {
    rays: &'a [Ray],
    edges: &'a RayEdges,
    opaque_last: bool,
    next: Vec<usize>,
}

impl<'a> ProposalRays<'a> {
    /// Samples of `rays` (model space) over their `edges` (one run per
    /// ray). With `opaque_last`, each ray's last interval stands for an
    /// infinite length, so any density there makes it opaque exactly as
    /// `composite` with `opaque_last` composites it (the render loop
    /// knows no options; a zero density there stays transparent).
    pub fn new(rays: &'a [Ray], edges: &'a RayEdges, opaque_last: bool) -> Result<Self, ProposalError> {
        check_rays(rays, edges)?;
        Ok(Self { rays, edges, opaque_last, next: vec![0; rays.len()] })
    }
}

impl RaySampler for ProposalRays<'_> {
    fn has_samples(&self, r: usize) -> bool {
        self.edges.intervals(r) > 0
    }

    fn next(&mut self, r: usize, limit: usize, out: &mut Samples) -> bool {
        let (Some(ray), Some(next)) = (self.rays.get(r), self.next.get_mut(r)) else {
            return false;
        };
        let e = self.edges.ray(r);
        let n = e.len().saturating_sub(1);
        let end = (*next + limit).min(n);
        for j in *next..end {
            let delta = (self.opaque_last && j + 1 == n).then_some(f32::INFINITY);
            push_interval(ray, e[j], e[j + 1], delta, out);
        }
        *next = end;
        end < n
    }
}

#[cfg(test)]
#[path = "proposal_tests.rs"]
mod tests;
