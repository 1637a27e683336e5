//! Camera paths, checked numerically: keyframes hit exactly, analytic
//! motions reproduced, continuity of position and velocity, rotations that
//! stay rotations.

use super::*;

/// A pose: the rotation of `angle` about `axis`, at `position`.
fn pose(axis: [f64; 3], angle: f64, position: [f64; 3]) -> [[f32; 4]; 3] {
    let r = Quat::from_axis_angle(axis, angle).to_matrix();
    [0, 1, 2].map(|i| [r[i][0], r[i][1], r[i][2], position[i]].map(|v| v as f32))
}

fn key(axis: [f64; 3], angle: f64, position: [f64; 3], fov: f32, time: f64) -> Keyframe {
    Keyframe { c2w: pose(axis, angle, position), fov, time }
}

fn max_diff(a: &[[f32; 4]; 3], b: &[[f32; 4]; 3]) -> f32 {
    a.iter().flatten().zip(b.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

fn position(m: &[[f32; 4]; 3]) -> [f64; 3] {
    [m[0][3], m[1][3], m[2][3]].map(f64::from)
}

/// Five keyframes at uneven times, turning about different axes.
fn winding() -> CameraPath {
    let s = std::f64::consts::FRAC_1_SQRT_2;
    CameraPath::new(vec![
        key([0.0, 0.0, 1.0], 0.0, [4.0, 0.0, 1.0], 50.0, 0.0),
        key([0.0, 0.0, 1.0], 1.2, [1.0, 3.5, 1.5], 40.0, 1.0),
        key([s, 0.0, s], 2.0, [-3.0, 2.0, 0.5], 60.0, 2.5),
        key([0.0, 1.0, 0.0], -0.7, [-2.0, -3.0, 2.0], 45.0, 3.0),
        key([1.0, 0.0, 0.0], 0.4, [2.0, -2.5, 1.0], 55.0, 5.0),
    ])
    .unwrap()
}

#[test]
fn keyframes_are_reproduced_at_their_times() {
    let path = winding();
    for k in path.keyframes() {
        let (c2w, fov) = path.at(k.time);
        assert!(max_diff(&c2w, &k.c2w) < 1e-5, "at {}: {c2w:?} vs {:?}", k.time, k.c2w);
        assert!((fov - k.fov).abs() < 1e-4, "at {}: fov {fov} vs {}", k.time, k.fov);
    }
    // Before the first and after the last: clamped to them.
    assert_eq!(path.at(-3.0), path.at(0.0));
    assert_eq!(path.at(9.0), path.at(5.0));
}

#[test]
fn two_keyframes_move_in_a_straight_line_and_slerp() {
    let axis = [0.0, 0.0, 1.0];
    let path =
        CameraPath::new(vec![key(axis, 0.2, [0.0, 0.0, 0.0], 40.0, 1.0), key(axis, 1.0, [2.0, -4.0, 6.0], 60.0, 3.0)])
            .unwrap();
    for u in [0.0, 0.1, 0.25, 0.5, 0.9, 1.0] {
        let (c2w, fov) = path.at(1.0 + 2.0 * u);
        let want = pose(axis, 0.2 + 0.8 * u, [2.0 * u, -4.0 * u, 6.0 * u]);
        assert!(max_diff(&c2w, &want) < 1e-5, "u {u}: {c2w:?} vs {want:?}");
        assert!((fov - (40.0 + 20.0 * u as f32)).abs() < 1e-4);
    }
}

#[test]
fn motion_linear_in_time_is_reproduced_between_uneven_keyframes() {
    // A camera flying along a line at constant speed while turning about a
    // fixed (skew) axis at constant angular speed, keyed at uneven times.
    let s = 1.0 / 3f64.sqrt();
    let axis = [s, s, -s];
    let at = |t: f64| pose(axis, 0.3 + 0.45 * t, [1.0 + 0.5 * t, -2.0 + 0.25 * t, 0.75 * t]);
    let times = [0.0, 0.4, 1.5, 1.9, 4.0, 4.2];
    let keys = times.iter().map(|&t| Keyframe { c2w: at(t), fov: 50.0, time: t }).collect();
    let path = CameraPath::new(keys).unwrap();
    for k in 0..=84 {
        let t = 4.2 * k as f64 / 84.0;
        let (c2w, fov) = path.at(t);
        assert!(max_diff(&c2w, &at(t)) < 2e-5, "t {t}: {c2w:?} vs {:?}", at(t));
        assert!((fov - 50.0).abs() < 1e-4);
    }
}

#[test]
fn positions_and_velocities_are_continuous_through_keyframes() {
    let path = winding();
    let h = 1e-4;
    for k in &path.keyframes()[1..path.keyframes().len() - 1] {
        let t = k.time;
        let (p0, p1, p2) = (position(&path.at(t - h).0), position(&path.at(t).0), position(&path.at(t + h).0));
        for c in 0..3 {
            let (before, after) = ((p1[c] - p0[c]) / h, (p2[c] - p1[c]) / h);
            // One-sided derivatives agree (a kink would differ by O(1)).
            assert!((before - after).abs() < 2e-2, "t {t} axis {c}: velocity {before} then {after}");
        }
        // Angular velocity too: the turn just before and just after the key.
        let q = |t: f64| Quat::from_matrix(rotation_of(&path.at(t).0).unwrap());
        let (w0, w1) = (q(t - h).angle_to(q(t)) / h, q(t).angle_to(q(t + h)) / h);
        assert!((w0 - w1).abs() < 2e-2 * w0.max(1.0), "t {t}: angular speed {w0} then {w1}");
    }
    // No jumps anywhere: small steps in time, small steps in space.
    let mut last = path.at(0.0).0;
    for k in 1..=5000 {
        let next = path.at(5.0 * k as f64 / 5000.0).0;
        assert!(max_diff(&last, &next) < 0.05, "jump at step {k}");
        last = next;
    }
}

#[test]
fn poses_along_the_path_stay_rigid() {
    let path = winding();
    for k in 0..=500 {
        let (c2w, fov) = path.at(5.0 * k as f64 / 500.0);
        let r = rotation_of(&c2w).unwrap_or_else(|e| panic!("step {k}: {e}"));
        let q = Quat::from_matrix(r);
        assert!((q.norm() - 1.0).abs() < 1e-9);
        for a in 0..3 {
            let n: f64 = (0..3).map(|i| r[i][a] * r[i][a]).sum();
            assert!((n - 1.0).abs() < 1e-5, "step {k}: column {a} has length {n}");
        }
        assert!(fov > 1.0 && fov < 179.0);
    }
}

#[test]
fn one_keyframe_holds_still_and_frames_span_the_keyframes() {
    let k = key([0.0, 0.0, 1.0], 0.5, [1.0, 2.0, 3.0], 45.0, 2.0);
    let path = CameraPath::new(vec![k.clone()]).unwrap();
    assert_eq!(path.at(0.0), (k.c2w, 45.0));
    assert_eq!(path.frame_time(0, 1), 2.0);
    let path = winding();
    assert_eq!((path.frame_time(0, 11), path.frame_time(10, 11), path.frame_time(5, 11)), (0.0, 5.0, 2.5));
}

#[test]
fn bad_keyframes_are_named() {
    let good = key([0.0, 0.0, 1.0], 0.0, [0.0, 0.0, 4.0], 50.0, 0.0);
    assert_eq!(CameraPath::new(vec![]), Err(PathError::Empty));
    let mut late = good.clone();
    late.time = 0.0;
    assert_eq!(
        CameraPath::new(vec![good.clone(), late]),
        Err(PathError::NotIncreasing { index: 1, time: 0.0, previous: 0.0 })
    );
    let mut skew = good.clone();
    skew.c2w[0][0] = 2.0;
    skew.time = 1.0;
    assert!(matches!(CameraPath::new(vec![good.clone(), skew]), Err(PathError::Pose { index: 1, .. })));
    let mut mirror = good.clone();
    mirror.c2w[0][0] = -1.0;
    assert_eq!(
        CameraPath::new(vec![mirror]),
        Err(PathError::Pose { index: 0, reason: "the rotation is a reflection" })
    );
    let wide = Keyframe { fov: 200.0, ..good.clone() };
    assert_eq!(CameraPath::new(vec![wide]), Err(PathError::Fov { index: 0, fov: 200.0 }));
    let nan = Keyframe { time: f64::NAN, ..good.clone() };
    assert!(matches!(CameraPath::new(vec![nan]), Err(PathError::Time { index: 0, .. })));
    // Through serde too: a path is checked as it is read.
    let json = serde_json::json!([{ "c2w": good.c2w, "fov": 50.0, "time": 1.0 }, { "c2w": good.c2w, "fov": 50.0, "time": 0.5 }]);
    let e = serde_json::from_value::<CameraPath>(json).unwrap_err().to_string();
    assert!(e.contains("keyframe 1: time 0.5 is not after"), "{e}");
}
