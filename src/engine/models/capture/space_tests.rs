//! Unit tests of `space.rs`: the NDC camera against the training
//! cameras' own poses (what lands on the near plane, the image's corners
//! and infinity), the refusals, and the configuration as checkpoints store
//! it.

use super::*;
use crate::engine::dataset::Dataset;
use crate::engine::dataset::textured::TexturedScene;
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::models::Model;
use crate::engine::models::capture::CaptureModel;
use crate::engine::models::config::ModelConfig;

fn forward() -> Dataset {
    TexturedScene { width: 16, height: 12, views: 9, fov: 0.9 }.forward_facing()
}

fn ndc_tiny() -> CaptureConfig {
    let ModelConfig::Capture(c) = ModelConfig::preset("capture-tiny").unwrap() else { unreachable!() };
    CaptureConfig { space: Space::Ndc, camera_radius: 0.7, ..c }
}

type V = [f64; 3];

fn unit(a: V) -> V {
    let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    a.map(|v| v / n)
}

fn cross(a: V, b: V) -> V {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// The mean training camera computed from the frames' poses in f64: the
/// mean centre, the mean optical axis, and the mean right axis made
/// perpendicular to it (Gram-Schmidt), as a camera-to-world matrix.
fn mean_pose(ds: &Dataset) -> [[f32; 4]; 3] {
    let (mut c, mut axis, mut right) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
    for &k in &ds.train {
        let m = ds.frames[k].camera.c2w;
        for i in 0..3 {
            c[i] += m[i][3] as f64 / ds.train.len() as f64;
            axis[i] -= m[i][2] as f64;
            right[i] += m[i][0] as f64;
        }
    }
    let back = unit(axis).map(|v| -v);
    let up = unit(cross(back, right));
    let right = cross(up, back);
    std::array::from_fn(|i| [right[i] as f32, up[i] as f32, back[i] as f32, c[i] as f32])
}

/// The NDC camera is the mean training camera moved into the model's units:
/// a world point on its axis at the dataset's near depth lands on `P_z = -1`,
/// at twice that depth on `P_z = 0`, far away near `P_z = 1`; rays through
/// the image's corners land on `P_x, P_y = ±1`, at every depth.
#[test]
fn the_ndc_camera_is_the_mean_training_camera_in_model_units() {
    let ds = forward();
    let scene = ds.scene();
    let rig = scene.rig.clone().unwrap();
    assert!(rig.forward_facing && rig.spread_deg < 2.0, "{}", rig.spread_deg);
    let config = ndc_tiny();
    let frame = ndc_frame(&scene, &config).unwrap();
    let model = capture_scene(&scene, &config);
    let pose = mean_pose(&ds);
    let centre = Vec3::new(pose[0][3], pose[1][3], pose[2][3]);
    let to_model = |p: Vec3| model.to_model(&Ray { origin: p, dir: Vec3::new(1.0, 0.0, 0.0) }).origin.to_array();
    let c = frame.camera();
    let got = Vec3::from_array(c.centre);
    assert!((got - Vec3::from_array(to_model(centre))).norm() < 1e-5, "{:?} vs {centre:?}", c.centre);
    for col in 0..3 {
        let dot: f32 = (0..3).map(|i| c.rotation[i][col] * pose[i][col]).sum();
        assert!(dot > 1.0 - 1e-6, "axis {col}: {:?} vs {pose:?}", c.rotation);
    }
    // Model units: the scale maps the rig's median camera distance to
    // camera_radius.
    assert!((c.near - ds.near * config.camera_radius / rig.radius).abs() < 1e-6 * c.near, "{}", c.near);

    let axis = Vec3::new(-pose[0][2], -pose[1][2], -pose[2][2]);
    for (depth, pz) in [(ds.near, -1.0), (2.0 * ds.near, 0.0), (1e6, 1.0)] {
        let p = frame.project(to_model(centre + axis * depth));
        assert!(p[0].abs() < 1e-4 && p[1].abs() < 1e-4 && (p[2] - pz).abs() < 1e-4, "depth {depth}: {p:?}");
    }
    let (w, h) = (ds.frames[0].camera.width, ds.frames[0].camera.height);
    let mean_camera = Camera::from_fov(w, h, 0.9, pose);
    for (u, v, want) in [(0.0, 0.0, [-1.0, 1.0]), (w as f32, h as f32, [1.0, -1.0]), (w as f32, 0.0, [1.0, 1.0])] {
        let ray = mean_camera.ray(u, v);
        for depth in [2.0, 40.0] {
            // The ray's point at z-depth `depth`.
            let p = frame.project(to_model(ray.at(depth / ray.dir.dot(axis))));
            assert!((p[0] - want[0]).abs() < 1e-4 && (p[1] - want[1]).abs() < 1e-4, "({u}, {v}) at {depth}: {p:?}");
        }
    }
}

/// NDC is refused with a message that says why and what to use instead:
/// for cameras all around (a ring), for a scene without cameras, and for a
/// rig without an image size; contraction builds on each of them.
#[test]
fn ndc_is_refused_where_it_cannot_map_the_capture() {
    let ring = (TexturedScene { width: 16, height: 12, views: 8, fov: 0.9 }.dataset()).scene();
    let no_rig = Scene { rig: None, ..ring.clone() };
    let mut no_image = (forward()).scene();
    no_image.rig.as_mut().unwrap().image = [0, 0];
    for (scene, want) in [(&ring, "forward-facing"), (&no_rig, "has none"), (&no_image, "image size")] {
        let err = ModelConfig::Capture(ndc_tiny()).build(scene.clone(), 1).err().expect("refused");
        let text = err.to_string();
        assert!(matches!(err, ModelError::Config { kind: "capture", .. }), "{text}");
        assert!(text.contains(want) && text.contains("space=ndc"), "{text}");
        let contract = CaptureConfig { space: Space::Contract, ..ndc_tiny() };
        assert!(ModelConfig::Capture(contract).build(scene.clone(), 1).is_ok());
    }
    let text = ndc_frame(&ring, &ndc_tiny()).unwrap_err().to_string();
    assert!(text.contains("spread") && text.contains("use space=contract"), "{text}");
}

/// Building fills the camera for NDC (replacing one it was given) and
/// clears it for contraction; rebuilding from saved parts needs it.
#[test]
fn the_camera_is_derived_at_build_and_required_at_rebuild() {
    let scene = (forward()).scene();
    let want = ndc_frame(&scene, &ndc_tiny()).unwrap();
    let m = CaptureModel::new(ndc_tiny(), scene.clone(), 1).unwrap();
    assert_eq!(m.config.ndc_camera.as_ref(), Some(&want));
    // Both the main field and the proposal networks map with it: the
    // proposals give no density in front of the near plane (nor behind the
    // camera), and some beyond it.
    let mut ps = crate::engine::nn::linear::ParamLayout::default();
    let crate::engine::models::capture::Parts { field, proposals, .. } =
        crate::engine::models::capture::layout(&mut ps, &m.config);
    assert_eq!(field.space(), &SpaceMap::Ndc(want.clone()));
    let c = want.camera();
    let on_axis = |depth: f32| -> [f32; 3] { std::array::from_fn(|i| c.centre[i] - depth * c.rotation[i][2]) };
    let pos: Vec<f32> = [-1.0, 0.5, 0.99, 1.01, 3.0, 1e4].iter().flat_map(|&k| on_axis(k * c.near)).collect();
    assert_eq!(proposals.len(), 2);
    for p in &proposals {
        let mut ctx = crate::engine::fields::proposal::ProposalCtx::default();
        p.density(m.params(), &pos, &mut ctx);
        let sigma = p.sigma(&ctx);
        assert!(sigma[..3] == [0.0; 3] && sigma[3..].iter().all(|&s| s > 0.0), "{sigma:?}");
    }

    let mut other = want.camera().clone();
    other.near *= 3.0;
    let given = CaptureConfig { ndc_camera: Some(NdcFrame::new(other).unwrap()), ..ndc_tiny() };
    assert_eq!(resolve(given.clone(), &scene).unwrap().ndc_camera, Some(want.clone()));
    let contract = resolve(CaptureConfig { space: Space::Contract, ..given }, &scene).unwrap();
    let contract_map = SpaceMap::Contract { norm: contract.contraction };
    assert_eq!((space_map(&contract), contract.ndc_camera), (contract_map, None));

    let params = m.params().to_vec();
    let err = CaptureModel::from_parts(ndc_tiny(), m.scene().clone(), params.clone()).err().expect("refused");
    assert!(err.to_string().contains("no ndc_camera"), "{err}");
    let back = CaptureModel::from_parts(m.config.clone(), m.scene().clone(), params).unwrap();
    assert_eq!(back.config, m.config);
}

/// The configuration as a checkpoint stores it: `space` and the derived
/// camera round-trip; configurations from before `space` existed read
/// `contract`; contraction writes no camera; a stored camera that is not a
/// valid one is refused by name.
#[test]
fn the_space_and_its_camera_round_trip_through_json() {
    let m = CaptureModel::new(ndc_tiny(), (forward()).scene(), 1).unwrap();
    let json = serde_json::to_value(&m.config).unwrap();
    assert_eq!(json["space"], "ndc");
    assert_eq!(json["ndc_camera"]["width"], 16);
    assert_eq!(ModelConfig::parse("capture", json.clone()).unwrap(), ModelConfig::Capture(m.config.clone()));

    let ModelConfig::Capture(plain) = ModelConfig::preset("capture").unwrap() else { unreachable!() };
    let mut old = serde_json::to_value(&plain).unwrap();
    assert_eq!(old["space"], "contract");
    let fields = old.as_object_mut().unwrap();
    assert!(!fields.contains_key("ndc_camera"));
    fields.remove("space");
    assert_eq!(ModelConfig::parse("capture", old).unwrap(), ModelConfig::Capture(plain));

    let mut bad = json;
    bad["ndc_camera"]["near"] = serde_json::json!(-1.0);
    let err = ModelConfig::parse("capture", bad).unwrap_err().to_string();
    assert!(err.contains("near must be a finite number above 0"), "{err}");
    let mut unknown = serde_json::to_value(&m.config).unwrap();
    unknown["space"] = serde_json::json!("sphere");
    assert!(ModelConfig::parse("capture", unknown).unwrap_err().to_string().contains("sphere"));
}

/// With `near_from_data` (the default) a contraction's rays start at the
/// dataset's near bound in model units when that is further than `near`:
/// the ball scene's near of 1 world unit, with its cameras a median
/// `rig.radius` from their focus, is `camera_radius / rig.radius` model
/// units. A nearer bound, no bound (transforms.json's 0), the setting off or
/// NDC leave `near` as set; the model's own normalised scene (what a
/// checkpoint holds) resolves to the same `near` again.
#[test]
fn a_contractions_near_rises_to_the_datasets_near_bound() {
    // A world scale other than 1: the scene's box normalisation differs
    // from the world's units.
    let ds = crate::engine::dataset::synthetic::BallScene { scale: 2.5, ..Default::default() }.dataset();
    let scene = ds.scene();
    let rig = scene.rig.clone().unwrap();
    let c = CaptureConfig { camera_radius: 0.8, ..CaptureConfig::tiny() };
    assert!(c.near_from_data && c.near == 0.05);
    let want = ds.near * c.camera_radius / rig.radius;
    assert!(want > 0.2 && want < 0.3, "{want} (rig radius {})", rig.radius);
    let got = resolve(c.clone(), &scene).unwrap();
    assert!((got.near - want).abs() < 1e-6 * want, "{} vs {want}", got.near);
    assert_eq!(resolve(got.clone(), &capture_scene(&scene, &got)).unwrap(), got);
    let model = CaptureModel::new(c.clone(), scene.clone(), 0).unwrap();
    assert_eq!(model.scene().near, got.near);

    for (config, scene, why) in [
        (CaptureConfig { near_from_data: false, ..c.clone() }, scene.clone(), "off"),
        (c.clone(), Scene { near: 0.0, ..scene.clone() }, "no bound"),
    ] {
        assert_eq!(resolve(config, &scene).unwrap().near, 0.05, "{why}");
    }
    let further = CaptureConfig { near: 0.4, ..c.clone() };
    assert_eq!(resolve(further, &scene).unwrap().near, 0.4);
    let fwd = (forward()).scene();
    assert_eq!(resolve(ndc_tiny(), &fwd).unwrap().near, ndc_tiny().near);
}
