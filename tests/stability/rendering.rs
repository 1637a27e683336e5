//! Volume rendering with extreme inputs.

use proptest::prelude::*;
use radiance::engine::render::composite::{
    Composite, CompositeOptions, RaySamples, Upstream, composite as composite_with, composite_backward as backward_with,
};
use radiance::engine::rng::Rng;

/// Densities from 0 to 1e30, and infinity.
fn density() -> BoxedStrategy<f32> {
    prop_oneof![
        2 => Just(0.0f32),
        2 => Just(f32::INFINITY),
        1 => Just(1e30f32),
        6 => (-30.0f32..30.0).prop_map(|e| 10f32.powf(e)),
        1 => 0.0f32..1e30,
    ]
    .boxed()
}

/// Interval lengths from 1e-12 to 1e3 (and exactly 0, which `deltas` makes
/// for coincident samples).
fn step_size() -> impl Strategy<Value = f32> {
    prop_oneof![
        1 => Just(0.0f32),
        1 => Just(1e-12f32),
        1 => Just(1e3f32),
        6 => (-12.0f32..3.0).prop_map(|e| 10f32.powf(e)),
    ]
}

/// A ray of `n` samples: sigma, rgb, t (sorted, from the deltas), delta.
type RayInputs = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);

fn ray_inputs(sigma: BoxedStrategy<f32>) -> impl Strategy<Value = RayInputs> {
    (1usize..48).prop_flat_map(move |n| {
        (
            proptest::collection::vec(sigma.clone(), n),
            proptest::collection::vec(0.0f32..=1.0, 3 * n),
            proptest::collection::vec(step_size(), n),
            0.0f32..10.0,
        )
            .prop_map(|(sigma, rgb, delta, near)| {
                let mut t = Vec::with_capacity(delta.len());
                let mut x = near;
                for d in &delta {
                    t.push(x + 0.5 * d);
                    x += d;
                }
                (sigma, rgb, t, delta)
            })
    })
}

/// The compositor with a background and an early stop only.
fn composite(
    sigma: &[f32],
    rgb: &[f32],
    t: &[f32],
    delta: &[f32],
    bg: [f32; 3],
    min_t: f32,
    w: &mut [f32],
) -> Composite {
    let s = RaySamples::new(sigma, rgb, t, delta).unwrap();
    let opts = CompositeOptions { background: bg, min_transmittance: min_t, opaque_last: false };
    composite_with(s, &opts, w).unwrap()
}

/// Its backward for colour and depth gradients.
#[allow(clippy::too_many_arguments)]
fn composite_backward(
    sigma: &[f32],
    rgb: &[f32],
    t: &[f32],
    delta: &[f32],
    w: &[f32],
    bg: [f32; 3],
    used: usize,
    g: [f32; 3],
    gd: f32,
    ds: &mut [f32],
    dc: &mut [f32],
) {
    let s = RaySamples::new(sigma, rgb, t, delta).unwrap();
    let opts = CompositeOptions { background: bg, min_transmittance: 0.0, opaque_last: false };
    backward_with(s, w, &opts, used, Upstream { rgb: g, depth: gd, weights: None }, ds, dc).unwrap();
}

/// Checks every invariant of one composite and its backward pass.
#[allow(clippy::too_many_arguments)]
fn check_composite(
    sigma: &[f32],
    rgb: &[f32],
    t: &[f32],
    delta: &[f32],
    bg: [f32; 3],
    min_t: f32,
    g: [f32; 3],
    gd: f32,
) {
    let n = sigma.len();
    let mut w = vec![f32::NAN; n];
    let c = composite(sigma, rgb, t, delta, bg, min_t, &mut w);
    assert!(c.used <= n);
    for (i, &wi) in w.iter().enumerate() {
        assert!((0.0..=1.0).contains(&wi), "weight {i} = {wi}");
    }
    let sum: f32 = w.iter().sum();
    assert!(sum <= 1.0 + 1e-5, "weights sum to {sum}");
    assert!((0.0..=1.0).contains(&c.opacity), "opacity {}", c.opacity);
    assert!((sum - c.opacity).abs() <= 1e-5, "weights sum {sum} but opacity {}", c.opacity);
    // The colour is a convex combination of the sample colours and the background.
    for k in 0..3 {
        let lo = (0..n).map(|i| rgb[3 * i + k]).fold(bg[k], f32::min);
        let hi = (0..n).map(|i| rgb[3 * i + k]).fold(bg[k], f32::max);
        assert!(c.rgb[k].is_finite() && c.rgb[k] >= lo - 1e-5 && c.rgb[k] <= hi + 1e-5, "rgb {:?}", c.rgb);
    }
    let tmax = t.iter().copied().fold(0.0, f32::max);
    assert!(c.depth.is_finite() && c.depth >= 0.0 && c.depth <= tmax * (1.0 + 1e-5), "depth {}", c.depth);
    // Transmittance T_i = 1 - sum_{j<i} w_j never increases along the ray,
    // and a prefix of the ray is never more opaque than the whole ray.
    let mut prev_opacity = 0.0f32;
    for k in 1..=n {
        let mut wk = vec![0.0; k];
        let ck = composite(&sigma[..k], &rgb[..3 * k], &t[..k], &delta[..k], bg, 0.0, &mut wk);
        assert!(ck.opacity >= prev_opacity, "transmittance rose at sample {k}: {prev_opacity} -> {}", ck.opacity);
        prev_opacity = ck.opacity;
    }
    // Gradients are finite.
    let mut ds = vec![f32::NAN; n];
    let mut dc = vec![f32::NAN; 3 * n];
    composite_backward(sigma, rgb, t, delta, &w, bg, c.used, g, gd, &mut ds, &mut dc);
    assert!(ds.iter().all(|v| v.is_finite()), "dsigma {ds:?}");
    assert!(dc.iter().all(|v| v.is_finite()), "drgb {dc:?}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn composite_survives_extreme_densities_and_steps(
        (sigma, rgb, t, delta) in ray_inputs(density()),
        bg in proptest::array::uniform3(0.0f32..=1.0),
        min_t in prop_oneof![Just(0.0f32), Just(1e-4f32), Just(0.5f32)],
        g in proptest::array::uniform3(-10.0f32..10.0),
        gd in -1.0f32..1.0,
    ) {
        check_composite(&sigma, &rgb, &t, &delta, bg, min_t, g, gd);
    }

    #[test]
    fn composite_survives_negative_and_nan_densities(
        (sigma, rgb, t, delta) in ray_inputs(prop_oneof![Just(f32::NAN), Just(-1.0f32), Just(f32::NEG_INFINITY), density()].boxed()),
        bg in proptest::array::uniform3(0.0f32..=1.0),
    ) {
        // Garbage densities count as empty space; nothing becomes NaN.
        check_composite(&sigma, &rgb, &t, &delta, bg, 0.0, [1.0, -1.0, 0.5], 0.25);
    }

    #[test]
    fn all_zero_and_all_opaque_rays(
        (_, rgb, t, delta) in ray_inputs(Just(0.0f32).boxed()),
        bg in proptest::array::uniform3(0.0f32..=1.0),
    ) {
        let n = t.len();
        let mut w = vec![0.0; n];
        let c = composite(&vec![0.0; n], &rgb, &t, &delta, bg, 0.0, &mut w);
        prop_assert_eq!(c.rgb, bg);
        prop_assert_eq!(c.opacity, 0.0);
        prop_assert!(w.iter().all(|&x| x == 0.0));
        check_composite(&vec![0.0; n], &rgb, &t, &delta, bg, 0.0, [1.0; 3], 1.0);
        // Infinite density everywhere: the first sample of non-zero length takes all.
        let sigma = vec![f32::INFINITY; n];
        let c = composite(&sigma, &rgb, &t, &delta, bg, 0.0, &mut w);
        match delta.iter().position(|&d| d > 0.0) {
            Some(i) => {
                prop_assert_eq!(w[i], 1.0);
                prop_assert_eq!(c.opacity, 1.0);
                prop_assert_eq!(&c.rgb[..], &rgb[3 * i..3 * i + 3]);
            }
            None => prop_assert_eq!(c.rgb, bg),
        }
        check_composite(&sigma, &rgb, &t, &delta, bg, 0.0, [1.0; 3], 1.0);
    }
}

/// The f64 reference: alpha compositing straight from the definition.
fn composite_f64(sigma: &[f32], rgb: &[f32], t: &[f32], delta: &[f32], bg: [f32; 3]) -> ([f64; 3], f64, f64) {
    let mut trans = 1.0f64;
    let (mut c, mut d) = ([0.0f64; 3], 0.0f64);
    for i in 0..sigma.len() {
        let alpha = 1.0 - (-(sigma[i] as f64) * delta[i] as f64).exp();
        let w = trans * alpha;
        for k in 0..3 {
            c[k] += w * rgb[3 * i + k] as f64;
        }
        d += w * t[i] as f64;
        trans *= 1.0 - alpha;
    }
    for k in 0..3 {
        c[k] += trans * bg[k] as f64;
    }
    (c, d, 1.0 - trans)
}

/// Tolerance of the f32 renderer against the f64 reference, for up to 256
/// samples with densities up to 1e4 and steps up to 1 (model units): colour
/// and opacity within `COLOUR_TOL` absolute, depth within `DEPTH_TOL` of the
/// ray's far end.
const COLOUR_TOL: f64 = 2e-5;
const DEPTH_TOL: f64 = 2e-5;

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn f32_composite_agrees_with_f64_reference(
        n in 1usize..256,
        seed in any::<u64>(),
        sigma_exp in -3.0f32..4.0,
        bg in proptest::array::uniform3(0.0f32..=1.0),
    ) {
        let mut rng = Rng::new(seed);
        let smax = 10f32.powf(sigma_exp);
        let sigma: Vec<f32> = (0..n).map(|_| if rng.f32() < 0.3 { 0.0 } else { rng.f32() * smax }).collect();
        let rgb: Vec<f32> = (0..3 * n).map(|_| rng.f32()).collect();
        let delta: Vec<f32> = (0..n).map(|_| rng.f32() * 4.0 / n as f32).collect();
        let mut t = Vec::with_capacity(n);
        let mut x = 2.0f32;
        for d in &delta {
            t.push(x + 0.5 * d);
            x += d;
        }
        let mut w = vec![0.0; n];
        let c = composite(&sigma, &rgb, &t, &delta, bg, 0.0, &mut w);
        let (rc, rd, ro) = composite_f64(&sigma, &rgb, &t, &delta, bg);
        for k in 0..3 {
            prop_assert!((rc[k] - c.rgb[k] as f64).abs() <= COLOUR_TOL, "rgb {:?} vs {:?}", c.rgb, rc);
        }
        prop_assert!((ro - c.opacity as f64).abs() <= COLOUR_TOL, "opacity {} vs {}", c.opacity, ro);
        prop_assert!((rd - c.depth as f64).abs() <= DEPTH_TOL * x as f64, "depth {} vs {}", c.depth, rd);
    }
}
