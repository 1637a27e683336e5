//! Unit tests of `proposal.rs` (kept apart so the module reads in one sitting).

use super::*;
use crate::engine::rng::Rng;
use proptest::prelude::*;

// ---- Warp ----

/// An upper bound of |dt/ds| near `t` (either side of the knee), in f64.
fn dt_ds_bound(w: &Warp, t: f64) -> f64 {
    let span = w.g_far - w.g_near;
    let linear = if w.knee > w.near { 2.0 * (w.knee - w.near) * span } else { 0.0 };
    let disparity = 2.0 * t * t / w.knee * span;
    linear.max(disparity)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn warp_is_monotone_onto_the_unit_interval_and_inverts(
        near in 0.01f32..2.0,
        length in 0.1f32..1000.0,
        knee_at in -0.2f32..1.2,
        a in 0.0f32..1.0,
        b in 0.0f32..1.0,
    ) {
        let far = near + length;
        // Knees before near and after far are clamped.
        let w = Warp::new(near, near + knee_at * length, far).unwrap();
        prop_assert_eq!((w.to_s(near), w.to_s(far)), (0.0, 1.0));
        prop_assert_eq!((w.to_t(0.0), w.to_t(1.0)), (near, far));
        let (ta, tb) = (near + a * length, near + b * length);
        let (sa, sb) = (w.to_s(ta), w.to_s(tb));
        prop_assert!((0.0..=1.0).contains(&sa) && (0.0..=1.0).contains(&sb));
        prop_assert!((ta <= tb) == (sa <= sb) || sa == sb, "s not monotone: {} {} -> {} {}", ta, tb, sa, sb);
        prop_assert!((a <= b) <= (w.to_t(a) <= w.to_t(b)), "t not monotone at s {} {}", a, b);
        prop_assert!((near..=far).contains(&w.to_t(a)));
        // t(s(t)) = t up to f32 rounding of s (at most 2^-24 near 1) carried
        // through dt/ds, and of t: 8x margin on both.
        for t in [ta, tb] {
            let back = w.to_t(w.to_s(t)) as f64;
            let tol = 2f64.powi(-21) * (dt_ds_bound(&w, t as f64) + t as f64);
            prop_assert!((back - t as f64).abs() <= tol, "t {} -> s {} -> {} (tol {})", t, w.to_s(t), back, tol);
        }
    }
}

#[test]
fn warp_by_hand() {
    // near 1, knee 2, far 4: g = (t - 1)/2 up to 2, then 1 - 1/t; g(4) = 3/4.
    let w = Warp::new(1.0, 2.0, 4.0).unwrap();
    for (t, s) in [(1.5f32, 1.0 / 3.0), (2.0, 2.0 / 3.0), (3.0, 8.0 / 9.0)] {
        assert!((w.to_s(t) - s).abs() < 1e-6, "s({t}) = {} vs {s}", w.to_s(t));
        assert!((w.to_t(s) - t).abs() < 1e-5, "t({s}) = {} vs {t}", w.to_t(s));
    }
    // Continuous at the knee: the two pieces meet.
    let (below, above) = (w.to_s(2.0 - 1e-5), w.to_s(2.0 + 1e-5));
    assert!(below < above && above - below < 1e-4, "{below} {above}");
    // Knee at near (the ray misses the cube): linear in disparity throughout,
    // s = (1 - 1/t) / (1 - 1/4).
    let w = Warp::new(1.0, 0.5, 4.0).unwrap();
    assert_eq!(w.knee(), 1.0);
    assert!((w.to_s(2.0) - 2.0 / 3.0).abs() < 1e-6);
    assert!((w.to_t(2.0 / 3.0) - 2.0).abs() < 1e-5);
    // Knee beyond far: linear in distance throughout.
    let w = Warp::new(1.0, 10.0, 4.0).unwrap();
    assert!((w.to_s(2.5) - 0.5).abs() < 1e-6 && (w.to_t(0.25) - 1.75).abs() < 1e-6);
    // Outside the domain: clamped; NaN is not turned into a number.
    assert_eq!((w.to_s(0.5), w.to_s(9.0), w.to_t(-1.0), w.to_t(2.0)), (0.0, 1.0, 1.0, 4.0));
    assert!(w.to_s(f32::NAN).is_nan() && w.to_t(f32::NAN).is_nan());
}

#[test]
fn warp_knee_is_where_the_ray_leaves_the_unit_cube() {
    let z = Vec3::new(0.0, 0.0, 1.0);
    let through = Ray { origin: Vec3::new(0.0, 0.0, -3.0), dir: z };
    assert_eq!(Warp::for_ray(&through, 0.05, 1000.0).unwrap().knee(), 4.0);
    let inside = Ray { origin: Vec3::new(0.2, 0.0, 0.0), dir: Vec3::new(-1.0, 0.0, 0.0) };
    assert_eq!(Warp::for_ray(&inside, 0.05, 1000.0).unwrap().knee(), 1.2);
    let miss = Ray { origin: Vec3::new(5.0, 5.0, -3.0), dir: z };
    assert_eq!(Warp::for_ray(&miss, 0.05, 1000.0).unwrap().knee(), 0.05);
    let broken = Ray { origin: Vec3::new(f32::NAN, 0.0, 0.0), dir: z };
    assert_eq!(Warp::for_ray(&broken, 0.05, 1000.0).unwrap().knee(), 0.05);
}

#[test]
fn bad_warp_bounds_are_errors() {
    for (near, knee, far) in
        [(0.0, 1.0, 2.0), (-1.0, 1.0, 2.0), (2.0, 2.0, 1.0), (1.0, f32::NAN, 2.0), (1.0, 1.0, f32::INFINITY)]
    {
        assert_eq!(
            Warp::new(near, knee, far).unwrap_err().to_string(),
            ProposalError::Bounds { near, knee, far }.to_string()
        );
    }
    let z = Vec3::new(0.0, 0.0, 1.0);
    assert!(Warp::for_ray(&Ray { origin: Vec3::splat(0.0), dir: z }, 0.0, 10.0).is_err());
}

// ---- stratified and PDF edges ----

#[test]
fn stratified_edges_tile_the_unit_interval() {
    let mut out = Vec::new();
    stratified_edges(4, None, &mut out).unwrap();
    assert_eq!(out, [0.0, 0.25, 0.5, 0.75, 1.0]);
    out.clear();
    stratified_edges(1, Some(&mut Rng::new(1)), &mut out).unwrap();
    assert_eq!(out, [0.0, 1.0]);
    assert_eq!(stratified_edges(0, None, &mut out), Err(ProposalError::NoIntervals));
    for seed in 0..50 {
        let n = 1 + seed as usize % 20;
        let mut out = vec![7.0]; // edges are appended
        stratified_edges(n, Some(&mut Rng::stream(seed, 3, 9)), &mut out).unwrap();
        let e = &out[1..];
        assert_eq!((e.len(), e[0], e[n]), (n + 1, 0.0, 1.0));
        assert!(e.windows(2).all(|p| p[0] <= p[1]), "{e:?}");
        // One jitter: each inner edge in its stratum, inner gaps all 1/n.
        for k in 1..n {
            let lo = (k as f32 - 0.5) / n as f32;
            assert!(e[k] >= lo - 1e-6 && e[k] < lo + 1.0 / n as f32 + 1e-6, "{k}: {e:?}");
        }
        assert!(e[1..n].windows(2).all(|p| (p[1] - p[0] - 1.0 / n as f32).abs() < 1e-5), "{e:?}");
    }
}

#[test]
fn edges_are_deterministic_per_seed() {
    let (edges, weights) = ([0.0f32, 0.2, 0.5, 0.6, 1.0], [0.1f32, 0.6, 0.05, 0.25]);
    let how = Resampling::new(1.0, 0.01).unwrap();
    let draw = |seed: u64| {
        let (mut a, mut b) = (Vec::new(), Vec::new());
        stratified_edges(16, Some(&mut Rng::stream(seed, 5, 2)), &mut a).unwrap();
        EdgeSampler::default()
            .pdf_edges(&edges, &weights, 16, how, Some(&mut Rng::stream(seed, 5, 2)), &mut b)
            .unwrap();
        (a, b)
    };
    assert_eq!(draw(1), draw(1));
    let (a1, b1) = draw(1);
    let (a2, b2) = draw(2);
    assert!(a1 != a2 && b1 != b2);
}

#[test]
fn pdf_edges_of_a_uniform_histogram_are_the_stratified_edges() {
    let how = Resampling::new(1.0, 0.0).unwrap();
    let mut sampler = EdgeSampler::default();
    for seed in 0..20 {
        let n = 1 + seed as usize;
        let (mut a, mut b) = (Vec::new(), Vec::new());
        stratified_edges(n, Some(&mut Rng::new(seed)), &mut a).unwrap();
        sampler.pdf_edges(&[0.0, 1.0], &[0.3], n, how, Some(&mut Rng::new(seed)), &mut b).unwrap();
        assert_eq!(a, b);
        // Equal bins of equal weight: the same up to rounding.
        let edges: Vec<f32> = (0..=8).map(|k| k as f32 / 8.0).collect();
        b.clear();
        sampler.pdf_edges(&edges, &[0.5; 8], n, how, Some(&mut Rng::new(seed)), &mut b).unwrap();
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-6), "{a:?} {b:?}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn pdf_edges_are_sorted_inside_the_domain_and_n_plus_one(
        raw in proptest::collection::vec(-3.0f32..5.0, 2..40),
        weights in proptest::collection::vec(prop_oneof![Just(0.0f32), 0.0f32..2.0, Just(f32::NAN)], 40),
        n in 1usize..80,
        exponent in prop_oneof![Just(0.0f32), Just(1.0f32), 0.0f32..1.0],
        padding in prop_oneof![Just(0.0f32), 0.0f32..0.1],
        seed in any::<u64>(),
        jitter in any::<bool>(),
    ) {
        let mut edges = raw;
        edges.sort_by(f32::total_cmp);
        let weights = &weights[..edges.len() - 1];
        let how = Resampling::new(exponent, padding).unwrap();
        let mut out = vec![-100.0];
        let mut rng = Rng::new(seed);
        let rng = jitter.then_some(&mut rng);
        EdgeSampler::default().pdf_edges(&edges, weights, n, how, rng, &mut out).unwrap();
        let drawn = &out[1..];
        let m = edges.len() - 1;
        prop_assert_eq!(drawn.len(), n + 1);
        prop_assert_eq!((drawn[0], drawn[n]), (edges[0], edges[m]));
        prop_assert!(drawn.windows(2).all(|p| p[0] <= p[1]), "not sorted: {:?}", drawn);
        prop_assert!(drawn.iter().all(|e| (edges[0]..=edges[m]).contains(e)), "outside: {:?}", drawn);
    }
}

/// The normalised CDF of masses `w^exponent + padding`, in f64.
fn cdf_f64(weights: &[f32], exponent: f64, padding: f64) -> Vec<f64> {
    let masses: Vec<f64> = weights.iter().map(|&w| (w as f64).powf(exponent) + padding).collect();
    let total: f64 = masses.iter().sum();
    let mut c = vec![0.0];
    for m in masses {
        c.push(c.last().unwrap() + m / total);
    }
    c
}

#[test]
fn edges_follow_the_weights() {
    // Bins of unequal widths, one of them empty. The inner edges of a ray sit
    // at the quantiles (k - 1/2 + r)/n, k = 1..n-1: over rays (r uniform) they
    // cover the quantiles [1/2n, 1 - 1/2n] evenly, so bin j's expected count
    // per ray is n |[C_j, C_j+1] ∩ [1/2n, 1 - 1/2n]|. Within one ray the
    // count is one of two neighbouring integers (a shifted lattice), so its
    // variance is at most 1/4 and the count over R independent rays is
    // within 5 sqrt(R)/2 of its mean but for a chance below 1e-6.
    let edges = [0.0f32, 0.1, 0.35, 0.4, 0.8, 1.0];
    let (n, rays) = (16usize, 4000u64);
    for (weights, exponent, padding) in [
        ([0.05f32, 0.5, 0.0, 0.3, 0.1], 1.0f32, 0.01f32),
        ([0.04, 0.25, 0.0, 0.49, 0.01], 0.5, 0.0),
        ([0.04, 0.25, 0.0, 0.49, 0.01], 0.0, 0.01),
    ] {
        let how = Resampling::new(exponent, padding).unwrap();
        let c = cdf_f64(&weights, exponent as f64, padding as f64);
        let mut counts = [0u64; 5];
        let (mut sampler, mut out) = (EdgeSampler::default(), Vec::new());
        for r in 0..rays {
            out.clear();
            sampler.pdf_edges(&edges, &weights, n, how, Some(&mut Rng::stream(7, 0, r)), &mut out).unwrap();
            for &e in &out[1..n] {
                counts[edges[1..].iter().position(|&hi| e < hi).unwrap_or(4)] += 1;
            }
        }
        let (lo, hi) = (0.5 / n as f64, 1.0 - 0.5 / n as f64);
        for j in 0..5 {
            let expected = rays as f64 * n as f64 * (c[j + 1].min(hi) - c[j].max(lo)).max(0.0);
            let tol = 5.0 * (rays as f64).sqrt() / 2.0;
            assert!(
                (counts[j] as f64 - expected).abs() <= tol,
                "exponent {exponent}: bin {j} has {} edges, expected {expected:.0} ± {tol:.0} ({counts:?})",
                counts[j]
            );
        }
    }
}

#[test]
fn edges_without_jitter_are_the_quantiles() {
    let edges = [0.0f32, 0.1, 0.35, 0.4, 0.8, 1.0];
    let weights = [0.05f32, 0.5, 0.0, 0.3, 0.1];
    let c = cdf_f64(&weights, 1.0, 0.01);
    let n = 10;
    let mut out = Vec::new();
    EdgeSampler::default().pdf_edges(&edges, &weights, n, Resampling::new(1.0, 0.01).unwrap(), None, &mut out).unwrap();
    for (k, &e) in out.iter().enumerate() {
        let u = k as f64 / n as f64;
        let j = (0..5).find(|&j| c[j + 1] >= u).unwrap_or(4);
        let want = edges[j] as f64 + (u - c[j]) / (c[j + 1] - c[j]) * (edges[j + 1] - edges[j]) as f64;
        assert!((e as f64 - want).abs() < 1e-5, "edge {k}: {e} vs {want}");
    }
}

#[test]
fn bad_histograms_and_settings_are_errors() {
    let how = Resampling::new(1.0, 0.01).unwrap();
    let mut s = EdgeSampler::default();
    let mut out = Vec::new();
    assert_eq!(s.pdf_edges(&[0.0], &[], 4, how, None, &mut out), Err(ProposalError::NoIntervals));
    assert_eq!(s.pdf_edges(&[0.0, 1.0], &[1.0], 0, how, None, &mut out), Err(ProposalError::NoIntervals));
    assert_eq!(
        s.pdf_edges(&[0.0, 1.0], &[1.0, 1.0], 4, how, None, &mut out),
        Err(ProposalError::Length { what: "edges", expected: 3, got: 2 })
    );
    assert_eq!(
        s.pdf_edges(&[0.0, 1.0, 0.5], &[1.0, 1.0], 4, how, None, &mut out),
        Err(ProposalError::Unsorted { what: "edges", index: 2, value: 0.5 })
    );
    assert!(out.is_empty(), "nothing is appended on an error");
    for (e, p) in [(-0.5, 0.0), (f32::NAN, 0.0), (1.0, -0.01), (1.0, f32::INFINITY)] {
        assert!(Resampling::new(e, p).is_err(), "{e} {p}");
    }
    for b in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        assert!(matches!(Anneal::new(500, b), Err(ProposalError::Slope(_))), "{b}");
    }
}

// ---- annealing ----

#[test]
fn anneal_rises_from_zero_to_one() {
    let a = Anneal::new(500, 10.0).unwrap();
    assert_eq!((a.exponent(0), a.exponent(500), a.exponent(10_000)), (0.0, 1.0, 1.0));
    // x = 1/2: 10 (1/2) / (9 (1/2) + 1) = 5 / 5.5.
    assert!((a.exponent(250) - 5.0 / 5.5).abs() < 1e-6);
    let e: Vec<f32> = (0..=500).map(|s| a.exponent(s)).collect();
    assert!(e.windows(2).all(|p| p[0] < p[1]), "strictly rising");
    // Slope 1 is linear; no steps is no annealing.
    assert!((Anneal::new(100, 1.0).unwrap().exponent(30) - 0.3).abs() < 1e-6);
    assert_eq!(Anneal::new(0, 10.0).unwrap().exponent(0), 1.0);
}

// ---- samples for the render loop ----

mod render {
    use super::*;
    use crate::engine::batch::RayOutput;
    use crate::engine::fields::toy::{Toy, ToyCtx};
    use crate::engine::fields::{Field, Points};
    use crate::engine::render::composite::{CompositeOptions, RaySamples, composite};
    use crate::engine::render::rounds::{RoundSettings, render_in_rounds};

    const W: [f32; 8] = [1.5, -0.5, 0.8, 0.4, -1.0, 0.7, 0.3, -0.2];
    const BG: [f32; 3] = [0.9, 0.2, 0.6];

    /// Six rays: edges from the warp and stratified edges (12 and 40
    /// intervals), none, a single edge, one interval, and uneven edges.
    fn batch() -> (Vec<Ray>, RayEdges) {
        let rays: Vec<Ray> = (0..6)
            .map(|k| Ray { origin: Vec3::new(-1.0, 0.1 * k as f32, 0.2), dir: Vec3::new(0.8, 0.0, 0.6) })
            .collect();
        let mut edges = RayEdges::default();
        for (r, n) in [(0usize, 12usize), (1, 0), (2, 1), (3, 2), (4, 40), (5, 6)] {
            let mut t = Vec::new();
            match n {
                0 => {}
                1 => t.push(0.7),
                2 => t.extend([0.6, 0.9]),
                6 => t.extend([0.3, 0.31, 0.5, 0.5, 0.8, 2.0]),
                _ => {
                    let warp = Warp::for_ray(&rays[r], 0.05, 3.0).unwrap();
                    let mut s = Vec::new();
                    stratified_edges(n, Some(&mut Rng::stream(1, 0, r as u64)), &mut s).unwrap();
                    warp.t_edges(&s, &mut t);
                }
            }
            edges.push(&t).unwrap();
        }
        (rays, edges)
    }

    /// Each ray composited whole by `composite` over the packed samples.
    fn reference(opaque_last: bool) -> Vec<RayOutput> {
        let (rays, edges) = batch();
        let mut m = Samples::default();
        pack(&rays, &edges, &mut m).unwrap();
        let mut ctx = ToyCtx::default();
        Toy.density(&W, Points { pos: &m.pos, dirs: &m.dirs, image: &[] }, &mut ctx);
        Toy.color(&W, &m.dirs, &mut ctx);
        let (sigma, rgb) = (Toy.sigma(&ctx), Toy.rgb(&ctx));
        let opts = CompositeOptions { background: BG, min_transmittance: 0.0, opaque_last };
        m.spans
            .iter()
            .map(|&(o, k)| {
                let s = RaySamples::new(&sigma[o..o + k], &rgb[3 * o..3 * (o + k)], &m.t[o..o + k], &m.delta[o..o + k]);
                let mut w = vec![0.0; k];
                let c = composite(s.unwrap(), &opts, &mut w).unwrap();
                RayOutput { rgb: c.rgb, depth: c.depth, opacity: c.opacity, median: c.median }
            })
            .collect()
    }

    #[test]
    fn rendering_in_rounds_is_the_compositor_bit_for_bit() {
        for opaque_last in [false, true] {
            let want = reference(opaque_last);
            assert_eq!((want[1].rgb, want[2].rgb), (BG, BG), "rays without intervals show the background");
            assert_eq!(want[3].opacity == 1.0, opaque_last);
            for round in [1, 3, 16] {
                let (rays, edges) = batch();
                let mut sampler = ProposalRays::new(&rays, &edges, opaque_last).unwrap();
                let settings = RoundSettings { round, min_transmittance: 0.0, max_dropped_weight: 0.0 };
                let mut out = vec![RayOutput::default(); rays.len()];
                let (mut ctx, mut m) = (ToyCtx::default(), Samples::default());
                let stats = render_in_rounds(&Toy, &W, &mut sampler, settings, BG, &mut ctx, &mut m, &mut out);
                assert_eq!(out, want, "round {round}, opaque last {opaque_last}");
                assert_eq!(stats.samples, 12 + 1 + 40 + 5);
            }
        }
    }

    #[test]
    fn samples_sit_at_interval_midpoints() {
        let (rays, edges) = batch();
        let mut m = Samples::default();
        pack(&rays, &edges, &mut m).unwrap();
        assert_eq!(m.spans, [(0, 12), (12, 0), (12, 0), (12, 1), (13, 40), (53, 5)]);
        let (o, e) = (53, [0.3f32, 0.31, 0.5, 0.5, 0.8, 2.0]);
        for j in 0..5 {
            let t = 0.5 * (e[j] + e[j + 1]);
            assert_eq!((m.t[o + j], m.delta[o + j]), (t, e[j + 1] - e[j]));
            let p = rays[5].at(t);
            assert_eq!(m.pos[3 * (o + j)..3 * (o + j) + 3], [p.x, p.y, p.z]);
            assert_eq!(m.dirs[3 * (o + j)..3 * (o + j) + 3], [0.8, 0.0, 0.6]);
        }
        // Handed out in rounds: the same samples, the last one infinitely
        // long when opaque.
        let mut sampler = ProposalRays::new(&rays, &edges, true).unwrap();
        let mut got = Samples::default();
        assert!(sampler.next(5, 3, &mut got));
        assert!(!sampler.next(5, 3, &mut got));
        assert!(!sampler.next(5, 3, &mut got), "a finished ray stays finished");
        assert_eq!(got.t, m.t[o..o + 5]);
        assert_eq!(got.delta[..4], m.delta[o..o + 4]);
        assert_eq!(got.delta[4], f32::INFINITY);
        assert!(!sampler.has_samples(1) && !sampler.has_samples(2) && sampler.has_samples(3));
        assert!(!sampler.has_samples(99) && !sampler.next(99, 4, &mut got), "rays out of range have nothing");
    }

    #[test]
    fn mismatched_batches_are_errors() {
        let (rays, edges) = batch();
        let err = ProposalRays::new(&rays[..5], &edges, false).err().unwrap();
        assert_eq!(err, ProposalError::Length { what: "ray edges", expected: 5, got: 6 });
        assert_eq!(pack(&rays[..2], &edges, &mut Samples::default()).unwrap_err(), err_for(2));
        let mut e = RayEdges::default();
        assert_eq!(e.push(&[0.5, 0.4]), Err(ProposalError::Unsorted { what: "ray edges", index: 1, value: 0.4 }));
        assert_eq!(e.rays(), 0, "a refused ray is not added");
    }

    fn err_for(rays: usize) -> ProposalError {
        ProposalError::Length { what: "ray edges", expected: rays, got: 6 }
    }
}
