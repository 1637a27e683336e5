//! Where the real-capture model samples a ray (design `real-captures.md`
//! 2.4): proposal sampling over the ray-distance warp `s`
//! (`sampling::proposal::Warp`). Level 0 is stratified in `s`; each
//! proposal network's densities along its level give weights, and the next
//! level's intervals are drawn from them; the last level's intervals are
//! the main field's samples. Training and rendering walk the levels with
//! the same code ([`Levels::place`]); they differ in where the edges go
//! ([`Placement`]): jittered once per ray and level in training, at bin
//! centres when rendering, and replayed from a record in the tests that
//! freeze sample positions.
//!
//! Each proposal level's weights are composited with an opaque last
//! interval, as the main field's are (photographs have no see-through
//! pixels), so every level's weights sum to 1 along a ray that reaches its
//! end.

use crate::engine::fields::proposal::{ProposalCtx, ProposalField};
use crate::engine::geometry::math::Ray;
use crate::engine::nn::hashgrid::HalfTable;
use crate::engine::render::InputError;
use crate::engine::render::composite::{CompositeOptions, RaySamples, Transmittance, composite};
use crate::engine::rng::Rng;
use crate::engine::sampling::Samples;
use crate::engine::sampling::proposal::{
    EdgeSampler, ProposalError, RayEdges, Resampling, Warp, pack, stratified_edges,
};

/// Why the levels could not be placed: an edge list or a compositor's
/// input did not fit (a bug of the caller's sizes, reported rather than a
/// panic).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LevelError {
    #[error("placing samples: {0}")]
    Proposal(#[from] ProposalError),
    #[error("compositing a level: {0}")]
    Input(#[from] InputError),
}

/// Where each level's interval edges (in `s`) go.
pub trait Placement {
    /// Starts a chunk of rays; `index[r]` identifies ray `r` (it seeds the
    /// ray's random stream).
    fn start(&mut self, index: &[u64]);
    /// Appends the `n + 1` edges of level 0 of ray `r`.
    fn first(&mut self, r: usize, n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError>;
    /// Appends the `n + 1` edges of the level after one with `edges` and
    /// `weights` (of ray `r`).
    fn next(
        &mut self,
        r: usize,
        edges: &[f32],
        weights: &[f32],
        n: usize,
        out: &mut Vec<f32>,
    ) -> Result<(), ProposalError>;
}

/// The placement of training and rendering: level 0 stratified, the next
/// levels drawn from the weights (`w^exponent + padding`), each with one
/// jitter per ray and level from the ray's stream `Rng::stream(seed, step,
/// index)`, or at bin centres without jitter.
pub struct Drawn {
    how: Resampling,
    jitter: Option<(u64, u64)>,
    rngs: Vec<Rng>,
    sampler: EdgeSampler,
}

impl Drawn {
    /// Jittered edges for training step `step` of a run seeded `seed`.
    pub fn jittered(how: Resampling, seed: u64, step: u64) -> Self {
        Self { how, jitter: Some((seed, step)), rngs: Vec::new(), sampler: EdgeSampler::default() }
    }

    /// Edges at bin centres (rendering).
    pub fn centred(how: Resampling) -> Self {
        Self { how, jitter: None, rngs: Vec::new(), sampler: EdgeSampler::default() }
    }
}

impl Placement for Drawn {
    fn start(&mut self, index: &[u64]) {
        self.rngs.clear();
        if let Some((seed, step)) = self.jitter {
            self.rngs.extend(index.iter().map(|&i| Rng::stream(seed, step, i)));
        }
    }

    fn first(&mut self, r: usize, n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        stratified_edges(n, self.rngs.get_mut(r), out)
    }

    fn next(
        &mut self,
        r: usize,
        edges: &[f32],
        weights: &[f32],
        n: usize,
        out: &mut Vec<f32>,
    ) -> Result<(), ProposalError> {
        self.sampler.pdf_edges(edges, weights, n, self.how, self.rngs.get_mut(r), out)
    }
}

/// One level of a chunk of rays: `n` intervals per ray.
#[derive(Debug, Default)]
pub struct Level {
    /// Intervals per ray.
    pub n: usize,
    /// Edges in `s`, `[rays x (n + 1)]`.
    pub s: Vec<f32>,
    /// The same edges in `t` (model units).
    pub t: RayEdges,
    /// One sample per interval, at its midpoint in `t`: a span of `n` per
    /// ray, in order.
    pub samples: Samples,
    /// Compositing weights `[rays x n]` (proposal levels only, after
    /// [`Levels::place`]).
    pub weights: Vec<f32>,
}

impl Level {
    /// Ray `r`'s edges in `s`.
    pub fn s_of(&self, r: usize) -> &[f32] {
        &self.s[r * (self.n + 1)..(r + 1) * (self.n + 1)]
    }

    /// Ray `r`'s weights.
    pub fn weights_of(&self, r: usize) -> &[f32] {
        &self.weights[r * self.n..(r + 1) * self.n]
    }
}

/// The levels of a chunk of rays and the proposal networks' activations
/// (kept for their backward pass); one per thread, reused.
#[derive(Default)]
pub struct Levels {
    /// The proposal levels, then the final one.
    pub levels: Vec<Level>,
    /// One context per proposal network.
    pub ctxs: Vec<ProposalCtx>,
    /// Zero colours, `[3 x max n]`: proposal levels composite densities only.
    pub zeros: Vec<f32>,
    edges: Vec<f32>,
    /// Transmittance below which a ray's proposal samples further on are
    /// not evaluated (rendering; 0, training's: all are).
    stop_below: f32,
    /// Rendering in rounds: the rays still going, their transmittance so
    /// far, and a round's sample positions.
    active: Vec<usize>,
    along: Vec<Transmittance>,
    round_pos: Vec<f32>,
}

/// Proposal samples per ray evaluated together when rendering stops rays
/// early ([`Levels::set_early_stop`]).
const PROPOSAL_ROUND: usize = 8;

/// How a proposal level's weights are composited.
pub const PROPOSAL_COMPOSITE: CompositeOptions =
    CompositeOptions { background: [0.0; 3], min_transmittance: 0.0, opaque_last: true };

impl Levels {
    /// Places the levels of `rays` (model space; `warps[r]` is ray `r`'s):
    /// `intervals[k]` per ray at level `k`, the last being the final level,
    /// one more than there are `proposals`. Evaluates each proposal network
    /// on its level and composites its weights. Returns the number of
    /// proposal samples evaluated.
    #[allow(clippy::too_many_arguments)]
    pub fn place(
        &mut self,
        proposals: &[ProposalField],
        params: &[f32],
        rays: &[Ray],
        warps: &[Warp],
        intervals: &[usize],
        placement: &mut dyn Placement,
        index: &[u64],
    ) -> Result<u64, LevelError> {
        if intervals.len() != proposals.len() + 1 || warps.len() != rays.len() || index.len() != rays.len() {
            return Err(
                ProposalError::Length { what: "levels", expected: proposals.len() + 1, got: intervals.len() }.into()
            );
        }
        self.levels.resize_with(intervals.len(), Level::default);
        self.ctxs.resize_with(proposals.len(), ProposalCtx::default);
        let widest = intervals.iter().copied().max().unwrap_or(0);
        self.zeros.resize(3 * widest, 0.0);
        placement.start(index);
        let mut evaluated = 0u64;
        for (k, &n) in intervals.iter().enumerate() {
            let (before, rest) = self.levels.split_at_mut(k);
            let level = &mut rest[0];
            level.n = n;
            level.s.clear();
            level.t.clear();
            for (r, warp) in warps.iter().enumerate() {
                let start = level.s.len();
                match before.last() {
                    None => placement.first(r, n, &mut level.s)?,
                    Some(prev) => placement.next(r, prev.s_of(r), prev.weights_of(r), n, &mut level.s)?,
                }
                if level.s.len() != start + n + 1 {
                    let got = level.s.len() - start;
                    return Err(ProposalError::Length { what: "placed edges", expected: n + 1, got }.into());
                }
                self.edges.clear();
                warp.t_edges(&level.s[start..], &mut self.edges);
                level.t.push(&self.edges)?;
            }
            pack(rays, &level.t, &mut level.samples)?;
            let Some(net) = proposals.get(k) else { continue };
            let ctx = &mut self.ctxs[k];
            if self.stop_below > 0.0 {
                let state = (&mut self.active, &mut self.along);
                evaluated += in_rounds(net, params, level, ctx, state, &mut self.round_pos, self.stop_below)?;
            } else {
                net.density(params, &level.samples.pos, ctx);
                evaluated += level.samples.len() as u64;
                level.weights.clear();
                level.weights.resize(rays.len() * n, 0.0);
                let m = &level.samples;
                let sigma = net.sigma(ctx);
                for (r, w) in level.weights.chunks_exact_mut(n.max(1)).enumerate().take(rays.len()) {
                    let (o, len) = m.spans[r];
                    let s = RaySamples::new(
                        &sigma[o..o + len],
                        &self.zeros[..3 * len],
                        &m.t[o..o + len],
                        &m.delta[o..o + len],
                    )?;
                    composite(s, &PROPOSAL_COMPOSITE, w)?;
                }
            }
        }
        Ok(evaluated)
    }

    /// Makes the proposal networks' passes of later [`Levels::place`] calls
    /// read their grids from `tables` (one per network, as
    /// [`ProposalField::half_table`] gives them; `None`: the parameters).
    /// Rendering sets them and clears them (`&[]`) when done; training
    /// never has them.
    pub fn set_render_tables(&mut self, proposals: &[ProposalField], tables: &[Option<std::sync::Arc<HalfTable>>]) {
        self.ctxs.resize_with(proposals.len(), ProposalCtx::default);
        for (k, (net, ctx)) in proposals.iter().zip(&mut self.ctxs).enumerate() {
            net.set_render_table(tables.get(k).cloned().flatten(), ctx);
        }
    }

    /// Makes later [`Levels::place`] calls stop evaluating a ray's proposal
    /// samples once its transmittance at that level falls below
    /// `min_transmittance` (0: never, as training must: the interlevel
    /// loss reads every weight). The weights further on are then 0 instead
    /// of their true values, whose sum is below `min_transmittance`; the
    /// next level is drawn from them as before. For rendering.
    pub fn set_early_stop(&mut self, min_transmittance: f32) {
        self.stop_below = min_transmittance.max(0.0);
    }

    /// The transmittance [`Levels::set_early_stop`] set (0: none).
    pub fn early_stop(&self) -> f32 {
        self.stop_below
    }

    /// The final level (after [`Levels::place`]).
    pub fn last(&self) -> Option<&Level> {
        self.levels.last()
    }
}

/// A proposal level's densities and weights evaluated in rounds of
/// [`PROPOSAL_ROUND`] samples per ray, each round for the rays whose
/// transmittance is still at least `stop_below`; the weights are those of
/// `composite` with [`PROPOSAL_COMPOSITE`] (the same sums in the same
/// order) where evaluated, 0 beyond. Returns the samples evaluated.
fn in_rounds(
    net: &ProposalField,
    params: &[f32],
    level: &mut Level,
    ctx: &mut ProposalCtx,
    (active, along): (&mut Vec<usize>, &mut Vec<Transmittance>),
    pos: &mut Vec<f32>,
    stop_below: f32,
) -> Result<u64, LevelError> {
    let (n, m) = (level.n, &level.samples);
    let rays = m.spans.len();
    level.weights.clear();
    level.weights.resize(rays * n, 0.0);
    for (r, &span) in m.spans.iter().enumerate() {
        if span != (r * n, n) {
            return Err(ProposalError::Length { what: "samples of a proposal ray", expected: n, got: span.1 }.into());
        }
    }
    active.clear();
    active.extend(0..rays);
    along.clear();
    along.resize(rays, Transmittance::default());
    let mut evaluated = 0u64;
    for start in (0..n).step_by(PROPOSAL_ROUND) {
        let end = (start + PROPOSAL_ROUND).min(n);
        let k = end - start;
        pos.clear();
        for &r in active.iter() {
            pos.extend_from_slice(&m.pos[3 * (r * n + start)..3 * (r * n + end)]);
        }
        net.density(params, pos, ctx);
        evaluated += (active.len() * k) as u64;
        let sigma = net.sigma(ctx);
        for (a, &r) in active.iter().enumerate() {
            let w = &mut level.weights[r * n..(r + 1) * n];
            for j in start..end {
                // `PROPOSAL_COMPOSITE`: the last interval is opaque.
                w[j] = along[r].step(sigma[a * k + j - start], m.delta[r * n + j], j + 1 == n);
            }
        }
        active.retain(|&r| along[r].value() >= stop_below);
        if active.is_empty() {
            break;
        }
    }
    Ok(evaluated)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::fields::space::{Norm, SpaceMap};
    use crate::engine::geometry::math::Vec3;
    use crate::engine::nn::hashgrid::HashGridConfig;
    use crate::engine::nn::linear::ParamLayout;

    fn rays() -> Vec<Ray> {
        (0..5)
            .map(|k| {
                let origin = Vec3::new(3.0, 0.3 * k as f32 - 0.6, 0.5);
                Ray { origin, dir: (Vec3::new(0.0, 0.0, 0.0) - origin).normalized().unwrap() }
            })
            .collect()
    }

    fn nets(layout: &mut ParamLayout) -> Vec<ProposalField> {
        let grid = HashGridConfig { levels: 3, log2_table: 8, base_resolution: 4, finest_resolution: 16 };
        let space = SpaceMap::Contract { norm: Norm::Linf };
        (0..2).map(|k| ProposalField::new(layout, &format!("p{k}"), space.clone(), grid.clone(), 8, 0.5)).collect()
    }

    /// Levels of 16, 8 and 6 intervals tile each ray's `[near, far]`, in
    /// order, with samples at the midpoints; proposal weights are those of
    /// the compositor with an opaque end (they sum to 1).
    #[test]
    fn levels_tile_each_ray_and_weigh_it_whole() {
        let mut layout = ParamLayout::default();
        let props = nets(&mut layout);
        let mut params = vec![0.0f32; layout.len];
        let mut rng = Rng::new(1);
        props.iter().for_each(|p| p.init(&mut params, &mut rng));
        let rays = rays();
        let (near, far) = (0.05, 1000.0);
        let warps: Vec<Warp> = rays.iter().map(|r| Warp::for_ray(r, near, far).unwrap()).collect();
        let how = Resampling::new(1.0, 0.01).unwrap();
        let index: Vec<u64> = (0..rays.len() as u64).collect();
        let mut levels = Levels::default();
        for mut placement in [Drawn::centred(how), Drawn::jittered(how, 7, 3)] {
            let n = levels.place(&props, &params, &rays, &warps, &[16, 8, 6], &mut placement, &index).unwrap();
            assert_eq!(n, 5 * (16 + 8));
            for (k, level) in levels.levels.iter().enumerate() {
                assert_eq!(level.samples.len(), 5 * level.n);
                for r in 0..5 {
                    let (s, t) = (level.s_of(r), level.t.ray(r));
                    assert_eq!((s[0], s[level.n]), (0.0, 1.0));
                    assert_eq!((t[0], t[level.n]), (near, far));
                    assert!(t.windows(2).all(|w| w[0] <= w[1]));
                    let (o, len) = level.samples.spans[r];
                    assert_eq!((o, len), (r * level.n, level.n));
                    for j in 0..len {
                        assert_eq!(level.samples.t[o + j], 0.5 * (t[j] + t[j + 1]));
                    }
                    if k < 2 {
                        let total: f32 = level.weights_of(r).iter().sum();
                        assert!((total - 1.0).abs() < 1e-5, "level {k} ray {r}: {total}");
                    }
                }
            }
        }
        // A wrong number of levels is an error, not a panic.
        let e = levels.place(&props, &params, &rays, &warps, &[16, 8], &mut Drawn::centred(how), &index);
        assert!(matches!(e, Err(LevelError::Proposal(ProposalError::Length { .. }))), "{e:?}");
    }

    /// With weight on one proposal interval, the next level's edges crowd
    /// into it: the drawn intervals follow the proposal.
    #[test]
    fn the_next_level_follows_the_weights() {
        let how = Resampling::new(1.0, 0.0).unwrap();
        let mut d = Drawn::centred(how);
        d.start(&[0]);
        let edges: Vec<f32> = (0..=10).map(|k| k as f32 / 10.0).collect();
        let mut w = vec![0.0f32; 10];
        w[6] = 1.0;
        let mut out = Vec::new();
        d.next(0, &edges, &w, 8, &mut out).unwrap();
        assert_eq!(out.len(), 9);
        assert!(out[1..8].iter().all(|&s| (0.6..=0.7).contains(&s)), "{out:?}");
        // Same seed, step and index: the same jitter.
        let (mut a, mut b) = (Drawn::jittered(how, 1, 2), Drawn::jittered(how, 1, 2));
        a.start(&[5]);
        b.start(&[5]);
        let (mut ea, mut eb) = (Vec::new(), Vec::new());
        a.first(0, 6, &mut ea).unwrap();
        b.first(0, 6, &mut eb).unwrap();
        assert_eq!(ea, eb);
        let mut c = Drawn::jittered(how, 1, 3);
        c.start(&[5]);
        let mut ec = Vec::new();
        c.first(0, 6, &mut ec).unwrap();
        assert_ne!(ea, ec, "another step, another jitter");
    }

    /// Stopping early (rendering): where a ray's transmittance at a level
    /// falls below the threshold, its later proposal samples are not
    /// evaluated and weigh 0; every weight of the rounds evaluated is the
    /// full pass's, bit for bit (each density is computed alone: the f32
    /// pass in whole groups of 8 here, 64 samples per ray at the first
    /// level; the fused half-table pass lane by lane), and the weights
    /// dropped sum to less than the threshold. On dense proposals (density
    /// 40 everywhere) fewer samples are evaluated; on thin ones none are
    /// dropped and the next level is the same. With the half tables
    /// rendering uses, as with the f32 parameters.
    #[test]
    fn early_stop_drops_only_what_lies_behind_opaque_matter() {
        let grid = HashGridConfig { levels: 3, log2_table: 8, base_resolution: 4, finest_resolution: 16 };
        let space = SpaceMap::Contract { norm: Norm::Linf };
        for (init, half) in [(0.05, false), (40.0, false), (0.05, true), (40.0, true)] {
            let mut layout = ParamLayout::default();
            let props: Vec<ProposalField> = (0..2)
                .map(|k| ProposalField::new(&mut layout, &format!("p{k}"), space.clone(), grid.clone(), 8, init))
                .collect();
            let mut params = vec![0.0f32; layout.len];
            let mut rng = Rng::new(2);
            props.iter().for_each(|p| p.init(&mut params, &mut rng));
            params.iter_mut().for_each(|p| *p *= 0.3);
            let tables: Vec<Option<std::sync::Arc<HalfTable>>> =
                props.iter().map(|p| p.half_table(&params).map(std::sync::Arc::new)).collect();
            if half && tables.iter().any(|t| t.is_none()) {
                assert!(!crate::engine::nn::hashgrid::half_tables_supported());
                continue;
            }
            let rays = rays();
            let warps: Vec<Warp> = rays.iter().map(|r| Warp::for_ray(r, 0.05, 1000.0).unwrap()).collect();
            let how = Resampling::new(1.0, 0.01).unwrap();
            let index: Vec<u64> = (0..rays.len() as u64).collect();
            let intervals = [64, 20, 6];
            let place = |stop: f32| {
                let mut levels = Levels::default();
                if half {
                    levels.set_render_tables(&props, &tables);
                }
                levels.set_early_stop(stop);
                let n = levels.place(&props, &params, &rays, &warps, &intervals, &mut Drawn::centred(how), &index);
                (n.unwrap(), levels)
            };
            let (all, full) = place(0.0);
            assert_eq!(all, 5 * (64 + 20));
            assert_eq!(place(0.0).1.levels[1].weights, full.levels[1].weights, "repeatable");
            let threshold = 1e-3;
            let (some, early) = place(threshold);
            if init > 1.0 {
                assert!(some < all / 2, "{some} of {all} evaluated on opaque proposals");
            } else {
                assert_eq!(some, all, "nothing stops in thin proposals");
            }
            // The first level is placed as before; its weights are the full
            // pass's over whole rounds, 0 after.
            assert_eq!(early.levels[0].s, full.levels[0].s);
            let mut first_level = 0;
            for r in 0..5 {
                let (a, b) = (early.levels[0].weights_of(r), full.levels[0].weights_of(r));
                let kept = a.iter().rposition(|&w| w != 0.0).map_or(0, |i| i + 1);
                let rounds = kept.div_ceil(PROPOSAL_ROUND).max(1) * PROPOSAL_ROUND;
                assert_eq!(&a[..rounds.min(64)], &b[..rounds.min(64)], "ray {r}");
                assert!(a[kept..].iter().all(|&w| w == 0.0));
                let dropped: f32 = b[kept..].iter().sum();
                assert!(dropped < threshold, "ray {r}: {dropped} dropped");
                first_level += rounds.min(64) as u64;
            }
            assert!(first_level <= some, "{first_level} first-level samples, {some} in all");
            if init < 1.0 {
                assert_eq!(early.levels[1].s, full.levels[1].s, "the same weights, the same next level");
            }
        }
    }
}
