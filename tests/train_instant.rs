//! The fast model learns a tiny generated scene; its skipping (occupancy
//! grid, early termination) does not change what it renders.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod psnr;
    pub mod tiny;
}

use std::sync::atomic::AtomicBool;

use common::psnr::test_psnr;
use common::tiny::{self, InstantModel};
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::dataset::{Dataset, Split};
use radiance::engine::geometry::math::Ray;
use radiance::engine::metrics::psnr;
use radiance::engine::models::Model;
use radiance::engine::models::training::TrainConfig;
use radiance::engine::nn::adam::{Adam, AdamConfig};
use radiance::engine::train::trainer::{TrainState, Trainer};
use radiance::engine::view::{View, render_view};

fn trained() -> (Dataset, Box<dyn Model>) {
    let ds = BallScene::default().dataset();
    let model = InstantModel::new(tiny::instant_small(), ds.scene(), 2);
    let adam =
        Adam::new(AdamConfig { lr: 1e-2, lr_end: 1e-3, beta1: 0.9, beta2: 0.99, eps: 1e-15 }, model.params().len());
    let cfg = TrainConfig { random_background: true, ..tiny::train_config(2, 0, 200) };
    let mut t = Trainer::new(Box::new(model), adam, cfg, TrainState::default(), &ds);
    t.run(&AtomicBool::new(false), |_, _| true);
    let model = t.model;
    (ds, model)
}

fn max_diff(a: &View, b: &View) -> f32 {
    a.rgb.iter().zip(&b.rgb).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn instant_model_learns_and_skipping_is_lossless() {
    let (ds, model) = trained();
    let test: Vec<usize> = ds.split(Split::Test).to_vec();
    let mean = test_psnr(&*model, &ds);
    eprintln!("instant test PSNR {mean:.2} dB");
    assert!(mean > 25.0, "test PSNR {mean:.2} dB");

    // Rebuild the same model three ways from its parameters.
    let ckpt = radiance::engine::train::persist::to_checkpoint(
        &*model,
        &Adam::new(AdamConfig::default(), model.params().len()),
        &TrainConfig::default(),
        &TrainState { step: 200, ..Default::default() },
        None,
    );
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    ckpt.save(&path).unwrap();
    let restored = radiance::engine::train::persist::load(&path).unwrap().model;
    let cam = &ds.frames[test[0]].camera;
    let marched = render_view(&*restored, cam, ds.background);
    assert_eq!(marched.rgb, render_view(&*model, cam, ds.background).rgb, "checkpoint round trip");

    let any = restored;
    let raw: &InstantModel = any.as_any().downcast_ref().expect("an instant model");
    assert!(raw.grid.active && raw.grid.occupancy() < 0.5, "grid skips space: {}", raw.grid.occupancy());
    let mut dense = InstantModel::from_parts(raw.config.clone(), raw.scene().clone(), raw.params().to_vec()).unwrap();
    dense.grid.active = false;
    dense.config.min_transmittance = 0.0;
    dense.config.max_dropped_weight = 0.0;
    let dense_view = render_view(&dense, cam, ds.background);
    assert!(dense_view.stats.samples > 2 * marched.stats.samples, "skipping saves samples");
    // The occupancy grid skips only cells whose density is below its
    // threshold (its cutoff), checked at every lattice point of the view
    // by the reference renderer; the estimate from random points per cell
    // may miss a rare one.
    let rays: Vec<Ray> = (0..cam.height)
        .flat_map(|j| (0..cam.width).map(move |i| (i, j)))
        .map(|(i, j)| raw.scene().to_model(&cam.pixel_ray(i, j)))
        .collect();
    let reference = raw.reference_rays(&rays, ds.background);
    let skipped: usize = reference.iter().map(|r| r.skipped).sum();
    let above: usize = reference.iter().map(|r| r.skipped_above_cutoff).sum();
    eprintln!("{skipped} lattice points skipped, {above} of them at or above the cutoff {:.3}", raw.grid.cutoff);
    assert!(skipped > dense_view.stats.samples as usize / 2, "{skipped} skipped");
    assert!(above * 500 <= skipped, "{above} of {skipped} skipped lattice points are above the cutoff");
    // The reference is what the renderer computes with all skipping off.
    let full: Vec<f32> = reference.iter().flat_map(|r| r.out.rgb).collect();
    let d = dense_view.rgb.iter().zip(&full).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    assert!(d < 1e-4, "reference and dense renderer differ by {d}");
    // Skipping changes a pixel by at most the opacity it skipped, early
    // termination by at most its threshold, skipped colours by at most
    // their weight.
    let (min_t, max_dropped) = (raw.config.min_transmittance, raw.config.max_dropped_weight);
    for (k, r) in reference.iter().enumerate() {
        for c in 0..3 {
            let d = (dense_view.rgb[3 * k + c] - marched.rgb[3 * k + c]).abs();
            let bound = r.skipped_opacity + min_t + max_dropped + 1e-4;
            assert!(d <= bound, "pixel {k}: marching changed it by {d}, more than {bound}");
        }
    }
    eprintln!(
        "marched vs dense: max difference {:.5}, PSNR {:.1} dB (skipped opacity up to {:.3})",
        max_diff(&dense_view, &marched),
        psnr(&dense_view.rgb, &marched.rgb),
        reference.iter().map(|r| r.skipped_opacity).fold(0.0, f32::max)
    );
    assert!(psnr(&dense_view.rgb, &marched.rgb) > 35.0, "marching keeps the image");
    let variant = |min_t: f32, max_dropped: f32| {
        let mut m = InstantModel::from_parts(raw.config.clone(), raw.scene().clone(), raw.params().to_vec()).unwrap();
        m.grid = raw.grid.clone();
        m.config.min_transmittance = min_t;
        m.config.max_dropped_weight = max_dropped;
        render_view(&m, cam, ds.background)
    };
    let (min_t, max_dropped) = (raw.config.min_transmittance, raw.config.max_dropped_weight);
    let exact = variant(0.0, 0.0);
    let early = variant(min_t, 0.0);
    let d = max_diff(&exact, &early);
    assert!(d <= min_t + 1e-6, "early termination changed a pixel by {d}");
    // Skipping the colour of nearly empty samples changes a pixel by at
    // most the weight skipped, and it does skip some.
    let d = max_diff(&early, &marched);
    assert!(d <= max_dropped + 1e-6, "skipping negligible weights changed a pixel by {d}");
    assert!(d > 0.0, "some colours were skipped");
}
