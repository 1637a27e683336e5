//! Camera pose refinement (design `real-captures.md` 2.7) undoes a known
//! error of the training cameras: the tests' generated scene with each
//! training camera turned and moved by its own small random amount, trained
//! with `capture-tiny` with and without refinement.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod psnr;
}

use std::sync::atomic::AtomicBool;

use common::psnr::ground_truth;
use radiance::engine::dataset::Dataset;
use radiance::engine::dataset::textured::TexturedScene;
use radiance::engine::geometry::so3;
use radiance::engine::metrics::psnr;
use radiance::engine::models::Model;
use radiance::engine::models::capture::{CaptureConfig, CaptureModel};
use radiance::engine::models::config::ModelConfig;
use radiance::engine::models::training::Budget;
use radiance::engine::rng::Rng;
use radiance::engine::train::trainer::{TrainState, Trainer};
use radiance::engine::view::render_view;

/// Degrees each training camera is turned by (about a random axis
/// through its centre).
const TURN_DEG: f64 = 1.5;
/// How far each is moved (random direction), as a fraction of the
/// cameras' distance from the focus.
const SHIFT: f64 = 0.02;

/// A training frame's pose error: its index, the rotation vector it was
/// turned by and the world translation it was moved by.
type PoseError = (usize, [f64; 3], [f64; 3]);
/// A camera's correction `(τ, ω)` (model units) and its centre `c`.
type Row = ([f64; 3], [f64; 3], [f64; 3]);

/// `train_capture.rs`'s scene (a textured ball on a textured ground, a
/// ring of 36 cameras at 40x30, every 6th held out), with the training
/// cameras' poses wrong by their own `(ω_i, Δc_i)` (world units), returned
/// per training frame.
fn perturbed() -> (Dataset, Vec<PoseError>) {
    let mut ds = TexturedScene { width: 40, height: 30, views: 36, fov: 0.9 }.dataset();
    let n = ds.frames.len();
    ds.test = (0..n).filter(|k| k % 6 == 3).collect();
    ds.val = ds.test.clone();
    ds.train = (0..n).filter(|k| k % 6 != 3).collect();
    let radius = f64::from(ds.scene().rig.unwrap().radius);
    let mut rng = Rng::new(11);
    let mut unit = || {
        let v: [f64; 3] = std::array::from_fn(|_| f64::from(rng.normal()));
        let len = so3::norm(v);
        v.map(|x| x / len)
    };
    let mut errors = Vec::new();
    for &k in &ds.train {
        let omega = unit().map(|x| x * TURN_DEG.to_radians());
        let shift = unit().map(|x| x * SHIFT * radius);
        let c2w = &mut ds.frames[k].camera.c2w;
        let axes: so3::Mat3 = std::array::from_fn(|i| std::array::from_fn(|j| f64::from(c2w[i][j])));
        let turned = so3::mul(&so3::exp(omega), &axes);
        for i in 0..3 {
            for j in 0..3 {
                c2w[i][j] = turned[i][j] as f32;
            }
            c2w[i][3] += shift[i] as f32;
        }
        errors.push((k, omega, shift));
    }
    (ds, errors)
}

/// `capture-tiny` with or without pose refinement, trained `steps` steps.
fn train(ds: &Dataset, pose_refine: bool, steps: u64) -> Box<dyn Model> {
    let config = ModelConfig::Capture(CaptureConfig { pose_refine, ..CaptureConfig::tiny() });
    let (model, adam) = config.build_with_adam(ds.scene(), 1, None).unwrap();
    let train = config.train_config(1, 1024, Budget { steps: Some(steps), seconds: None });
    let mut t = Trainer::new(model, adam, train, TrainState::default(), ds);
    t.run(&AtomicBool::new(false), |_, _| true);
    t.model
}

/// Mean PSNR of the held-out views rendered from `models::heldout_pose`.
fn heldout_psnr(model: &dyn Model, ds: &Dataset) -> f64 {
    let test = &ds.test;
    let total: f64 = test
        .iter()
        .map(|&k| {
            let mut cam = ds.frames[k].camera.clone();
            cam.c2w = radiance::engine::models::heldout_pose(model, cam.c2w);
            psnr(&render_view(model, &cam, ds.background).rgb, &ground_truth(ds, k))
        })
        .sum();
    total / test.len() as f64
}

/// Residual rotation (degrees) and translation (% of the camera radius)
/// errors, mean over the training cameras, after the common drift is taken
/// out: `delta[i] = (τ_i, ω_i)` in model units against the cameras'
/// centres `c_i`, the drift fitted as the model fits it (`ω_g = mean ω`,
/// `t_g = mean(τ - ω_g × c)`).
fn relative_error(rows: &[Row], radius: f64) -> (f64, f64) {
    let n = rows.len() as f64;
    let mean = |f: &dyn Fn(&Row) -> [f64; 3]| {
        rows.iter().fold([0.0; 3], |a, r| {
            let v = f(r);
            std::array::from_fn(|k| a[k] + v[k] / n)
        })
    };
    let wg = mean(&|r| r.1);
    let tg = mean(&|r| {
        let x = so3::cross(wg, r.2);
        std::array::from_fn(|k| r.0[k] - x[k])
    });
    let (mut rot, mut tra) = (0.0, 0.0);
    for (tau, omega, c) in rows {
        let x = so3::cross(wg, *c);
        let eta: [f64; 3] = std::array::from_fn(|k| tau[k] - x[k] - tg[k]);
        let eps: [f64; 3] = std::array::from_fn(|k| omega[k] - wg[k]);
        rot += so3::norm(eps).to_degrees() / n;
        tra += 100.0 * so3::norm(eta) / radius / n;
    }
    (rot, tra)
}

/// The training cameras turned by 1.5 deg and moved by 2% of their
/// distance from the focus, each its own way; 600 steps of `capture-tiny`
/// with refinement (its default learning-rate scale, 0.1). The ideal
/// correction of camera `i` is `ω* = -ω_i`, `τ* = -Δc_i` (model units);
/// without refinement the cameras stay wrong by the whole perturbation:
/// 1.48 deg and 1.90% on average after taking out its common part.
/// Observed (6.7 s for both runs, 2 threads): the refined cameras are wrong
/// by 0.87 deg and 1.00% (0.59 and 0.52 of the error), and the held-out
/// views score 19.42 dB against 17.90 dB without refinement. With 1200
/// steps the rotation error fell to 0.36 of it but the translation's rose
/// to 0.69 and held-out views scored 18.45 dB against 17.38: on images of
/// 40x30 pixels a small turn and a small sideways move of a camera look
/// alike.
#[test]
fn refinement_undoes_most_of_a_known_pose_error() {
    let (ds, errors) = perturbed();
    let steps = 600;
    let refined = train(&ds, true, steps);
    let capture = refined.as_any().downcast_ref::<CaptureModel>().unwrap();
    let (scale, centre) = (f64::from(refined.scene().scale), refined.scene().centre);
    let radius = f64::from(capture.config.camera_radius);
    let layout_pose = {
        let mut ps = radiance::engine::nn::linear::ParamLayout::default();
        radiance::engine::models::capture::layout(&mut ps, &capture.config).pose.unwrap()
    };
    let (mut before, mut after) = (Vec::new(), Vec::new());
    for &(k, omega, shift) in &errors {
        let c2w = ds.frames[k].camera.c2w;
        let c: [f64; 3] = std::array::from_fn(|a| (f64::from(c2w[a][3]) - f64::from(centre[a])) * scale);
        let ideal_tau = shift.map(|v| -v * scale);
        let ideal_omega = omega.map(|v| -v);
        let row = &refined.params()[layout_pose.row(k as u32).unwrap()];
        let (tau, w): ([f64; 3], [f64; 3]) =
            (std::array::from_fn(|a| f64::from(row[a])), std::array::from_fn(|a| f64::from(row[3 + a])));
        before.push((ideal_tau, ideal_omega, c));
        after.push((std::array::from_fn(|a| tau[a] - ideal_tau[a]), std::array::from_fn(|a| w[a] - ideal_omega[a]), c));
    }
    let (rot0, tra0) = relative_error(&before, radius);
    let (rot1, tra1) = relative_error(&after, radius);
    let plain = train(&ds, false, steps);
    let (with, without) = (heldout_psnr(&*refined, &ds), heldout_psnr(&*plain, &ds));
    let report = capture.pose_report().unwrap();
    eprintln!(
        "pose error without refinement {rot0:.3} deg, {tra0:.3}%; refined {rot1:.3} deg, {tra1:.3}% \
         ({:.2} and {:.2} of it); held-out {with:.2} dB refined, {without:.2} dB not; {report}",
        rot1 / rot0,
        tra1 / tra0
    );
    assert_eq!(report.images, ds.train.len());
    assert!(rot1 < 0.75 * rot0, "rotation error {rot0:.3} -> {rot1:.3} deg");
    assert!(tra1 < 0.75 * tra0, "translation error {tra0:.3} -> {tra1:.3}%");
    assert!(with > without + 0.75, "held-out PSNR {with:.2} dB refined, {without:.2} dB not");
    // Held-out images get no correction.
    for &k in &ds.test {
        assert!(refined.params()[layout_pose.row(k as u32).unwrap()].iter().all(|&v| v == 0.0), "image {k}");
    }
}
