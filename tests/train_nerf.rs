//! The classic model learns a tiny procedurally generated scene.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod psnr;
    pub mod tiny;
}

use std::sync::atomic::AtomicBool;

use common::psnr::test_psnr;
use common::tiny::{self, NerfConfig, NerfModel};
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::models::Model;
use radiance::engine::nn::adam::{Adam, AdamConfig};
use radiance::engine::train::trainer::{TrainState, Trainer};
use radiance::engine::view::render_view;

#[test]
fn classic_nerf_learns_a_tiny_scene() {
    let ds = BallScene::default().dataset();
    let model = NerfModel::new(tiny::nerf_small(), ds.scene(), 1);
    let before = test_psnr(&model, &ds);
    let adam = Adam::new(AdamConfig { lr: 5e-3, lr_end: 5e-4, ..Default::default() }, model.params().len());
    let cfg = tiny::train_config(1, 256, 300);
    let mut trainer = Trainer::new(Box::new(model), adam, cfg, TrainState::default(), &ds);
    trainer.run(&AtomicBool::new(false), |_, _| true);
    let after = test_psnr(&*trainer.model, &ds);
    eprintln!("test PSNR before {before:.2} dB, after {after:.2} dB");
    assert!(after > 28.0 && after > before + 15.0, "before {before:.2}, after {after:.2}");

    // Early termination when rendering: rays stop being evaluated once their
    // transmittance falls below the threshold, which changes a pixel by at
    // most that threshold.
    let restored = {
        let r = trainer.model.as_any().downcast_ref::<NerfModel>().expect("a nerf model");
        NerfModel::from_parts(r.config.clone(), r.scene().clone(), r.params().to_vec()).unwrap()
    };
    let mut dense = NerfModel::from_parts(
        NerfConfig { min_transmittance: 0.0, ..restored.config.clone() },
        restored.scene().clone(),
        restored.params().to_vec(),
    )
    .unwrap();
    let trained = trainer.model.as_any().downcast_ref::<NerfModel>().unwrap();
    dense.copy_grid_from(trained);
    let cam = &ds.frames[ds.test[0]].camera;
    let cut = render_view(&*trainer.model, cam, ds.background);
    let full = render_view(&dense, cam, ds.background);
    let d = cut.rgb.iter().zip(&full.rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(d <= 1e-4 + 1e-6, "early termination changed a pixel by {d}");
    assert!(cut.stats.samples <= full.stats.samples, "{} vs {} samples", cut.stats.samples, full.stats.samples);
}
