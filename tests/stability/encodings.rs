//! Encodings at the domain's edges, cameras with odd directions.

use proptest::prelude::*;
use radiance::engine::geometry::camera::{Camera, Distortion};
use radiance::engine::nn::encoding::{encode, encode_backward, encoded_width};

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
