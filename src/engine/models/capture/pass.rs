//! The training pass of the real-capture model (design `real-captures.md`
//! 2.4 and 2.5), for a chunk of rays:
//!
//! 1. proposal levels: each proposal network's densities along its level,
//!    and the next level's intervals drawn from their weights
//!    ([`Levels::place`]);
//! 2. the main field's densities on the final intervals, the samples behind
//!    the point where transmittance falls below the cull threshold dropped
//!    (they change the colour by less than that), colours of the rest;
//! 3. compositing with an opaque last interval (a ray that was culled never
//!    reaches it, and shows the background by less than the threshold);
//! 4. losses: L2 on the colour (`1 / (3 batch)` per squared channel error),
//!    the distortion loss on the final weights over `s` (`λ_d / batch`),
//!    and for each proposal level the interlevel loss of its weights
//!    against the final ones (`λ_i / (batch n)`, `n` final intervals);
//! 5. backward: the colour and distortion gradients through the main field;
//!    the interlevel gradients through each proposal network. The final
//!    weights are detached in the interlevel loss (it trains the proposals
//!    only), and no gradient flows through where samples were placed.
//!
//! With pose refinement (design 2.7, [`PassSettings::pose`]) each ray is
//! first moved by its image's correction (`o' = o + τ`, `d' = R(ω) d`) and
//! the main field's backward also gives each sample's position and
//! direction gradients: per ray `∂L/∂o' = Σ g_k` and
//! `∂L/∂d' = Σ (t_k g_k + h_k)` (samples at `x_k = o' + t_k d'`), which
//! [`Correction::backward`] takes to the image's six parameters. Sample
//! distances are detached: the ray-distance warp is that of the uncorrected
//! ray, so where samples sit along a ray (in `t`) does not depend on the
//! pose at all. The proposal networks give the poses no gradient (their
//! interlevel loss only shapes sampling).

use crate::engine::batch::TrainRay;
use crate::engine::fields::capture::{CaptureField, Ctx};
use crate::engine::fields::proposal::ProposalField;
use crate::engine::fields::{Field, Points};
use crate::engine::geometry::math::Ray;
use crate::engine::models::RayMeasure;
#[cfg(test)]
use crate::engine::models::capture::levels::Drawn;
use crate::engine::models::capture::levels::{LevelError, Levels, PROPOSAL_COMPOSITE, Placement};
use crate::engine::models::pass::visible;
use crate::engine::nn::pose::{Correction, PoseRefine};
use crate::engine::render::composite::{CompositeOptions, RaySamples, Upstream, composite, composite_backward};
use crate::engine::render::loss::l2;
use crate::engine::render::regularize::{Histogram, Interlevel, distortion};
use crate::engine::sampling::proposal::{ProposalError, Warp};

/// The networks a pass trains, over one flat parameter buffer.
#[derive(Clone, Copy)]
pub struct CaptureNets<'a> {
    /// The proposal networks, one per proposal level.
    pub proposals: &'a [ProposalField],
    pub field: &'a CaptureField,
    pub params: &'a [f32],
}

/// How a pass samples and weighs its losses.
#[derive(Clone, Copy, Debug)]
pub struct PassSettings<'a> {
    /// Intervals per ray at each proposal level, then at the final level.
    pub intervals: &'a [usize],
    /// Where each ray is sampled.
    pub interval: RayInterval,
    /// Transmittance below which the final samples are dropped after their
    /// densities (`None`: keep them all).
    pub cull: Option<f32>,
    /// Rays of the whole batch (losses are means over it).
    pub batch_rays: usize,
    /// Weight of the interlevel loss (summed over proposal levels).
    pub interlevel: f32,
    /// Weight of the distortion loss.
    pub distortion: f32,
    /// The camera pose corrections to apply and train (`None`: rays as
    /// given, and the pass of before pose refinement, bit for bit).
    pub pose: Option<&'a PoseRefine>,
}

/// What a pass measured, summed over its rays (the batch loss is `loss /
/// batch_rays`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CaptureStats {
    /// Sum over rays of the mean squared colour error.
    pub sq_err: f64,
    /// `λ_i / n` times the rays' interlevel losses.
    pub interlevel: f64,
    /// `λ_d` times the rays' distortion losses.
    pub distortion: f64,
    /// Main-field samples evaluated (before culling).
    pub samples: u64,
    /// Proposal-network samples evaluated.
    pub proposal_samples: u64,
    /// Final samples dropped behind the termination point.
    pub culled: u64,
    pub rays: u64,
}

impl CaptureStats {
    /// The loss summed over rays: colour, interlevel and distortion.
    pub fn loss(&self) -> f64 {
        self.sq_err + self.interlevel + self.distortion
    }
}

/// A pass's buffers, reused across chunks by one thread.
#[derive(Default)]
pub struct CaptureBuffers {
    pub levels: Levels,
    pub ctx: Ctx,
    /// The chunk's rays that have samples (finite, with a direction).
    valid: Vec<usize>,
    rays: Vec<Ray>,
    warps: Vec<Warp>,
    index: Vec<u64>,
    /// Each valid ray's pose correction (with pose refinement only).
    corrections: Vec<Option<Correction>>,
    image: Vec<u32>,
    keep: Vec<usize>,
    /// Compositing weights of the kept final samples.
    weights: Vec<f32>,
    dsigma: Vec<f32>,
    drgb: Vec<f32>,
    /// Final weights of every interval, `[rays x n]` (0 where culled).
    full: Vec<f32>,
    /// One ray's dL/dw from the distortion loss, `[n]`.
    dfull: Vec<f32>,
    /// A proposal level's dL/dŵ, dL/dσ and (discarded) dL/dc.
    dprop: Vec<f32>,
    dsig_prop: Vec<f32>,
    drgb_prop: Vec<f32>,
    interlevel: Interlevel,
    /// What the pass measured of each of the chunk's rays.
    pub errors: Vec<RayMeasure>,
}

/// Where a model-space ray is sampled, training and rendering alike: from
/// its near end ([`RayInterval::near_of`]) to `far`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayInterval {
    /// `[near, far]` in model units.
    pub near: f32,
    pub far: f32,
    /// The training cameras' distance from the focus (0: `near` for every
    /// ray).
    pub radius: f32,
}

/// The lowest near end [`RayInterval::near_of`] gives (the capture
/// model's default `near`).
pub const NEAR_FLOOR: f32 = 0.05;

impl RayInterval {
    /// The near end of `ray`'s interval: `near` for a ray that starts at
    /// least `radius` from the focus (the origin), and in proportion to its
    /// distance for one nearer, never below `min(near, NEAR_FLOOR)`: a
    /// close-up keeps its subject when `near` was set for the training
    /// cameras' distance (the dataset's near bound). `radius` 0 (or not
    /// finite): `near` for every ray.
    pub fn near_of(&self, ray: &Ray) -> f32 {
        let (near, radius, d) = (self.near, self.radius, ray.origin.norm());
        if radius > 0.0 && radius.is_finite() && d < radius {
            (near * d / radius).max(near.min(NEAR_FLOOR))
        } else {
            near
        }
    }

    /// `ray`'s ray-distance warp over its interval.
    pub fn warp(&self, ray: &Ray) -> Result<Warp, ProposalError> {
        Warp::for_ray(ray, self.near_of(ray), self.far)
    }
}

/// Whether a model-space ray can be sampled: a finite origin and a finite,
/// non-zero direction. The others see only the background.
pub fn samplable(ray: &Ray) -> bool {
    ray.origin.is_finite() && ray.dir.is_finite() && ray.dir.dot(ray.dir) > 0.0
}

/// Trains `nets` on `rays` (model space) with samples placed by
/// `placement`; gradients of the batch loss accumulate into `grads`. An
/// inconsistency of the caller's sizes is reported as a non-finite loss
/// (the trainer then skips the step) rather than a panic.
pub fn capture_pass(
    nets: CaptureNets<'_>,
    settings: &PassSettings<'_>,
    rays: &[TrainRay],
    placement: &mut dyn Placement,
    buf: &mut CaptureBuffers,
    grads: &mut [f32],
) -> CaptureStats {
    match run(nets, settings, rays, placement, buf, grads) {
        Ok(stats) => stats,
        Err(_) => CaptureStats { sq_err: f64::NAN, rays: rays.len() as u64, ..Default::default() },
    }
}

fn run(
    nets: CaptureNets<'_>,
    settings: &PassSettings<'_>,
    rays: &[TrainRay],
    placement: &mut dyn Placement,
    buf: &mut CaptureBuffers,
    grads: &mut [f32],
) -> Result<CaptureStats, LevelError> {
    let mut stats = CaptureStats { rays: rays.len() as u64, ..Default::default() };
    buf.valid.clear();
    buf.rays.clear();
    buf.warps.clear();
    buf.index.clear();
    buf.corrections.clear();
    buf.errors.clear();
    buf.errors.resize(rays.len(), RayMeasure::UNKNOWN);
    for (i, r) in rays.iter().enumerate() {
        if samplable(&r.ray) {
            buf.valid.push(i);
            let correction = settings.pose.and_then(|p| p.correction(nets.params, r.image));
            buf.rays.push(correction.map_or(r.ray, |c| c.apply(&r.ray)));
            buf.corrections.push(correction);
            // The uncorrected ray's warp: sample distances do not depend
            // on the pose.
            buf.warps.push(settings.interval.warp(&r.ray)?);
            buf.index.push(r.index);
        } else {
            // The background alone: in the loss, without a gradient.
            let sq = l2(r.background, r.target, 0.0).0;
            stats.sq_err += sq;
            buf.errors[i] = RayMeasure { sq_err: sq as f32, depth: f32::NAN };
        }
    }
    if buf.valid.is_empty() {
        return Ok(stats);
    }
    let (proposals, params) = (nets.proposals, nets.params);
    // The interlevel loss reads every proposal weight: none may be dropped.
    debug_assert_eq!(buf.levels.early_stop(), 0.0, "a training pass with rendering's early stop");
    stats.proposal_samples =
        buf.levels.place(proposals, params, &buf.rays, &buf.warps, settings.intervals, placement, &buf.index)?;
    main_field(nets, settings, rays, buf, &mut stats, grads)?;
    for k in 0..proposals.len() {
        stats.interlevel += proposal_backward(nets, settings, k, buf, grads)?;
    }
    Ok(stats)
}

/// Where a ray met a surface: its median depth, unless that is none or the
/// last of its samples `t` when the pass made that one opaque (`opaque_last`:
/// the ray ran out there); NaN then.
fn surface_depth(median: f32, t: &[f32], opaque_last: bool) -> f32 {
    let ran_out = opaque_last && t.last() == Some(&median);
    if median > 0.0 && !ran_out { median } else { f32::NAN }
}

/// The main field on the final level: densities, culling, colours,
/// compositing, colour and distortion losses, backward. Leaves every final
/// interval's weight in `buf.full` for the interlevel loss.
fn main_field(
    nets: CaptureNets<'_>,
    settings: &PassSettings<'_>,
    rays: &[TrainRay],
    buf: &mut CaptureBuffers,
    stats: &mut CaptureStats,
    grads: &mut [f32],
) -> Result<(), LevelError> {
    let (field, params) = (nets.field, nets.params);
    let Some(fin) = buf.levels.levels.last_mut() else { return Ok(()) };
    let n = fin.n;
    {
        let m = &mut fin.samples;
        stats.samples = m.len() as u64;
        buf.image.clear();
        for &i in &buf.valid {
            buf.image.extend(std::iter::repeat_n(rays[i].image, n));
        }
        field.density(params, Points { pos: &m.pos, dirs: &m.dirs, image: &buf.image }, &mut buf.ctx);
        if let Some(min_t) = settings.cull {
            visible(&m.spans, field.sigma(&buf.ctx), &m.delta, min_t, &mut buf.keep);
            if buf.keep.len() < m.len() {
                stats.culled = (m.len() - buf.keep.len()) as u64;
                field.compact(&mut buf.ctx, &buf.keep);
                m.compact(&buf.keep);
            }
        }
        field.color(params, &m.dirs, &mut buf.ctx);
    }
    let fin = &*fin;
    let m = &fin.samples;
    let kept = m.len();
    for v in [&mut buf.weights, &mut buf.dsigma] {
        v.clear();
        v.resize(kept, 0.0);
    }
    buf.drgb.clear();
    buf.drgb.resize(3 * kept, 0.0);
    buf.full.clear();
    buf.full.resize(buf.valid.len() * n, 0.0);
    buf.dfull.resize(n, 0.0);
    let batch = settings.batch_rays.max(1) as f32;
    let scale = 1.0 / (3.0 * batch);
    let (sigma, rgb) = (field.sigma(&buf.ctx), field.rgb(&buf.ctx));
    for (r, &i) in buf.valid.iter().enumerate() {
        let ray = &rays[i];
        let (o, k) = m.spans[r];
        let s = RaySamples::new(&sigma[o..o + k], &rgb[3 * o..3 * (o + k)], &m.t[o..o + k], &m.delta[o..o + k])?;
        // A culled ray never reaches its last interval.
        let opts = CompositeOptions { background: ray.background, min_transmittance: 0.0, opaque_last: k == n };
        let comp = composite(s, &opts, &mut buf.weights[o..o + k])?;
        // A transient's ray (weight 0) still counts in the error reported.
        let (sq, g) = l2(comp.rgb, ray.target, scale * ray.weight);
        stats.sq_err += sq;
        buf.errors[i] = RayMeasure { sq_err: sq as f32, depth: surface_depth(comp.median, &m.t[o..o + k], k == n) };
        let full = &mut buf.full[r * n..(r + 1) * n];
        full[..k].copy_from_slice(&buf.weights[o..o + k]);
        buf.dfull.fill(0.0);
        let hist = Histogram::new(fin.s_of(r), full)?;
        let d = distortion(hist, settings.distortion / batch, &mut buf.dfull)?;
        stats.distortion += settings.distortion as f64 * d;
        let upstream = Upstream { rgb: g, depth: 0.0, weights: Some(&buf.dfull[..k]) };
        let (ds, dc) = (&mut buf.dsigma[o..o + k], &mut buf.drgb[3 * o..3 * (o + k)]);
        composite_backward(s, &buf.weights[o..o + k], &opts, comp.used, upstream, ds, dc)?;
    }
    if kept == 0 {
        return Ok(());
    }
    match settings.pose {
        None => field.backward(params, &mut buf.ctx, &buf.dsigma, &buf.drgb, grads),
        Some(pose) => {
            let ctx = &mut buf.ctx;
            field.backward_with_input_grads(params, ctx, &m.pos, &m.dirs, &buf.dsigma, &buf.drgb, grads);
            pose_backward(pose, field.input_grads(ctx), m, &buf.rays, &buf.corrections, grads);
        }
    }
    Ok(())
}

/// Takes the main field's gradients with respect to each kept sample's
/// position and direction (`d_pos`, `d_dirs`, `[kept x 3]` each) to the pose
/// corrections of the rays' images: per ray `∂L/∂o' = Σ g_k`,
/// `∂L/∂d' = Σ (t_k g_k + h_k)`, summed in f64.
fn pose_backward(
    pose: &PoseRefine,
    (d_pos, d_dirs): (&[f32], &[f32]),
    m: &crate::engine::sampling::Samples,
    rays: &[Ray],
    corrections: &[Option<Correction>],
    grads: &mut [f32],
) {
    for (r, (ray, c)) in rays.iter().zip(corrections).enumerate() {
        let (Some(c), Some(&(o, k))) = (c, m.spans.get(r)) else { continue };
        let (mut d_origin, mut d_dir) = ([0.0f64; 3], [0.0f64; 3]);
        for j in o..o + k {
            let t = f64::from(m.t[j]);
            for a in 0..3 {
                let g = f64::from(d_pos[3 * j + a]);
                d_origin[a] += g;
                d_dir[a] += t * g + f64::from(d_dirs[3 * j + a]);
            }
        }
        let dir = [ray.dir.x, ray.dir.y, ray.dir.z].map(f64::from);
        c.backward(pose, dir, d_origin, d_dir, grads);
    }
}

/// The interlevel loss of proposal level `k` against the final weights,
/// and its backward through the level's network; returns `λ_i / n` times
/// the loss summed over rays.
fn proposal_backward(
    nets: CaptureNets<'_>,
    settings: &PassSettings<'_>,
    k: usize,
    buf: &mut CaptureBuffers,
    grads: &mut [f32],
) -> Result<f64, LevelError> {
    let levels = &mut buf.levels;
    let (Some(fin), Some(net)) = (levels.levels.last(), nets.proposals.get(k)) else { return Ok(0.0) };
    let (level, ctx) = (&levels.levels[k], &mut levels.ctxs[k]);
    let (n, nk, rays) = (fin.n, level.n, buf.valid.len());
    let scale = settings.interlevel / (settings.batch_rays.max(1) as f32 * n.max(1) as f32);
    buf.dprop.clear();
    buf.dprop.resize(rays * nk, 0.0);
    buf.dsig_prop.clear();
    buf.dsig_prop.resize(rays * nk, 0.0);
    buf.drgb_prop.resize(3 * nk, 0.0);
    let sigma = net.sigma(ctx);
    let m = &level.samples;
    let mut loss = 0.0f64;
    for r in 0..rays {
        let fine = Histogram::new(fin.s_of(r), &buf.full[r * n..(r + 1) * n])?;
        let prop = Histogram::new(level.s_of(r), level.weights_of(r))?;
        let dw = &mut buf.dprop[r * nk..(r + 1) * nk];
        loss += buf.interlevel.loss(fine, prop, scale, dw)?;
        let (o, len) = m.spans[r];
        let s = RaySamples::new(&sigma[o..o + len], &levels.zeros[..3 * len], &m.t[o..o + len], &m.delta[o..o + len])?;
        let upstream = Upstream { rgb: [0.0; 3], depth: 0.0, weights: Some(dw) };
        let ds = &mut buf.dsig_prop[o..o + len];
        let dc = &mut buf.drgb_prop[..3 * len];
        composite_backward(s, level.weights_of(r), &PROPOSAL_COMPOSITE, len, upstream, ds, dc)?;
    }
    net.backward(nets.params, ctx, &buf.dsig_prop, grads);
    Ok(settings.interlevel as f64 / n.max(1) as f64 * loss)
}

#[cfg(test)]
#[path = "pass_tests.rs"]
pub(crate) mod tests;
