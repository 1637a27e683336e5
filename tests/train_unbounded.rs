//! An unbounded scene (issue 12): a textured ball at the cameras' focus and
//! a textured background shell 30 times further out than the cameras,
//! rendered analytically. The real-capture model learns it to a stated
//! held-out PSNR; the fast model, whose box holds the ball and the cameras
//! but not the shell (as a capture's box holds its sparse points), does
//! worse on it.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod psnr;
}

use std::sync::atomic::AtomicBool;
use std::time::Instant;

use common::psnr::test_psnr;
use radiance::engine::dataset::{Dataset, DatasetFormat, Frame, Image, MaskUse};
use radiance::engine::geometry::camera::{Camera, look_at};
use radiance::engine::geometry::math::{Aabb, Ray, Vec3};
use radiance::engine::models::config::ModelConfig;
use radiance::engine::models::training::Budget;
use radiance::engine::train::trainer::{TrainState, Trainer};

/// Radius of the ball at the origin.
const BALL: f32 = 0.5;
/// Distance of the cameras from the origin.
const RING: f32 = 2.0;
/// Radius of the background shell around the origin: 30 camera distances.
const SHELL: f32 = 30.0 * RING;
/// Half-width of the dataset's box (the ball and the cameras).
const BOX: f32 = 2.5;

/// The ball's colour at unit-sphere point `p`: smooth bands.
fn ball_colour(p: Vec3) -> [f32; 3] {
    [0.5 + 0.4 * (4.0 * p.x).sin(), 0.5 + 0.4 * (4.0 * p.y + 1.0).sin(), 0.5 + 0.4 * (4.0 * p.z + 2.0).sin()]
}

/// The shell's colour at unit direction `q` from the origin: bands in
/// azimuth and height, several per view.
fn shell_colour(q: Vec3) -> [f32; 3] {
    let u = q.y.atan2(q.x);
    let v = q.z;
    [0.5 + 0.35 * (3.0 * u).sin(), 0.5 + 0.35 * (5.0 * v + u).sin(), 0.5 + 0.35 * (2.0 * u - 3.0 * v).cos()]
}

/// The colour along `ray` (unit direction, origin inside the shell): the
/// ball where the ray meets it, else the shell.
fn shade(ray: &Ray) -> [f32; 3] {
    let b = ray.origin.dot(ray.dir);
    let sphere = |r: f32| {
        let disc = b * b - (ray.origin.dot(ray.origin) - r * r);
        (disc >= 0.0).then(|| (-b - disc.sqrt(), -b + disc.sqrt()))
    };
    if let Some((t, _)) = sphere(BALL).filter(|(t, _)| *t > 0.0) {
        return ball_colour(ray.at(t) * (1.0 / BALL));
    }
    // Inside the shell, the far root is the hit.
    let (_, t) = sphere(SHELL).expect("the cameras are inside the shell");
    shell_colour(ray.at(t) * (1.0 / SHELL))
}

/// `views` cameras on a ring of radius [`RING`] around the ball, looking
/// at it, alternately higher and lower, at `width`x`height` with a 0.9 rad
/// horizontal field of view; every 6th view held out. Each pixel averages
/// 3x3 rays. The box holds the ball and the cameras, not the shell.
fn dataset(views: usize, width: u32, height: u32) -> Dataset {
    let frames: Vec<Frame> = (0..views)
        .map(|k| {
            let a = k as f32 / views as f32 * std::f32::consts::TAU;
            let z = if k % 2 == 0 { 0.3 } else { -0.2 };
            let eye = Vec3::new(RING * a.cos(), RING * a.sin(), z);
            let pose = look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
            let camera = Camera::from_fov(width, height, 0.9, pose);
            let mut rgba = Vec::with_capacity((width * height * 4) as usize);
            for j in 0..height {
                for i in 0..width {
                    let mut c = [0.0f32; 3];
                    for s in 0..9 {
                        let (sx, sy) = ((s % 3) as f32, (s / 3) as f32);
                        let v = shade(&camera.ray(i as f32 + (sx + 0.5) / 3.0, j as f32 + (sy + 0.5) / 3.0));
                        (0..3).for_each(|ch| c[ch] += v[ch] / 9.0);
                    }
                    rgba.extend(c.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).chain([255]));
                }
            }
            let image = Image { width, height, rgba, has_alpha: false };
            Frame { name: format!("v{k:02}"), path: format!("v{k:02}.png").into(), camera, image, mask: None }
        })
        .collect();
    let test: Vec<usize> = (0..views).filter(|k| k % 6 == 3).collect();
    Dataset {
        format: DatasetFormat::Blender,
        root: ".".into(),
        frames,
        train: (0..views).filter(|k| k % 6 != 3).collect(),
        val: test.clone(),
        test,
        near: 0.1,
        far: 2.0 * SHELL,
        aabb: Aabb { min: Vec3::splat(-BOX), max: Vec3::splat(BOX) },
        background: [1.0; 3],
        warnings: Vec::new(),
        masks: MaskUse::Off,
        mask_folder: None,
    }
}

/// Trains `preset` on `ds` for `steps` steps with `seed`; returns the
/// trainer and the held-out PSNR before and after.
fn train<'a>(ds: &'a Dataset, preset: &str, seed: u64, steps: u64) -> (Trainer<'a>, f64, f64) {
    let config = ModelConfig::preset(preset).unwrap();
    let (model, adam) = config.build_with_adam(ds.scene(), seed, None).unwrap();
    let budget = Budget { steps: Some(steps), seconds: None };
    let mut t = Trainer::new(model, adam, config.train_config(seed, 1024, budget), TrainState::default(), ds);
    let before = test_psnr(&*t.model, ds);
    t.run(&AtomicBool::new(false), |_, _| true);
    let after = test_psnr(&*t.model, ds);
    (t, before, after)
}

/// 500 steps of `capture-tiny` and of `instant-tiny` (seed 1 each, about
/// 3 s and 2 s here) on 72 views at 24x18, 60 of them trained on.
///
/// Observed held-out PSNR (from about 11.5 dB untrained): `capture-tiny`
/// 31.61, 31.45, 29.08, 31.54, 29.83, 30.20 dB for seeds 1-6;
/// `instant-tiny` 21.00, 20.30, 20.52, 19.61 dB for seeds 1-4. Asserted:
/// `capture-tiny` at least 26 dB, and at least 5 dB above `instant-tiny`
/// (observed: 10.6 dB for seed 1).
///
/// Sparser views do not make a test: with 24 views at 32x24 (20 trained
/// on, 18 deg apart) `capture-tiny` fits the training views (26 dB) but
/// its held-out PSNR went to 26.6, 23.4 and 26.3 dB for seeds 1, 2, 4 and
/// fell below the untrained model's (12.1, 10.5, 10.4 dB) for seeds 3, 5,
/// 6, which rendered their training views at 24-26 dB: geometry that only
/// the training views agree with. 48 views still failed one seed of three.
#[test]
fn the_capture_model_learns_an_unbounded_scene_and_the_box_bounded_one_does_worse() {
    let ds = dataset(72, 24, 18);
    let steps = 500;
    let start = Instant::now();
    let (capture, before, after) = train(&ds, "capture-tiny", 1, steps);
    let capture_secs = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let (instant, instant_before, instant_after) = train(&ds, "instant-tiny", 1, steps);
    let instant_secs = start.elapsed().as_secs_f64();
    eprintln!(
        "capture-tiny: held-out PSNR {before:.2} -> {after:.2} dB in {capture_secs:.1} s; \
         instant-tiny: {instant_before:.2} -> {instant_after:.2} dB in {instant_secs:.1} s"
    );
    assert!(after >= 26.0, "capture-tiny: held-out PSNR {before:.2} -> {after:.2} dB");
    assert!(
        after - instant_after >= 5.0,
        "capture-tiny {after:.2} dB against instant-tiny {instant_after:.2} dB: less than 5 dB apart"
    );
    // Every training ray had its two proposal levels (16 + 8 samples)
    // evaluated, whatever its main samples did; the fast model has none.
    let s = &capture.state;
    assert!(s.rays > 0 && s.proposal_samples == 24 * s.rays, "{s:?}");
    assert_eq!(instant.state.proposal_samples, 0);
}
