//! Numerical stability: tests that try hard to break the engine.
//!
//! Volume rendering, inverse-CDF sampling, encodings and cameras under
//! extreme inputs (property tests), f32 against an f64 reference, scale
//! invariance, degenerate datasets, a long run, the trainer's divergence
//! guard, bit-identical checkpoints and fuzzed dataset parsers.

use std::path::Path;
use std::sync::atomic::AtomicBool;

use proptest::prelude::*;

use radiance::engine::geometry::camera::{Camera, Distortion};
use radiance::engine::nn::encoding::{encode, encode_backward, encoded_width};
use radiance::engine::render::composite::{composite, composite_backward};
use radiance::engine::rng::Rng;
use radiance::engine::sampling::stratified::sample_pdf;

// ---------------------------------------------------------------------------
// Volume rendering with extreme inputs.

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

// ---------------------------------------------------------------------------
// Inverse-CDF sampling.

fn nasty_weight() -> impl Strategy<Value = f32> {
    prop_oneof![
        3 => Just(0.0f32),
        1 => Just(1e-30f32),
        1 => Just(1e-45f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
        1 => Just(-1.0f32),
        1 => Just(f32::MAX),
        1 => Just(1e38f32),
        4 => 0.0f32..1.0,
        2 => (-30.0f32..38.0).prop_map(|e| 10f32.powf(e)),
    ]
}

/// Sorted bin edges (coincident edges included).
fn bin_edges(bins: usize) -> impl Strategy<Value = Vec<f32>> {
    (
        -1e3f32..1e3,
        proptest::collection::vec(
            prop_oneof![1 => Just(0.0f32), 4 => (-6.0f32..3.0).prop_map(|e| 10f32.powf(e))],
            bins,
        ),
    )
        .prop_map(|(start, steps)| {
            let mut e = vec![start];
            for s in steps {
                let last = *e.last().unwrap();
                e.push(last + s);
            }
            e
        })
}

fn check_samples(edges: &[f32], out: &[f32], n: usize) {
    let (lo, hi) = (edges[0], edges[edges.len() - 1]);
    assert_eq!(out.len(), n);
    for &s in out {
        assert!(s.is_finite() && s >= lo && s <= hi, "sample {s} outside [{lo}, {hi}]");
    }
    assert!(out.windows(2).all(|p| p[0] <= p[1]), "not sorted: {out:?}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    #[test]
    fn sample_pdf_is_sorted_finite_and_inside(
        (edges, weights) in (1usize..64).prop_flat_map(|b| (bin_edges(b), proptest::collection::vec(nasty_weight(), b))),
        n in 1usize..200,
        seed in proptest::option::of(any::<u64>()),
    ) {
        let mut rng = seed.map(Rng::new);
        let mut out = Vec::new();
        sample_pdf(&edges, &weights, n, rng.as_mut(), &mut out);
        check_samples(&edges, &out, n);
    }

    #[test]
    fn sample_pdf_all_zero_and_tiny_weights_are_uniform(
        bins in 1usize..64,
        tiny in prop_oneof![Just(0.0f32), Just(1e-45f32), Just(1e-30f32), Just(1e-12f32)],
        n in 64usize..256,
    ) {
        let edges: Vec<f32> = (0..=bins).map(|i| 2.0 + 4.0 * i as f32 / bins as f32).collect();
        let mut out = Vec::new();
        sample_pdf(&edges, &vec![tiny; bins], n, None, &mut out);
        check_samples(&edges, &out, n);
        // Uniform: the k-th sample sits at the k-th quantile of [2, 6].
        for (k, &s) in out.iter().enumerate() {
            let want = 2.0 + 4.0 * (k as f32 + 0.5) / n as f32;
            prop_assert!((s - want).abs() < 1e-3, "sample {k}: {s} vs {want}");
        }
    }

    #[test]
    fn sample_pdf_one_hot_concentrates_at_any_magnitude(
        bins in 2usize..64,
        hot in any::<prop::sample::Index>(),
        // a hot bin that dominates the 1e-5 padding of the others, up to f32::MAX
        magnitude in prop_oneof![Just(1.0f32), Just(0.5f32), Just(1e30f32), Just(1e38f32), Just(f32::MAX)],
        seed in any::<u64>(),
    ) {
        let hot = hot.index(bins);
        let edges: Vec<f32> = (0..=bins).map(|i| i as f32).collect();
        let mut w = vec![0.0f32; bins];
        w[hot] = magnitude;
        let mut out = Vec::new();
        sample_pdf(&edges, &w, 128, Some(&mut Rng::new(seed)), &mut out);
        check_samples(&edges, &out, 128);
        let inside = out.iter().filter(|&&s| s >= hot as f32 && s <= hot as f32 + 1.0).count();
        prop_assert!(inside >= 120, "{inside} of 128 samples in the hot bin {hot}");
        // Equal huge weights in every bin give the uniform density, as equal small ones do.
        let mut out = Vec::new();
        sample_pdf(&edges, &vec![magnitude; bins], 128, None, &mut out);
        check_samples(&edges, &out, 128);
        for (k, &s) in out.iter().enumerate() {
            let want = bins as f32 * (k as f32 + 0.5) / 128.0;
            prop_assert!((s - want).abs() < 1e-3 * bins as f32, "equal weights {magnitude}: sample {k} at {s}, want {want}");
        }
    }
}

// ---------------------------------------------------------------------------
// Encodings at the domain's edges, cameras with odd directions.

fn coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(-1.0f32),
        Just(1.0f32),
        Just(0.0f32),
        Just(-0.0f32),
        Just(1.0000001f32),
        Just(-1.5f32),
        Just(1e3f32),
        Just(-1e30f32),
        Just(f32::MAX),
        Just(f32::MIN),
        Just(f32::MIN_POSITIVE),
        -1.0f32..=1.0,
        any::<f32>().prop_filter("finite", |v| v.is_finite()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn encodings_are_finite_and_bounded_for_any_finite_point(
        pts in proptest::collection::vec(coordinate(), 3..=30).prop_map(|mut v| { v.truncate(v.len() / 3 * 3); v }),
        freqs in 0usize..=10,
        g in -100.0f32..100.0,
    ) {
        let w = encoded_width(3, freqs);
        let n = pts.len() / 3;
        let mut out = vec![f32::NAN; n * w];
        encode(&pts, 3, freqs, &mut out);
        for (p, o) in pts.chunks(3).zip(out.chunks(w)) {
            prop_assert_eq!(&o[..3], p, "the input passes through");
            prop_assert!(o[3..].iter().all(|v| v.is_finite() && v.abs() <= 1.0), "{:?} -> {:?}", p, o);
        }
        let dout = vec![g; n * w];
        let mut dx = vec![0.0f32; pts.len()];
        encode_backward(&pts, 3, freqs, &dout, &mut dx);
        prop_assert!(dx.iter().all(|v| v.is_finite()), "{:?}", dx);
    }

    #[test]
    fn camera_rays_are_unit_and_finite_for_any_pose(
        rot in proptest::array::uniform9(prop_oneof![Just(0.0f32), -1.0f32..1.0, (-15.0f32..15.0).prop_map(|e| 10f32.powf(e)), (-15.0f32..15.0).prop_map(|e| -(10f32.powf(e)))]),
        focal in prop_oneof![Just(0.0f32), Just(1e-30f32), Just(f32::INFINITY), 0.1f32..1e4],
        uv in proptest::array::uniform2(prop_oneof![Just(0.0f32), Just(-1e30f32), Just(1e30f32), -10.0f32..110.0]),
        distorted in any::<bool>(),
    ) {
        let c2w = [[rot[0], rot[1], rot[2], 1.0], [rot[3], rot[4], rot[5], -2.0], [rot[6], rot[7], rot[8], 3.0]];
        let mut cam = Camera::from_fov(100, 80, 1.0, c2w);
        cam.fx = focal;
        cam.fy = focal;
        if distorted {
            cam.distortion = Distortion { k1: 0.3, k2: -0.2, p1: 0.01, p2: -0.01 };
        }
        let r = cam.ray(uv[0], uv[1]);
        prop_assert!(r.dir.is_finite(), "{:?}", r.dir);
        prop_assert!((r.dir.norm() - 1.0).abs() < 1e-5, "|dir| = {}", r.dir.norm());
    }

    #[test]
    fn scaled_rotations_give_the_same_rays(
        angle in 0.0f32..6.3,
        scale_exp in -15.0f32..15.0,
        uv in proptest::array::uniform2(0.0f32..100.0),
    ) {
        // A pose whose rotation is not normalised still looks the same way.
        let (s, c) = angle.sin_cos();
        let rot = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]];
        let k = 10f32.powf(scale_exp);
        let pose = |k: f32| [[rot[0][0] * k, rot[0][1] * k, rot[0][2] * k, 0.5], [rot[1][0] * k, rot[1][1] * k, rot[1][2] * k, 0.0], [rot[2][0] * k, rot[2][1] * k, rot[2][2] * k, 0.0]];
        let a = Camera::from_fov(100, 100, 0.8, pose(1.0)).ray(uv[0], uv[1]);
        let b = Camera::from_fov(100, 100, 0.8, pose(k)).ray(uv[0], uv[1]);
        prop_assert!((a.dir - b.dir).norm() < 1e-5, "{:?} vs {:?}", a.dir, b.dir);
    }
}

// ---------------------------------------------------------------------------
// Fuzzing the dataset parsers.

use radiance::engine::dataset::{Dataset, LoadOptions, parse_npy};

/// Loads `root` on another thread: must return (Ok or Err) within 10 s.
fn load_no_hang(root: &Path) -> Result<Dataset, String> {
    let root = root.to_path_buf();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let r = std::panic::catch_unwind(|| Dataset::load(&root, &LoadOptions::default()).map_err(|e| e.to_string()));
        let _ = tx.send(r);
    });
    match rx.recv_timeout(std::time::Duration::from_secs(10)) {
        Ok(Ok(r)) => r,
        Ok(Err(_)) => panic!("Dataset::load panicked"),
        Err(_) => panic!("Dataset::load hung"),
    }
}

fn tiny_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbaImage::from_pixel(4, 3, image::Rgba([10, 200, 30, 128])).save(path).unwrap();
}

/// JSON values that stress number handling.
fn nasty_json_number() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_string()),
        Just("-1".to_string()),
        Just("1e308".to_string()),
        Just("-1e308".to_string()),
        Just("1e-320".to_string()),
        Just("1e400".to_string()),
        Just("18446744073709551616".to_string()),
        Just("4294967296".to_string()),
        Just("null".to_string()),
        Just("\"x\"".to_string()),
        Just("[]".to_string()),
        Just("{}".to_string()),
        Just("true".to_string()),
        (-1e3f64..1e3).prop_map(|v| v.to_string()),
        Just("1".to_string()),
        Just("0.5".to_string()),
    ]
}

/// A Blender or ngp transforms file whose numbers are replaced by nasty values.
fn mutated_transforms(ngp: bool) -> impl Strategy<Value = String> {
    (proptest::collection::vec(nasty_json_number(), 40), proptest::collection::vec(any::<bool>(), 40)).prop_map(
        move |(vals, keep)| {
            // `keep[i]` leaves the i-th number of a valid document alone.
            let mut k = 0;
            let mut v = |good: &str| {
                let out = if keep[k % keep.len()] { good.to_string() } else { vals[k % vals.len()].clone() };
                k += 1;
                out
            };
            let m = format!(
                "[[{},{},{},{}],[{},{},{},{}],[{},{},{},{}],[{},{},{},{}]]",
                v("1"), v("0"), v("0"), v("0.5"), v("0"), v("1"), v("0"), v("0"), v("0"), v("0"), v("1"), v("4"), v("0"), v("0"), v("0"), v("1")
            );
            if ngp {
                format!(
                    r#"{{"fl_x":{},"fl_y":{},"cx":{},"cy":{},"w":{},"h":{},"k1":{},"p1":{},"aabb_scale":{},"scale":{},"offset":[{},{},{}],"frames":[{{"file_path":"img.png","transform_matrix":{m}}},{{"file_path":"img.png","transform_matrix":{m},"fl_x":{}}}]}}"#,
                    v("3"), v("3"), v("2"), v("1.5"), v("4"), v("3"), v("0.1"), v("0.01"), v("4"), v("0.33"), v("0.5"), v("0.5"), v("0.5"), v("2")
                )
            } else {
                format!(
                    r#"{{"camera_angle_x":{},"near":{},"far":{},"frames":[{{"file_path":"./img","transform_matrix":{m}}},{{"file_path":"img.png","transform_matrix":{m},"cx":{}}}]}}"#,
                    v("0.7"), v("2"), v("6"), v("1")
                )
            }
        },
    )
}

/// A valid npy header for shape `(rows, 17)` followed by `data`.
fn npy_bytes(rows: usize, data: &[f64]) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, 17), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    for v in data {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

fn nasty_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(0.0),
        Just(1.0),
        Just(-1.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(1e300),
        Just(1e-300),
        Just(f64::MAX),
        -10.0f64..10.0,
        any::<f64>(),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_as_transforms_json_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..512),
            "[ -~]{0,300}".prop_map(String::into_bytes),
            mutated_transforms(false).prop_map(String::into_bytes),
        ],
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("img.png"));
        let bytes = if truncate && !bytes.is_empty() { bytes[..cut.index(bytes.len())].to_vec() } else { bytes };
        std::fs::write(dir.path().join("transforms_train.json"), &bytes).unwrap();
        let _ = load_no_hang(dir.path());
    }

    #[test]
    fn random_bytes_as_ngp_transforms_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..512),
            mutated_transforms(true).prop_map(String::into_bytes),
        ],
    ) {
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("img.png"));
        std::fs::write(dir.path().join("transforms.json"), &bytes).unwrap();
        if let Ok(ds) = load_no_hang(dir.path()) {
            prop_assert!(ds.aabb.min.is_finite() && ds.aabb.max.is_finite() && ds.far.is_finite());
        }
    }

    #[test]
    fn random_bytes_as_poses_bounds_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..600),
            // a valid header with random values, sometimes short
            (proptest::collection::vec(nasty_f64(), 17), 0usize..3).prop_map(|(row, drop)| {
                let mut b = npy_bytes(1, &row);
                b.truncate(b.len() - drop * 3);
                b
            }),
            // a plausible row with one nasty entry
            (nasty_f64(), 0usize..17).prop_map(|(x, i)| {
                let mut row = [0.0, 1.0, 0.0, 0.5, 3.0, -1.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 1.0, 2.0, 3.5, 1.0, 5.0];
                row[i] = x;
                npy_bytes(1, &row)
            }),
            // random header text after the magic
            "[ -~]{0,120}".prop_map(|h| {
                let mut b = b"\x93NUMPY\x01\x00".to_vec();
                b.extend_from_slice(&(h.len() as u16).to_le_bytes());
                b.extend_from_slice(h.as_bytes());
                b
            }),
        ],
    ) {
        let _ = parse_npy(&bytes, Path::new("poses_bounds.npy"));
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("images_8/a.png"));
        std::fs::write(dir.path().join("poses_bounds.npy"), &bytes).unwrap();
        if let Ok(ds) = load_no_hang(dir.path()) {
            prop_assert!(ds.aabb.min.is_finite() && ds.aabb.max.is_finite() && ds.near > 0.0 && ds.far > ds.near);
        }
    }
}

// ---------------------------------------------------------------------------
// Whole models: odd rays, scale, degenerate datasets, long runs, the
// divergence guard and determinism.

use radiance::engine::dataset::Split;
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::geometry::math::{Ray, Vec3};
use radiance::engine::geometry::scene::Scene;
use radiance::engine::io::persist;
use radiance::engine::metrics::psnr;
use radiance::engine::models::nerf::{NerfConfig, NerfModel};
use radiance::engine::models::{Model, RayOutput, StepCtx, TrainRay};
use radiance::engine::nn::adam::{Adam, AdamConfig};
use radiance::engine::nn::nerf_net::NetConfig;
use radiance::engine::render::render_view;
use radiance::engine::sampling::occupancy::OccupancyConfig;
use radiance::engine::train::trainer::{Budget, DivergenceGuard, StopReason, TrainConfig, TrainState, Trainer};

/// A very small classic model (tests/checkpoint_resume.rs's shape).
fn micro_config(occupancy: bool) -> NerfConfig {
    NerfConfig {
        net: NetConfig { pos_freqs: 3, dir_freqs: 1, width: 16, depth: 3, skip: 1, dir_width: 8 },
        coarse_samples: 8,
        fine_samples: 8,
        occupancy: occupancy.then(|| OccupancyConfig {
            resolution: 8,
            update_every: 4,
            sweep: 2,
            warmup_steps: 8,
            ..Default::default()
        }),
        ..Default::default()
    }
}

fn trainer_for<'a>(model: Box<dyn Model>, ds: &'a Dataset, steps: u64, batch: usize, lr: f32) -> Trainer<'a> {
    let adam = Adam::new(AdamConfig { lr, lr_end: lr / 10.0, ..Default::default() }, model.params().len());
    let cfg = TrainConfig {
        seed: 9,
        batch_rays: batch,
        budget: Budget { steps: Some(steps), seconds: None },
        ..Default::default()
    };
    Trainer::new(model, adam, cfg, TrainState::default(), ds)
}

fn all_finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

#[test]
fn odd_world_rays_render_finite_pixels() {
    let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
    // `far` as an ngp dataset with cameras a million box sizes away has it.
    let scene = Scene::from_bounds(ds.aabb, 0.0, 1e9);
    let mut config = micro_config(true);
    config.occupancy.as_mut().unwrap().resolution = 32;
    let mut model = NerfModel::new(config, scene, 1);
    // Activate the occupancy grid (everything occupied) so rays march through it.
    let cells = model.grid().unwrap().density.len();
    model.set_grid_state(vec![1e3; cells], 1000).unwrap();
    assert!(model.grid().unwrap().active);
    let origins = [
        Vec3::new(0.1, 0.2, 0.3),
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(-1.0, -1.0, -1.0),
        Vec3::new(0.0, 0.0, -4.0),
        Vec3::new(0.0, 0.0, 1e6),
        Vec3::new(0.0, 0.0, 4e6),
        Vec3::new(3e38, 0.0, 0.0),
        Vec3::new(f32::NAN, 0.0, 0.0),
        Vec3::new(0.0, f32::INFINITY, 0.0),
    ];
    let dirs = [
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(0.0, 0.0, -1.0),
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(1e-30, 0.0, -1e-30),
        Vec3::new(1e30, 2e30, -1e30),
        Vec3::new(f32::NAN, 0.0, 1.0),
        Vec3::new(0.0, f32::NEG_INFINITY, 0.0),
    ];
    let scene = model.scene().clone();
    let rays: Vec<Ray> = origins
        .iter()
        .flat_map(|&origin| dirs.iter().map(move |&dir| Ray { origin, dir }))
        .map(|r| scene.to_model(&r))
        .collect();
    let (tx, rx) = std::sync::mpsc::channel();
    let job = std::thread::spawn(move || {
        let mut out = vec![RayOutput::default(); rays.len()];
        model.render_rays(&rays, [1.0, 0.5, 0.0], &mut out);
        let train: Vec<TrainRay> = rays
            .iter()
            .enumerate()
            .map(|(i, &ray)| TrainRay { ray, target: [0.2; 3], background: [1.0; 3], index: i as u64, image: 0 })
            .collect();
        let mut g = vec![0.0; model.params().len()];
        let s = model.train_rays(&train, &StepCtx { seed: 1, step: 0, batch_rays: train.len() }, &mut g);
        let _ = tx.send((out, s, g));
    });
    let (out, stats, grads) = rx.recv_timeout(std::time::Duration::from_secs(20)).expect("rendering odd rays hung");
    job.join().unwrap();
    for (k, o) in out.iter().enumerate() {
        let (i, j) = (k / dirs.len(), k % dirs.len());
        assert!(
            o.rgb.iter().all(|v| v.is_finite()) && o.depth.is_finite() && (0.0..=1.0).contains(&o.opacity),
            "origin {:?} dir {:?}: {o:?}",
            origins[i],
            dirs[j]
        );
    }
    assert!(stats.loss.is_finite() && all_finite(&grads));
}

/// A trainer whose callback can poison the parameters: a NaN weight makes
/// the loss and every gradient of the following steps non-finite, as a
/// blown-up model does. (Fault injection through the trainer's public API;
/// a `Model` wrapper would tie these tests to the trait's exact shape.)
fn guarded_trainer(ds: &Dataset, steps: u64) -> Trainer<'_> {
    let model = NerfModel::new(micro_config(false), Scene::from_dataset(ds), 3);
    let mut t = trainer_for(Box::new(model), ds, steps, 32, 5e-3);
    t.guard = DivergenceGuard { patience: 5, snapshot_every: 10, max_rollbacks: 3 };
    t
}

/// The index of the poisoned parameter (a weight of the coarse network's first layer).
const POISONED: usize = 7;

#[test]
fn isolated_non_finite_steps_are_skipped() {
    let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
    let mut t = guarded_trainer(&ds, 30);
    // Poison before steps 3, 7, 8 and 20..=23 (never 5 in a row), heal after.
    let poisoned = [3u64, 7, 8, 20, 21, 22, 23];
    let mut good = t.model.params()[POISONED];
    let mut prev = t.model.params().to_vec();
    let reason = t.run(&AtomicBool::new(false), |t, p| {
        let skipped = poisoned.contains(&(p.step - 1));
        assert_eq!(p.loss.is_nan(), skipped, "step {}", p.step);
        if skipped {
            assert!(t.model.params()[POISONED].is_nan());
            t.model.params_mut()[POISONED] = good;
            assert_eq!(t.model.params(), prev.as_slice(), "a skipped step leaves the parameters alone");
        } else {
            assert_ne!(t.model.params(), prev.as_slice(), "a good step moves them");
        }
        prev = t.model.params().to_vec();
        if poisoned.contains(&p.step) {
            good = t.model.params()[POISONED];
            t.model.params_mut()[POISONED] = f32::NAN;
        }
        true
    });
    assert_eq!(reason, StopReason::Budget);
    assert_eq!(t.state.diverged_steps, 7);
    assert_eq!((t.state.rollbacks, t.state.lr_scale), (0, 1.0), "fewer than `patience` in a row: no rollback");
    assert!(all_finite(t.model.params()));
}

#[test]
fn a_burst_of_divergence_rolls_back_with_half_the_learning_rate() {
    let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
    // Snapshots every 10 good steps; the model blows up after step 25.
    let mut t = guarded_trainer(&ds, 40);
    let (mut at20, mut lr_before, mut seen) = (Vec::new(), 0.0f32, None);
    let reason = t.run(&AtomicBool::new(false), |t, p| {
        match p.step {
            20 => at20 = t.model.params().to_vec(),
            25 => t.model.params_mut()[POISONED] = f32::NAN,
            26..=29 => assert!(p.loss.is_nan() && p.rollbacks == 0),
            30 => {
                seen = Some(*p);
                lr_before = t.adam.config.lr_at(t.config.budget.progress(p.step, 0.0));
                assert_eq!(t.model.params(), at20.as_slice(), "rolled back to the snapshot of step 20");
            }
            31.. => assert!(p.loss.is_finite(), "training goes on after the rollback"),
            _ => {}
        }
        true
    });
    assert_eq!(reason, StopReason::Budget);
    let p = seen.unwrap();
    assert_eq!(p.rollbacks, 1, "the rollback is reported in the progress");
    assert_eq!(p.lr, lr_before * 0.5, "the scheduled learning rate is halved");
    assert_eq!((t.state.rollbacks, t.state.lr_scale, t.state.diverged_steps), (1, 0.5, 5));
    assert!(all_finite(t.model.params()));
}

#[test]
fn persistent_divergence_fails_the_run_with_a_clear_error() {
    let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
    let mut t = guarded_trainer(&ds, 500);
    let mut at10 = Vec::new();
    let mut last = None;
    let reason = t.run(&AtomicBool::new(false), |t, p| {
        if p.step == 10 {
            at10 = t.model.params().to_vec();
        }
        // From step 12 on the model blows up after every good step.
        if p.step >= 12 && p.loss.is_finite() {
            t.model.params_mut()[POISONED] = f32::NAN;
        }
        last = Some(*p);
        true
    });
    // Bursts 13..=17, 19..=23, 25..=29 roll back; the fourth (31..=35) fails the run.
    assert_eq!(reason, StopReason::Diverged { step: 35, good_step: 10, rollbacks: 3 });
    let msg = reason.to_string();
    assert!(msg.contains("diverged") && msg.contains("step 10"), "{msg}");
    assert_eq!(last.unwrap().rollbacks, 3);
    assert_eq!(t.state.lr_scale, 0.125);
    assert_eq!(t.model.params(), at10.as_slice(), "left with the last good parameters");
    // ... which can be saved: never a NaN checkpoint.
    let dir = tempfile::tempdir().unwrap();
    persist::save(&dir.path().join("m.ckpt"), &*t.model, &t.adam, &t.config, &t.state).unwrap();
    assert_eq!(persist::load(&dir.path().join("m.ckpt")).unwrap().state.rollbacks, 3);
}

#[test]
fn old_train_states_default_to_full_learning_rate() {
    let old = r#"{"step":3,"elapsed":1.5,"rays":1,"samples":2,"skipped":0,"diverged_steps":0,"smoothed_mse":0.1}"#;
    let s: TrainState = serde_json::from_str(old).unwrap();
    assert_eq!((s.lr_scale, s.rollbacks, s.elapsed), (1.0, 0, 1.5));
}

/// Trains the micro model with occupancy for `steps` on a 2-thread pool and
/// returns the checkpoint.
fn train_checkpoint(ds: &Dataset, steps: u64) -> radiance::engine::io::checkpoint::Checkpoint {
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| {
        let model = NerfModel::new(micro_config(true), Scene::from_dataset(ds), 5);
        let mut t = trainer_for(Box::new(model), ds, steps, 64, 5e-3);
        assert_eq!(t.run(&AtomicBool::new(false), |_, _| true), StopReason::Budget);
        persist::to_checkpoint(&*t.model, &t.adam, &t.config, &t.state)
    })
}

#[test]
fn same_data_config_seed_and_threads_give_a_bit_identical_checkpoint() {
    let ds = BallScene { size: 10, views: 6, ..Default::default() }.dataset();
    let a = train_checkpoint(&ds, 24);
    let b = train_checkpoint(&ds, 24);
    assert_eq!(persist::identity_bytes(&a), persist::identity_bytes(&b), "checkpoints differ");
    // Only the wall-clock time is outside the identity...
    let mut c = b.clone();
    c.meta["timing"]["elapsed"] = serde_json::json!(12345.0);
    assert_eq!(persist::identity_bytes(&a), persist::identity_bytes(&c));
    assert_ne!(c.to_bytes(), b.to_bytes());
    // ... and the state itself holds no time.
    assert!(a.meta["state"].get("elapsed").is_none(), "{}", a.meta["state"]);
    // Anything that is not time changes it.
    let mut d = b.clone();
    d.meta["state"]["step"] = serde_json::json!(25);
    assert_ne!(persist::identity_bytes(&a), persist::identity_bytes(&d));
    // Files on disk: same identity, and the time survives a round trip.
    let dir = tempfile::tempdir().unwrap();
    let (pa, pb) = (dir.path().join("a.ckpt"), dir.path().join("b.ckpt"));
    a.save(&pa).unwrap();
    c.save(&pb).unwrap();
    let (la, lb) = (
        radiance::engine::io::checkpoint::Checkpoint::load(&pa).unwrap(),
        radiance::engine::io::checkpoint::Checkpoint::load(&pb).unwrap(),
    );
    assert_eq!(persist::identity_bytes(&la), persist::identity_bytes(&lb));
    assert_eq!(persist::load(&pb).unwrap().state.elapsed, 12345.0);
}

fn test_psnr(model: &dyn Model, ds: &Dataset) -> f64 {
    let (mut total, mut n) = (0.0, 0);
    for f in ds.split_frames(Split::Test) {
        let v = render_view(model, &f.camera, ds.background);
        let gt: Vec<f32> = (0..f.camera.height)
            .flat_map(|j| (0..f.camera.width).map(move |i| (i, j)))
            .flat_map(|(i, j)| f.image.rgb_on(i, j, ds.background))
            .collect();
        total += psnr(&v.rgb, &gt);
        n += 1;
    }
    total / n as f64
}

#[test]
fn scaled_scenes_train_to_the_same_psnr() {
    let config = NerfConfig {
        net: NetConfig { pos_freqs: 4, dir_freqs: 2, width: 32, depth: 4, skip: 2, dir_width: 16 },
        coarse_samples: 16,
        fine_samples: 16,
        occupancy: Some(OccupancyConfig { resolution: 16, ..Default::default() }),
        ..Default::default()
    };
    let mut results = Vec::new();
    for scale in [1.0f32, 1e-3, 1e3] {
        let ds = BallScene { size: 16, views: 12, scale, ..Default::default() }.dataset();
        let model = NerfModel::new(config.clone(), Scene::from_dataset(&ds), 1);
        let mut t = trainer_for(Box::new(model), &ds, 200, 192, 5e-3);
        assert_eq!(t.run(&AtomicBool::new(false), |_, _| true), StopReason::Budget);
        results.push((scale, test_psnr(&*t.model, &ds)));
    }
    eprintln!("test PSNR by scale: {results:?}");
    let base = results[0].1;
    assert!(base > 22.0, "the scene is learnt at all: {base:.2} dB");
    for &(scale, p) in &results[1..] {
        assert!((p - base).abs() <= 0.5, "scale {scale}: {p:.2} dB vs {base:.2} dB at scale 1");
    }
}

/// Trains a few steps on a degenerate dataset: the run ends with a clear
/// outcome and the model is finite and saveable.
fn train_briefly(name: &str, ds: &Dataset) {
    let model = NerfModel::new(micro_config(true), Scene::from_dataset(ds), 2);
    let mut t = trainer_for(Box::new(model), ds, 30, 64, 1e-2);
    let mut losses = Vec::new();
    let reason = t.run(&AtomicBool::new(false), |_, p| {
        losses.push(p.loss);
        true
    });
    eprintln!("{name}: {reason} after {} steps, last loss {:?}", t.state.step, losses.last());
    assert!(matches!(reason, StopReason::Budget | StopReason::Diverged { .. }), "{name}: {reason:?}");
    assert!(all_finite(t.model.params()), "{name}: non-finite parameters");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    persist::save(&path, &*t.model, &t.adam, &t.config, &t.state).unwrap_or_else(|e| panic!("{name}: {e}"));
    let r = persist::load(&path).unwrap();
    assert!(all_finite(r.model.params()) && all_finite(&r.adam.m) && all_finite(&r.adam.v), "{name}");
    if reason == StopReason::Budget {
        assert_eq!(t.state.diverged_steps, 0, "{name}: steps were skipped");
        assert!(losses.iter().all(|l| l.is_finite()), "{name}: {losses:?}");
    }
}

#[test]
fn degenerate_datasets_train_to_a_clear_outcome() {
    let ball = BallScene { size: 10, views: 6, ..Default::default() };
    train_briefly("one image", &BallScene { views: 1, ..ball }.dataset());

    let mut ds = ball.dataset();
    let first = ds.frames[0].clone();
    for &i in &ds.train {
        ds.frames[i].camera = first.camera.clone();
        ds.frames[i].image = first.image.clone();
    }
    train_briefly("duplicate poses", &ds);

    let mut ds = ball.dataset();
    for f in &mut ds.frames {
        f.image.rgba.fill(255);
    }
    train_briefly("all-white images", &ds);

    let mut ds = ball.dataset();
    for f in &mut ds.frames {
        for px in f.image.rgba.chunks_mut(4) {
            px.copy_from_slice(&[0, 0, 0, 255]);
        }
        f.image.has_alpha = false;
    }
    train_briefly("all-black opaque images", &ds);

    let mut ds = ball.dataset();
    for &i in &ds.train {
        // camera inside the box (and inside the ball)
        for (r, v) in ds.frames[i].camera.c2w.iter_mut().zip([0.2, -0.1, 0.05]) {
            r[3] = v;
        }
    }
    train_briefly("cameras inside the scene box", &ds);

    let mut ds = ball.dataset();
    for (k, f) in ds.frames.iter_mut().enumerate() {
        let gain = [1.0 / 64.0, 8.0, 1.0, 0.001, 40.0][k % 5];
        for px in f.image.rgba.chunks_mut(4) {
            for c in &mut px[..3] {
                *c = (*c as f32 * gain).round().min(255.0) as u8;
            }
        }
    }
    train_briefly("wildly different exposures", &ds);

    let mut ds = ball.dataset();
    ds.near = 0.0;
    ds.far = 1e6;
    train_briefly("near 0 and a huge far", &ds);
}

#[test]
fn a_long_run_keeps_finite_loss_and_parameters() {
    let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
    let config = NerfConfig {
        net: NetConfig { pos_freqs: 2, dir_freqs: 1, width: 8, depth: 2, skip: 0, dir_width: 4 },
        coarse_samples: 4,
        fine_samples: 4,
        occupancy: None,
        ..Default::default()
    };
    let model = NerfModel::new(config, Scene::from_dataset(&ds), 4);
    // An aggressive learning rate that stays high for the whole run.
    let mut t = trainer_for(Box::new(model), &ds, 3000, 16, 2e-2);
    t.adam.config.lr_end = 1e-2;
    let start = std::time::Instant::now();
    let mut bad = Vec::new();
    let reason = t.run(&AtomicBool::new(false), |t, p| {
        if !p.loss.is_finite() || (p.step % 500 == 0 && !all_finite(t.model.params())) {
            bad.push(p.step);
        }
        true
    });
    let secs = start.elapsed().as_secs_f64();
    eprintln!("3000 steps in {secs:.1} s, train PSNR {:.2} dB", t.progress(0.0).train_psnr);
    assert_eq!(reason, StopReason::Budget);
    assert!(bad.is_empty() && t.state.diverged_steps == 0, "non-finite at steps {bad:?}");
    assert!(all_finite(t.model.params()) && all_finite(&t.adam.m) && all_finite(&t.adam.v));
}
