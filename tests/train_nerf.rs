//! The classic model learns a tiny procedurally generated scene.

use std::sync::atomic::AtomicBool;

use radiance::engine::dataset::Split;
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::geometry::scene::Scene;
use radiance::engine::metrics::psnr;
use radiance::engine::models::Model;
use radiance::engine::models::nerf::{NerfConfig, NerfModel};
use radiance::engine::nn::adam::{Adam, AdamConfig};
use radiance::engine::nn::nerf_net::NetConfig;
use radiance::engine::render::render_view;
use radiance::engine::train::trainer::{Budget, TrainConfig, TrainState, Trainer};

fn test_psnr(model: &dyn Model, ds: &radiance::engine::dataset::Dataset) -> f64 {
    let mut total = 0.0;
    let mut n = 0;
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
fn classic_nerf_learns_a_tiny_scene() {
    let ds = BallScene::default().dataset();
    let config = NerfConfig {
        net: NetConfig { pos_freqs: 4, dir_freqs: 2, width: 32, depth: 4, skip: 2, dir_width: 16 },
        coarse_samples: 16,
        fine_samples: 16,
        ..Default::default()
    };
    let model = NerfModel::new(config, Scene::from_dataset(&ds), 1);
    let before = test_psnr(&model, &ds);
    let adam = Adam::new(AdamConfig { lr: 5e-3, lr_end: 5e-4, ..Default::default() }, model.params().len());
    let cfg = TrainConfig {
        seed: 1,
        batch_rays: 256,
        budget: Budget { steps: Some(300), seconds: None },
        ..Default::default()
    };
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
