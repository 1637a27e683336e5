//! Unit tests of `space.rs`: the maps against hand-computed values and
//! NeRF's ray NDC, inverses, and every VJP against central differences of
//! an f64 re-implementation of the map (itself checked against the f32 one).

use proptest::prelude::*;

use super::*;
use crate::engine::geometry::quat::Quat;
use crate::engine::rng::Rng;

/// The contraction in f64, straight from the formula.
fn contract64(norm: Norm, x: [f64; 3]) -> [f64; 3] {
    let m = match norm {
        Norm::Linf => x[0].abs().max(x[1].abs()).max(x[2].abs()),
        Norm::L2 => (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt(),
    };
    if m <= 1.0 { x } else { x.map(|v| (2.0 - 1.0 / m) * v / m) }
}

/// NDC in f64, straight from the formula.
fn ndc64(cam: &NdcCamera, x: [f64; 3]) -> [f64; 3] {
    let r = cam.rotation.map(|row| row.map(|v| v as f64));
    let d: [f64; 3] = std::array::from_fn(|i| x[i] - cam.centre[i] as f64);
    let c: [f64; 3] = std::array::from_fn(|i| r[0][i] * d[0] + r[1][i] * d[1] + r[2][i] * d[2]);
    let n = cam.near as f64;
    let z = c[2].min(-0.5 * n);
    let sx = 2.0 * cam.fx as f64 / cam.width as f64;
    let sy = 2.0 * cam.fy as f64 / cam.height as f64;
    [-sx * c[0] / z, -sy * c[1] / z, 1.0 + 2.0 * n / z]
}

/// `map` in f64 for either kind.
fn map64(map: &SpaceMap, x: [f64; 3]) -> [f64; 3] {
    match map {
        SpaceMap::Contract { norm } => contract64(*norm, x).map(|y| (y + 2.0) / 4.0),
        SpaceMap::Ndc(f) => ndc64(f.camera(), x).map(|p| (p + 1.0) / 2.0),
    }
}

fn to64(x: [f32; 3]) -> [f64; 3] {
    x.map(|v| v as f64)
}

fn max_abs64(x: [f64; 3]) -> f64 {
    x[0].abs().max(x[1].abs()).max(x[2].abs())
}

/// A random rotation (camera-to-model, rows) about a random axis.
fn rotation(rng: &mut Rng) -> [[f32; 3]; 3] {
    let a = [rng.normal() as f64, rng.normal() as f64, rng.normal() as f64];
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let q = Quat::from_axis_angle(a.map(|v| v / n), 6.0 * rng.f32() as f64);
    q.to_matrix().map(|row| row.map(|v| v as f32))
}

fn camera(rng: &mut Rng) -> NdcCamera {
    NdcCamera {
        rotation: rotation(rng),
        centre: [rng.normal(), rng.normal(), rng.normal()],
        near: 0.5,
        fx: 90.0,
        fy: 80.0,
        width: 120,
        height: 100,
    }
}

/// A point with camera coordinates `c` in `frame`.
fn from_camera(cam: &NdcCamera, c: [f32; 3]) -> [f32; 3] {
    let r = &cam.rotation;
    std::array::from_fn(|i| r[i][0] * c[0] + r[i][1] * c[1] + r[i][2] * c[2] + cam.centre[i])
}

/// A random point at a log-uniform distance (1e-2 to 1e3) from the origin.
fn point(rng: &mut Rng) -> [f32; 3] {
    let scale = 10f32.powf(rng.f32() * 5.0 - 2.0);
    [rng.normal() * scale, rng.normal() * scale, rng.normal() * scale]
}

#[test]
fn contraction_matches_hand_computed_values() {
    // L-inf, m = 2: y = (2 - 1/2) x / 2.
    assert_eq!(Norm::Linf.contract([2.0, 1.0, 0.0]), [1.5, 0.75, 0.0]);
    // L2, r = 4: y = (2 - 1/4) x / 4.
    assert_eq!(Norm::L2.contract([0.0, 0.0, -4.0]), [0.0, 0.0, -1.75]);
    // Inside the unit ball nothing moves.
    assert_eq!(Norm::Linf.contract([0.9, -1.0, 0.3]), [0.9, -1.0, 0.3]);
    assert_eq!(Norm::L2.contract([0.3, -0.0, 0.4]), [0.3, -0.0, 0.4]);
    // Infinity lands on its limit: the cube's faces, the ball's sphere.
    let map = SpaceMap::Contract { norm: Norm::Linf };
    assert_eq!(map.map([f32::INFINITY, 5.0, f32::NEG_INFINITY]), [1.0, 0.5, 0.0]);
    assert_eq!(Norm::L2.contract([f32::INFINITY, 5.0, 0.0]), [2.0, 0.0, 0.0]);
    assert_eq!(map.map([0.0, 0.0, 0.0]), [0.5, 0.5, 0.5]);
    assert!(map.map([f32::NAN, 0.0, 0.0])[0].is_nan(), "NaN stays NaN (the grid reads it as 0)");
}

#[test]
fn uncontract_inverts_contract_both_ways() {
    let mut rng = Rng::new(11);
    for norm in [Norm::Linf, Norm::L2] {
        for _ in 0..2000 {
            let x = point(&mut rng);
            let back = norm.uncontract(norm.contract(x)).expect("a finite point contracts inside radius 2");
            let m = max_abs(x) as f64;
            // Near radius 2 the inverse divides by 2 - |y| ~ 1/m: f32 rounding
            // of y grows by m there.
            let tol = 1e-6 * m * m.max(1.0) + 1e-7;
            for i in 0..3 {
                assert!((back[i] as f64 - x[i] as f64).abs() <= tol, "{norm:?} {x:?} -> {back:?}");
            }
        }
        for _ in 0..2000 {
            let y = [rng.f32() * 4.0 - 2.0, rng.f32() * 4.0 - 2.0, rng.f32() * 4.0 - 2.0];
            let inside = match norm {
                Norm::Linf => max_abs(y) < 1.99,
                Norm::L2 => norm2(y) < 1.99,
            };
            if !inside {
                continue;
            }
            let again = norm.contract(norm.uncontract(y).expect("inside radius 2"));
            for i in 0..3 {
                assert!((again[i] - y[i]).abs() < 1e-5, "{norm:?} {y:?} -> {again:?}");
            }
        }
        assert_eq!(norm.uncontract([2.0, 0.0, 0.0]), None, "radius 2 is infinitely far");
        assert_eq!(norm.uncontract([f32::NAN, 0.0, 0.0]), None);
        assert_eq!(norm.uncontract([0.5, -0.25, 0.0]), Some([0.5, -0.25, 0.0]));
    }
    // Through the grid coordinates.
    let map = SpaceMap::Contract { norm: Norm::Linf };
    let x = [-3.0, 0.5, 1.25];
    let back = map.unmap(map.map(x)).unwrap();
    assert!(back.iter().zip(x).all(|(a, b)| (a - b).abs() < 1e-5), "{back:?}");
}

#[test]
fn contraction_is_continuous_at_the_unit_sphere() {
    let mut rng = Rng::new(12);
    for norm in [Norm::Linf, Norm::L2] {
        for _ in 0..200 {
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let m = match norm {
                Norm::Linf => max_abs(d),
                Norm::L2 => norm2(d),
            };
            let on = d.map(|v| v / m);
            for eps in [1e-3f32, 1e-5] {
                let (a, b) = (on.map(|v| v * (1.0 - eps)), on.map(|v| v * (1.0 + eps)));
                let (ya, yb) = (norm.contract(a), norm.contract(b));
                // Both sides within ~ the step: the value is continuous.
                for i in 0..3 {
                    assert!((ya[i] - yb[i]).abs() <= 2.5 * eps + 1e-6, "{norm:?} {on:?} eps {eps}: {ya:?} {yb:?}");
                }
                // And the Jacobian tends to the identity from outside.
                let g = [rng.normal(), rng.normal(), rng.normal()];
                let dx = norm.contract_vjp(b, g);
                let size: f32 = g.iter().map(|v| v.abs()).sum();
                for i in 0..3 {
                    assert!((dx[i] - g[i]).abs() <= 10.0 * eps * (1.0 + size), "{norm:?} J^T g {dx:?} vs {g:?}");
                }
            }
        }
    }
}

/// Central differences of the f64 map at `x`, dotted with `du`.
fn numeric_vjp(map: &SpaceMap, x: [f32; 3], du: [f32; 3], h: f64) -> [f64; 3] {
    let x = to64(x);
    std::array::from_fn(|i| {
        let (mut a, mut b) = (x, x);
        a[i] += h;
        b[i] -= h;
        let (ua, ub) = (map64(map, a), map64(map, b));
        (0..3).map(|k| (ua[k] - ub[k]) / (2.0 * h) * du[k] as f64).sum()
    })
}

/// Checks `vjp` against finite differences, and `map` against the f64
/// map, at `x`; `scale` is the size of a derivative there.
fn check_vjp(map: &SpaceMap, x: [f32; 3], rng: &mut Rng, h: f64, what: &str) {
    let u = map.map(x);
    let u64 = map64(map, to64(x));
    for k in 0..3 {
        assert!((u[k] as f64 - u64[k]).abs() < 1e-5 * (1.0 + u64[k].abs()), "{what} map at {x:?}: {u:?} vs {u64:?}");
    }
    let du = [rng.normal(), rng.normal(), rng.normal()];
    let got = map.vjp(x, du);
    let want = numeric_vjp(map, x, du, h);
    let scale = want.iter().map(|v| v.abs()).fold(0.0, f64::max);
    for i in 0..3 {
        assert!(
            (got[i] as f64 - want[i]).abs() <= 1e-4 * scale + 1e-9,
            "{what} vjp at {x:?} (du {du:?}): {got:?} vs {want:?}"
        );
    }
}

#[test]
fn contraction_vjps_match_finite_differences_in_f64() {
    let mut rng = Rng::new(13);
    for norm in [Norm::Linf, Norm::L2] {
        let map = SpaceMap::Contract { norm };
        let (mut inside, mut outside) = (0, 0);
        while inside + outside < 3000 {
            let x = point(&mut rng);
            let x64 = to64(x);
            let m = max_abs64(x64);
            let r = (x64[0] * x64[0] + x64[1] * x64[1] + x64[2] * x64[2]).sqrt();
            let radius = if norm == Norm::Linf { m } else { r };
            // Off the unit sphere and, for L-inf, off the faces where the
            // largest coordinate changes axis (one-sided derivatives there).
            let mut sorted = x64.map(f64::abs);
            sorted.sort_by(f64::total_cmp);
            if (radius - 1.0).abs() < 0.05 || (norm == Norm::Linf && sorted[1] > 0.95 * m) {
                continue;
            }
            check_vjp(&map, x, &mut rng, 1e-6 * radius.max(1.0), &format!("{norm:?}"));
            if radius < 1.0 { inside += 1 } else { outside += 1 }
        }
        assert!(inside > 200 && outside > 1500, "{norm:?}: {inside} inside, {outside} outside");
    }
}

#[test]
fn ndc_vjp_matches_finite_differences_in_f64() {
    let mut rng = Rng::new(14);
    for _ in 0..20 {
        let cam = camera(&mut rng);
        let map = SpaceMap::Ndc(NdcFrame::new(cam.clone()).unwrap());
        for _ in 0..100 {
            // In the frustum and beyond it, between the near plane and the
            // camera, and in the held region nearer than n / 2 (avoiding
            // its boundary z_c = -n / 2, where the derivative is one-sided).
            let z = match rng.below(3) {
                0 => -cam.near * 10f32.powf(3.0 * rng.f32()),
                1 => -cam.near * (0.55 + 0.45 * rng.f32()),
                _ => cam.near * (2.0 * rng.f32() - 0.45),
            };
            let c = [rng.normal() * z.abs().max(0.3), rng.normal() * z.abs().max(0.3), z];
            let x = from_camera(&cam, c);
            check_vjp(&map, x, &mut rng, 1e-6 * (1.0 + z.abs() as f64), "ndc");
        }
    }
}

#[test]
fn ndc_maps_the_frustum_to_the_cube_as_nerf_does() {
    let mut rng = Rng::new(15);
    let cam = camera(&mut rng);
    let frame = NdcFrame::new(cam.clone()).unwrap();
    let (n, w, h) = (cam.near, cam.width as f32, cam.height as f32);
    // The image's corners on the near plane: P = (±1, ±1, -1).
    for (sx, sy) in [(1.0f32, 1.0f32), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)] {
        let c = [sx * n * w / (2.0 * cam.fx), sy * n * h / (2.0 * cam.fy), -n];
        let p = frame.project(from_camera(&cam, c));
        let want = [sx, sy, -1.0];
        assert!(p.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-4), "{c:?} -> {p:?}");
    }
    // Far along the optical axis: P -> (0, 0, 1).
    let p = frame.project(from_camera(&cam, [0.0, 0.0, -1e6]));
    assert!(p[0].abs() < 1e-4 && p[1].abs() < 1e-4 && (p[2] - 1.0).abs() < 1e-5, "{p:?}");

    // NeRF's ray NDC (paper, appendix C; `ndc_rays` of the reference code):
    // a ray (o, d) in camera coordinates, its origin moved to the near
    // plane, becomes o' + t' d' with t' = 1 - o_z / z in [0, 1).
    let (ax, ay) = (2.0 * cam.fx as f64 / w as f64, 2.0 * cam.fy as f64 / h as f64);
    for _ in 0..50 {
        let d = [rng.normal() as f64 * 0.3, rng.normal() as f64 * 0.3, -1.0];
        let o0 = [rng.normal() as f64 * 0.2, rng.normal() as f64 * 0.2, rng.normal() as f64 * 0.2];
        let t0 = -(n as f64 + o0[2]) / d[2];
        let o: [f64; 3] = std::array::from_fn(|i| o0[i] + t0 * d[i]);
        let op = [-ax * o[0] / o[2], -ay * o[1] / o[2], 1.0 + 2.0 * n as f64 / o[2]];
        let dp = [-ax * (d[0] / d[2] - o[0] / o[2]), -ay * (d[1] / d[2] - o[1] / o[2]), -2.0 * n as f64 / o[2]];
        for s in [0.0, 0.1, 1.0, 7.0, 300.0] {
            let c: [f64; 3] = std::array::from_fn(|i| o[i] + s * d[i]);
            let p = frame.project(from_camera(&cam, c.map(|v| v as f32)));
            let t = 1.0 - o[2] / c[2];
            for k in 0..3 {
                let want = op[k] + t * dp[k];
                assert!((p[k] as f64 - want).abs() < 2e-4 * (1.0 + want.abs()), "s {s}: {p:?}, axis {k}: {want}");
            }
        }
    }
}

#[test]
fn ndc_unproject_inverts_project() {
    let mut rng = Rng::new(16);
    for _ in 0..10 {
        let cam = camera(&mut rng);
        let map = SpaceMap::Ndc(NdcFrame::new(cam.clone()).unwrap());
        for _ in 0..200 {
            let z = -cam.near * (0.6 + 100.0 * rng.f32());
            let c = [rng.normal() * z.abs(), rng.normal() * z.abs(), z];
            let x = from_camera(&cam, c);
            let back = map.unmap(map.map(x)).expect("a point in front of the camera");
            let tol = 1e-5 * (1.0 + z.abs() * z.abs() / cam.near);
            assert!(back.iter().zip(x).all(|(a, b)| (a - b).abs() <= tol), "{x:?} -> {back:?}");
        }
        let frame = NdcFrame::new(cam.clone()).unwrap();
        assert_eq!(frame.unproject([0.0, 0.0, 1.0]), None, "P_z = 1 is at infinity");
        assert_eq!(frame.unproject([0.0, 0.0, -3.5]), None, "no point maps below P_z = -3");
        assert_eq!(frame.unproject([f32::NAN, 0.0, 0.0]), None);
    }
}

#[test]
fn ndc_sends_points_off_the_frustum_out_of_the_cube() {
    let mut rng = Rng::new(17);
    let cam = camera(&mut rng);
    let map = SpaceMap::Ndc(NdcFrame::new(cam.clone()).unwrap());
    let n = cam.near;
    // Behind the camera, on its plane, between it and the near plane: u_z < 0.
    for z in [5.0, 0.0, -0.0, -0.3 * n, -0.99 * n] {
        let u = map.map(from_camera(&cam, [0.1, -0.2, z]));
        assert!(u.iter().all(|v| v.is_finite()) && u[2] < 0.0, "z_c {z}: {u:?}");
    }
    // Beside the frustum: u_x > 1.
    let u = map.map(from_camera(&cam, [10.0, 0.0, -2.0]));
    assert!(u[0] > 1.0 && (0.0..=1.0).contains(&u[2]), "{u:?}");
    assert_eq!(map.vjp([f32::INFINITY, 0.0, 0.0], [1.0; 3]), [0.0; 3]);
}

#[test]
fn ndc_cameras_are_checked() {
    let mut rng = Rng::new(18);
    let good = camera(&mut rng);
    assert!(NdcFrame::new(good.clone()).is_ok());
    let bad = |f: &dyn Fn(&mut NdcCamera)| {
        let mut c = good.clone();
        f(&mut c);
        NdcFrame::new(c).unwrap_err()
    };
    assert_eq!(bad(&|c| c.near = 0.0), SpaceError::NotPositive { field: "near", value: 0.0 });
    assert!(matches!(bad(&|c| c.fx = f32::NAN), SpaceError::NotPositive { field: "fx", .. }));
    assert_eq!(bad(&|c| c.fy = -2.0), SpaceError::NotPositive { field: "fy", value: -2.0 });
    assert_eq!(bad(&|c| c.height = 0), SpaceError::Size { width: 120, height: 0 });
    assert!(matches!(bad(&|c| c.centre[1] = f32::INFINITY), SpaceError::Centre(_)));
    let e = bad(&|c| c.rotation[0][0] *= 1.01);
    assert!(e.to_string().contains("not orthonormal"), "{e}");
    let e = bad(&|c| c.rotation[2] = c.rotation[2].map(|v| -v));
    assert!(e.to_string().contains("reflection"), "{e}");
    let e = bad(&|c| c.rotation[1][2] = f32::NAN);
    assert!(e.to_string().contains("not finite"), "{e}");
    // Finite focal lengths whose scale 2 fx / W overflows.
    assert!(matches!(bad(&|c| c.fx = f32::MAX), SpaceError::NotPositive { field: "focal length over image size", .. }));
}

#[test]
fn space_maps_round_trip_through_json_and_refuse_bad_frames() {
    let mut rng = Rng::new(19);
    let maps = [
        SpaceMap::Contract { norm: Norm::Linf },
        SpaceMap::Contract { norm: Norm::L2 },
        SpaceMap::Ndc(NdcFrame::new(camera(&mut rng)).unwrap()),
    ];
    for map in &maps {
        let json = serde_json::to_value(map).unwrap();
        assert_eq!(&serde_json::from_value::<SpaceMap>(json.clone()).unwrap(), map, "{json}");
    }
    assert_eq!(serde_json::to_value(&maps[0]).unwrap(), serde_json::json!({"kind": "contract", "norm": "linf"}));
    let mut json = serde_json::to_value(&maps[2]).unwrap();
    assert_eq!(json["kind"], "ndc");
    assert_eq!(json["width"], 120);
    json["near"] = serde_json::json!(-1.0);
    let err = serde_json::from_value::<SpaceMap>(json).unwrap_err().to_string();
    assert!(err.contains("near must be a finite number above 0"), "{err}");
    let err = serde_json::from_value::<SpaceMap>(serde_json::json!({"kind": "contract", "norm": "l3"}));
    assert!(err.is_err());
}

#[test]
fn batched_forms_equal_the_scalar_ones() {
    let mut rng = Rng::new(20);
    let maps = [
        SpaceMap::Contract { norm: Norm::Linf },
        SpaceMap::Contract { norm: Norm::L2 },
        SpaceMap::Ndc(NdcFrame::new(camera(&mut rng)).unwrap()),
    ];
    let xs: Vec<[f32; 3]> = (0..50).map(|_| point(&mut rng)).collect();
    let dus: Vec<[f32; 3]> = (0..50).map(|_| [rng.normal(), rng.normal(), rng.normal()]).collect();
    for map in &maps {
        let mut us = vec![[f32::NAN; 3]; xs.len()];
        map.map_batch(&xs, &mut us);
        let mut dxs = vec![[f32::NAN; 3]; xs.len()];
        map.vjp_batch(&xs, &dus, &mut dxs);
        for i in 0..xs.len() {
            assert_eq!(us[i], map.map(xs[i]));
            assert_eq!(dxs[i], map.vjp(xs[i], dus[i]));
        }
    }
}

/// Coordinates of any size, with the extremes of f32.
fn coordinate() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(0.0f32),
        Just(-0.0f32),
        Just(1.0f32),
        Just(-1.0f32),
        Just(f32::MAX),
        Just(f32::MIN),
        Just(f32::MIN_POSITIVE),
        -2.0f32..2.0,
        (-38.0f32..38.0).prop_map(|e| 10f32.powf(e)),
        (-38.0f32..38.0).prop_map(|e| -(10f32.powf(e))),
        any::<f32>().prop_filter("finite", |v| v.is_finite()),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Every finite point lands in the unit cube, at the distance from its
    /// centre the contraction says: `‖y‖ = 2 - 1/‖x‖` beyond the unit ball,
    /// so far points go to the boundary (the cube's faces for L-inf, the
    /// sphere of radius 2 for L2); and further out along a ray is never
    /// nearer the centre.
    #[test]
    fn contracted_points_stay_in_the_cube_and_far_ones_reach_its_boundary(
        x in proptest::array::uniform3(coordinate()),
        l2 in any::<bool>(),
        factor in 1.0f32..1e6,
    ) {
        let norm = if l2 { Norm::L2 } else { Norm::Linf };
        let map = SpaceMap::Contract { norm };
        let u = map.map(x);
        prop_assert!(u.iter().all(|v| (0.0..=1.0).contains(v)), "{:?} -> {:?}", x, u);
        let y = to64(u).map(|v| 4.0 * v - 2.0);
        let x64 = to64(x);
        let (size_x, size_y) = match norm {
            Norm::Linf => (max_abs64(x64), max_abs64(y)),
            Norm::L2 => {
                // Scaled first, as f64 squares of f32::MAX still fit.
                let m = max_abs64(x64).max(f64::MIN_POSITIVE);
                let s = x64.map(|v| v / m);
                (m * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt(), (y[0] * y[0] + y[1] * y[1] + y[2] * y[2]).sqrt())
            }
        };
        let want = if size_x <= 1.0 { size_x } else { 2.0 - 1.0 / size_x };
        prop_assert!((size_y - want).abs() <= 2e-6 * (1.0 + want), "{:?}: |y| {} vs {}", x, size_y, want);
        if size_x > 1e4 {
            let boundary = match norm {
                Norm::Linf => u.iter().map(|&v| v.min(1.0 - v)).fold(1.0, f32::min) as f64,
                Norm::L2 => (2.0 - size_y) / 4.0,
            };
            prop_assert!(boundary < 1e-4, "{:?} -> {:?} is {} from the boundary", x, u, boundary);
        }
        let further = x.map(|v| v * factor);
        if further.iter().all(|v| v.is_finite()) {
            let yf = to64(map.map(further)).map(|v| 4.0 * v - 2.0);
            let size_f = match norm {
                Norm::Linf => max_abs64(yf),
                Norm::L2 => (yf[0] * yf[0] + yf[1] * yf[1] + yf[2] * yf[2]).sqrt(),
            };
            prop_assert!(size_f >= size_y - 1e-6, "{:?}: {} then {}", x, size_y, size_f);
        }
        let g = map.vjp(x, [1.0, -2.0, 0.5]);
        prop_assert!(g.iter().all(|v| v.is_finite()), "{:?}: vjp {:?}", x, g);
    }
}
