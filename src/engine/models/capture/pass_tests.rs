//! Unit tests of `capture_pass.rs`: the whole pass against central
//! differences in f64 with its sample positions frozen (a record of a first
//! pass's placement is replayed), culling, rays without samples, and the
//! losses' bookkeeping. `check_pass_gradients` is also run on the
//! `capture-tiny` preset's networks by the model's tests.

use std::ops::Range;

use super::*;
use crate::engine::fields::capture::CaptureFieldConfig;
use crate::engine::fields::space::{Norm, SpaceMap};
use crate::engine::geometry::math::Vec3;
use crate::engine::nn::hashgrid::HashGridConfig;
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::pose::PoseRefine;
use crate::engine::rng::Rng;
use crate::engine::sampling::proposal::{ProposalError, Resampling};

/// Records the edges another placement gives, in call order.
pub(crate) struct Recorder<'a> {
    pub inner: &'a mut dyn Placement,
    pub calls: Vec<Vec<f32>>,
}

impl Placement for Recorder<'_> {
    fn start(&mut self, index: &[u64]) {
        self.inner.start(index);
    }
    fn first(&mut self, r: usize, n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        let start = out.len();
        self.inner.first(r, n, out)?;
        self.calls.push(out[start..].to_vec());
        Ok(())
    }
    fn next(&mut self, r: usize, e: &[f32], w: &[f32], n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        let start = out.len();
        self.inner.next(r, e, w, n, out)?;
        self.calls.push(out[start..].to_vec());
        Ok(())
    }
}

/// Gives back recorded edges in the same order, whatever the weights: the
/// samples stay where they were when parameters move.
pub(crate) struct Replay<'a> {
    pub calls: &'a [Vec<f32>],
    pub next: usize,
}

impl Replay<'_> {
    fn take(&mut self, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        let e = self.calls.get(self.next).ok_or(ProposalError::NoIntervals)?;
        self.next += 1;
        out.extend_from_slice(e);
        Ok(())
    }
}

impl Placement for Replay<'_> {
    fn start(&mut self, _index: &[u64]) {
        self.next = 0;
    }
    fn first(&mut self, _r: usize, _n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        self.take(out)
    }
    fn next(&mut self, _r: usize, _e: &[f32], _w: &[f32], _n: usize, out: &mut Vec<f32>) -> Result<(), ProposalError> {
        self.take(out)
    }
}

/// `check_pass_gradients`' summary: parameters checked, and the largest
/// numeric gradient of each range.
pub(crate) struct Checked {
    pub count: usize,
    pub largest: Vec<(String, f64)>,
}

/// Checks the gradient of a whole pass over `rays` against central
/// differences of its loss, with the sample positions of a first pass
/// (placed by `placement`) frozen. `settings.batch_rays` should be 1, so
/// the loss is a sum over rays. Ranges named `proposal*` are checked
/// against the interlevel loss, the others against the colour and
/// distortion losses (the interlevel loss takes the final weights as
/// constants, so the main field gets no gradient from it). In each range
/// the parameters with the largest analytic gradients and a few others
/// are checked; a ReLU or `max(0, .)` kink within the step spoils the
/// wider difference, so a quarter step may agree instead, and a kink
/// within the quarter step spoils that too, so a one-sided quarter step
/// may agree instead (the side without the kink: the analytic gradient is
/// the derivative of the piece the point is on). Such kinks are common:
/// moving `rays(5)`'s rays by 1% of a unit made a central quarter step
/// disagree in 3 of 12 draws, with the analytic gradient equal to one
/// side's derivative.
pub(crate) fn check_pass_gradients(
    nets: CaptureNets<'_>,
    names: &[(String, Range<usize>)],
    settings: &PassSettings<'_>,
    rays: &[TrainRay],
    placement: &mut dyn Placement,
) -> Checked {
    let mut grads = vec![0.0f32; nets.params.len()];
    let mut rec = Recorder { inner: placement, calls: Vec::new() };
    let first = capture_pass(nets, settings, rays, &mut rec, &mut CaptureBuffers::default(), &mut grads);
    assert!(first.loss().is_finite(), "{first:?}");
    let calls = rec.calls;
    // The gradient again with the placement replayed: the same numbers.
    let mut again = vec![0.0f32; nets.params.len()];
    let replayed = Replay { calls: &calls, next: 0 };
    let stats = capture_pass(nets, settings, rays, &mut { replayed }, &mut CaptureBuffers::default(), &mut again);
    assert_eq!(stats, first, "replaying the placement changes the pass");
    assert!(grads.iter().zip(&again).all(|(a, b)| a.to_bits() == b.to_bits()));
    let loss = |p: &[f32], proposal: bool| -> f64 {
        let nets = CaptureNets { params: p, ..nets };
        let mut replay = Replay { calls: &calls, next: 0 };
        let mut g = vec![0.0f32; p.len()];
        let s = capture_pass(nets, settings, rays, &mut replay, &mut CaptureBuffers::default(), &mut g);
        if proposal { s.interlevel } else { s.sq_err + s.distortion }
    };
    let mut rng = Rng::new(99);
    let mut checked = Checked { count: 0, largest: Vec::new() };
    for (name, range) in names {
        let proposal = name.starts_with("proposal");
        let mut order: Vec<usize> = range.clone().collect();
        order.sort_by(|&a, &b| grads[b].abs().total_cmp(&grads[a].abs()));
        let mut picks: Vec<usize> = order.iter().take(6).copied().collect();
        picks.extend((0..3).map(|_| range.start + rng.below(range.len() as u64) as usize));
        let mut largest = 0.0f64;
        for i in picks {
            let diff = |h: f32| {
                let mut p = nets.params.to_vec();
                p[i] += h;
                let up = loss(&p, proposal);
                p[i] -= 2.0 * h;
                (up - loss(&p, proposal)) / (2.0 * h as f64)
            };
            // One side only: the derivative of the piece on that side.
            let side = |h: f32| {
                let mut p = nets.params.to_vec();
                let at = loss(&p, proposal);
                p[i] += h;
                (loss(&p, proposal) - at) / h as f64
            };
            let ana = grads[i] as f64;
            let close = |num: f64| (num - ana).abs() < 3e-4 + 2e-2 * num.abs();
            // Pose parameters move every sample of their rays, over many
            // cell faces of the grids for a wide step: a narrower one.
            let step = if name.starts_with("pose") { 2e-4f32 } else { 1e-3 };
            let h = step * (1.0 + nets.params[i].abs());
            let num = diff(h);
            let q = 0.25 * h;
            assert!(
                close(num) || close(diff(q)) || close(side(q)) || close(side(-q)),
                "{name}[{}]: numeric {num} (and {} with a quarter step, {} and {} on either side), analytic {ana}",
                i - range.start,
                diff(q),
                side(q),
                side(-q)
            );
            largest = largest.max(num.abs());
            checked.count += 1;
        }
        checked.largest.push((name.clone(), largest));
    }
    checked
}

/// Small networks: two proposal levels and the main field, in L-inf space,
/// and pose corrections for 4 images (last, so the networks' parameters
/// are those of a layout without them).
struct Nets {
    proposals: Vec<ProposalField>,
    field: CaptureField,
    pose: PoseRefine,
    layout: ParamLayout,
    params: Vec<f32>,
}

/// Networks whose untrained densities are about `proposal_density` and
/// `main_density`.
fn nets(seed: u64, proposal_density: f32, main_density: f32) -> Nets {
    let mut layout = ParamLayout::default();
    let space = SpaceMap::Contract { norm: Norm::Linf };
    let grid = |finest| HashGridConfig { levels: 3, log2_table: 8, base_resolution: 4, finest_resolution: finest };
    let proposals = (0..2)
        .map(|k| ProposalField::new(&mut layout, &format!("proposal{k}"), space.clone(), grid(16), 8, proposal_density))
        .collect();
    let c = CaptureFieldConfig {
        grid: grid(32),
        hidden: 16,
        geo_features: 4,
        init_density: main_density,
        max_images: 4,
        appearance_dim: 3,
    };
    let field = CaptureField::new(&mut layout, space, &c);
    let pose = PoseRefine::new(&mut layout, "pose", 4);
    let mut params = vec![0.0f32; layout.len];
    let mut rng = Rng::new(seed);
    for p in &proposals {
        ProposalField::init(p, &mut params, &mut rng);
    }
    field.init(&mut params, &mut rng);
    // Larger than initial values, so that every part has a gradient.
    for p in params.iter_mut() {
        *p += 0.2 * rng.normal();
    }
    Nets { proposals, field, pose, layout, params }
}

/// Rays from a ring of cameras at distance 1.5 through the unit cube, from
/// images 0-2, with a target colour each.
fn rays(count: usize) -> Vec<TrainRay> {
    (0..count)
        .map(|k| {
            let a = k as f32 * 0.9;
            let origin = Vec3::new(1.5 * a.cos(), 1.5 * a.sin(), 0.2);
            let look = Vec3::new(0.1 * a.sin(), -0.2, 0.05 * k as f32) - origin;
            TrainRay {
                ray: Ray { origin, dir: look.normalized().unwrap() },
                target: [0.2 + 0.1 * k as f32, 0.5, 0.9 - 0.1 * k as f32],
                background: [1.0; 3],
                index: k as u64,
                image: (k % 3) as u32,
                weight: 1.0,
            }
        })
        .collect()
}

fn settings(intervals: &[usize], cull: Option<f32>) -> PassSettings<'_> {
    PassSettings {
        intervals,
        interval: RayInterval { near: 0.05, far: 1000.0, radius: 0.0 },
        cull,
        batch_rays: 1,
        interlevel: 1.0,
        distortion: 0.01,
        pose: None,
    }
}

/// With pose refinement on, the pose corrections of images 0 and 1 (all
/// twelve parameters, set to N(0, 0.05): rotations of about 5 degrees)
/// are checked as well, through the sample positions (hash grid,
/// contraction) and directions (SH code), with a narrower step. Moving a
/// pose moves every sample of its rays across the grids' cell faces, so
/// kinks are common: over 12 draws of the pose rows at N(0, 0.01) and 12
/// at N(0, 0.05) (images 0-2 checked), 23 of the 24 passed with `far`
/// 1000 and all 24 with `far` 4; the failure (a rotation parameter,
/// one-sided quarter steps 0.047 and 0.0087 around an analytic 0.0174) was
/// not explained further.
#[test]
fn the_whole_pass_matches_finite_differences_with_frozen_samples() {
    let mut n = nets(4, 0.5, 0.5);
    let mut rng = Rng::new(40);
    n.params[n.pose.range.clone()].iter_mut().for_each(|p| *p = 0.05 * rng.normal());
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let mut names: Vec<(String, Range<usize>)> = n.layout.names.iter().filter(|(k, _)| k != "pose").cloned().collect();
    names.extend((0..2).map(|i| (format!("pose of image {i}"), n.pose.row(i).unwrap())));
    // A strong interlevel weight, so the proposals' gradients stand well
    // above the differences' rounding.
    let checked = check_pass_gradients(
        cn,
        &names,
        &PassSettings { interlevel: 50.0, pose: Some(&n.pose), ..settings(&[12, 8, 6], None) },
        &rays(5),
        &mut Drawn::jittered(how, 3, 2),
    );
    // Each range has gradients over 3x the check's absolute tolerance.
    for (name, largest) in &checked.largest {
        assert!(*largest > 1e-3, "{name}: every gradient checked is tiny ({largest}): {:?}", checked.largest);
    }
    assert!(checked.largest.iter().any(|(k, _)| k == "pose of image 1"), "{:?}", checked.largest);
    assert!(checked.count > 150, "{}", checked.count);
}

/// Pose refinement with zero corrections changes nothing else: the same
/// loss and the same network gradients, bit for bit, as the pass without
/// it (zero corrections leave the rays exactly as they are); only the
/// rows of the images trained on get a gradient, and a held-out image's
/// row (image 3 here) none.
#[test]
fn zero_corrections_train_the_networks_as_without_pose_refinement() {
    let mut n = nets(14, 0.5, 0.5);
    n.params[n.pose.range.clone()].fill(0.0);
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let run = |pose: Option<&PoseRefine>| {
        let mut g = vec![0.0f32; n.params.len()];
        let s = PassSettings { pose, ..settings(&[10, 8, 6], Some(1e-4)) };
        let stats =
            capture_pass(cn, &s, &rays(6), &mut Drawn::jittered(how, 4, 1), &mut CaptureBuffers::default(), &mut g);
        (stats, g)
    };
    let (off, g_off) = run(None);
    let (on, g_on) = run(Some(&n.pose));
    assert_eq!(on, off);
    let nets_end = n.pose.range.start;
    assert!(g_on[..nets_end].iter().zip(&g_off[..nets_end]).all(|(a, b)| a.to_bits() == b.to_bits()));
    assert!(g_off[nets_end..].iter().all(|&g| g == 0.0), "no pose gradient when off");
    for i in 0..3 {
        assert!(g_on[n.pose.row(i).unwrap()].iter().any(|&g| g != 0.0), "image {i} has a pose gradient");
    }
    assert!(g_on[n.pose.row(3).unwrap()].iter().all(|&g| g == 0.0), "image 3 has no rays");
}

/// Culling drops samples whose weights the threshold bounds: the loss and
/// gradient barely move.
#[test]
fn culling_drops_samples_but_barely_changes_the_loss_or_gradient() {
    let n = nets(6, 0.5, 30.0);
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let run = |cull| {
        let mut g = vec![0.0f32; n.params.len()];
        let s = capture_pass(
            cn,
            &settings(&[16, 8, 16], cull),
            &rays(6),
            &mut Drawn::jittered(how, 1, 1),
            &mut CaptureBuffers::default(),
            &mut g,
        );
        (s, g)
    };
    let (all, g_all) = run(None);
    let (culled, g_culled) = run(Some(1e-4));
    assert!(culled.culled > 0 && all.culled == 0, "{culled:?}");
    assert_eq!((culled.samples, culled.proposal_samples), (6 * 16, 6 * 24));
    assert!((culled.sq_err - all.sq_err).abs() < 1e-3, "{culled:?} {all:?}");
    let big = g_all.iter().fold(0.0f32, |m, g| m.max(g.abs()));
    for (a, b) in g_culled.iter().zip(&g_all) {
        assert!((a - b).abs() < 1e-2 * big, "{a} vs {b} (largest {big})");
    }
}

/// A ray with a non-finite origin or a zero direction shows the background
/// in the loss and adds no gradient; the other rays are trained as without
/// it.
#[test]
fn rays_without_samples_count_in_the_loss_only() {
    let n = nets(8, 0.5, 0.5);
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let good = rays(3);
    let mut mixed = good.clone();
    let mut bad = good[0];
    bad.ray.origin.x = f32::NAN;
    bad.target = [0.0, 0.5, 1.0];
    bad.index = 100;
    mixed.insert(1, bad);
    let mut zero = good[1];
    zero.ray.dir = Vec3::splat(0.0);
    zero.index = 101;
    mixed.push(zero);
    let run = |rays: &[TrainRay]| {
        let mut g = vec![0.0f32; n.params.len()];
        let s = settings(&[8, 8, 8], None);
        let stats = capture_pass(cn, &s, rays, &mut Drawn::jittered(how, 2, 0), &mut CaptureBuffers::default(), &mut g);
        (stats, g)
    };
    let (a, ga) = run(&good);
    let (b, gb) = run(&mixed);
    assert_eq!(ga, gb);
    // Background white against targets (0, 0.5, 1) and good[1]'s.
    let t = good[1].target;
    let background_err =
        (1.0 + 0.25) / 3.0 + ((1.0 - t[0]).powi(2) + (1.0 - t[1]).powi(2) + (1.0 - t[2]).powi(2)) / 3.0;
    assert!((b.sq_err - a.sq_err - background_err as f64).abs() < 1e-6, "{} {} {background_err}", b.sq_err, a.sq_err);
    assert_eq!((b.rays, b.samples), (5, a.samples));
    assert_eq!(b.interlevel, a.interlevel);
}

/// The reported losses are the losses the definitions give, and an
/// untrained, transparent field's proposals are penalised by the
/// interlevel loss only where they miss the final weights.
#[test]
fn stats_add_up_and_weights_sum_to_one() {
    let n = nets(10, 0.5, 0.5);
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let mut buf = CaptureBuffers::default();
    let s = capture_pass(
        cn,
        &settings(&[10, 6, 5], None),
        &rays(4),
        &mut Drawn::centred(how),
        &mut buf,
        &mut vec![0.0; n.params.len()],
    );
    assert_eq!((s.rays, s.samples, s.proposal_samples), (4, 20, 64));
    assert!(s.sq_err > 0.0 && s.interlevel >= 0.0 && s.distortion > 0.0, "{s:?}");
    assert!((s.loss() - (s.sq_err + s.interlevel + s.distortion)).abs() < 1e-12);
    // Every ray's final weights sum to 1 (opaque last interval, no culling).
    for r in 0..4 {
        let total: f32 = buf.full[r * 5..(r + 1) * 5].iter().sum();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
    }
}

/// One thread's buffers serve passes of any shape in turn (a service
/// trains models of different configurations on the same threads): a pass
/// after a larger one gives what it gives with fresh buffers.
#[test]
fn buffers_serve_passes_of_any_shape() {
    let n = nets(12, 0.5, 0.5);
    let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
    let how = Resampling::new(1.0, 0.01).unwrap();
    let pass = |intervals: &[usize], count: usize, buf: &mut CaptureBuffers| {
        let mut g = vec![0.0f32; n.params.len()];
        let s = capture_pass(cn, &settings(intervals, Some(1e-4)), &rays(count), &mut Drawn::centred(how), buf, &mut g);
        (s, g)
    };
    let mut shared = CaptureBuffers::default();
    pass(&[24, 16, 12], 7, &mut shared);
    for (intervals, count) in [(&[8usize, 6, 4][..], 3usize), (&[5, 3, 2], 9)] {
        let (a, ga) = pass(intervals, count, &mut shared);
        let (b, gb) = pass(intervals, count, &mut CaptureBuffers::default());
        assert!(a.loss().is_finite(), "{a:?}");
        assert_eq!(a, b, "{intervals:?}");
        assert!(ga == gb, "{intervals:?}");
    }
}

/// A ray's near end: `near` from `radius` on, in proportion nearer the
/// focus, never below the floor; a radius of 0 keeps `near` everywhere.
#[test]
fn rays_nearer_the_focus_start_nearer() {
    let at = |x: f32| Ray { origin: Vec3::new(x, 0.0, 0.0), dir: Vec3::new(-1.0, 0.0, 0.0) };
    let interval = |near: f32, radius: f32| RayInterval { near, far: 1000.0, radius };
    for (x, want) in [(2.0, 0.4), (1.0, 0.4), (0.5, 0.2), (0.25, 0.1), (0.1, NEAR_FLOOR), (0.0, NEAR_FLOOR)] {
        let got = interval(0.4, 1.0).near_of(&at(x));
        assert!((got - want).abs() < 1e-6, "origin {x}: {got} vs {want}");
    }
    assert_eq!(interval(0.4, 0.0).near_of(&at(0.1)), 0.4);
    // A near already below the floor is kept.
    assert_eq!(interval(0.01, 1.0).near_of(&at(0.0)), 0.01);
    assert_eq!(interval(0.4, 1.0).near_of(&at(f32::NAN)), 0.4);
    // The warp spans the ray's own interval.
    let w = interval(0.4, 1.0).warp(&at(0.5)).unwrap();
    assert_eq!((w.to_s(0.2), w.to_s(1000.0)), (0.0, 1.0));
    assert!(w.to_s(0.21) > 0.0);
}

/// Each ray's measure: its squared error as the statistics count it, and a
/// depth only where its opacity reaches one half before the last interval,
/// which the pass makes opaque (a ray through an empty field ran out there;
/// it met no surface).
#[test]
fn a_ray_reports_a_depth_only_where_it_meets_a_surface() {
    for (density, meets) in [(1e-6, false), (1e3, true)] {
        let n = nets(8, 0.5, density);
        let cn = CaptureNets { proposals: &n.proposals, field: &n.field, params: &n.params };
        let how = Resampling::new(1.0, 0.01).unwrap();
        let mut g = vec![0.0f32; n.params.len()];
        let mut buf = CaptureBuffers::default();
        let s = settings(&[8, 8, 8], None);
        let stats = capture_pass(cn, &s, &rays(4), &mut Drawn::jittered(how, 2, 0), &mut buf, &mut g);
        let sq: f64 = buf.errors.iter().map(|e| e.sq_err as f64).sum();
        assert!((sq - stats.sq_err).abs() < 1e-5, "{sq} {}", stats.sq_err);
        for e in &buf.errors {
            assert_eq!(e.depth.is_finite(), meets, "density {density}: {e:?}");
            assert!(!meets || (e.depth > 0.0 && e.depth < 3.0), "{e:?}");
        }
    }
}
