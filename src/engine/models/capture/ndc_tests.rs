//! Unit tests of `capture.rs` in NDC space (`space: ndc`): the whole
//! training pass against finite differences through the NDC map, and
//! rendering and training on a forward-facing scene.

use super::*;
use crate::engine::dataset::Dataset;
use crate::engine::dataset::textured::TexturedScene;
use crate::engine::fields::space::SpaceMap;
use crate::engine::models::capture::pass::tests::check_pass_gradients;
use crate::engine::models::config::ModelConfig;

fn forward() -> Dataset {
    TexturedScene { width: 16, height: 12, views: 9, fov: 0.9 }.forward_facing()
}

/// `capture-tiny` in NDC on [`forward`], its parameters moved off their
/// initial values (zero embeddings, tiny tables) so every range has a
/// gradient.
fn perturbed(seed: u64) -> CaptureModel {
    let ModelConfig::Capture(c) = ModelConfig::preset("capture-tiny").unwrap() else { unreachable!() };
    let config = CaptureConfig { space: Space::Ndc, ..c };
    let mut m = CaptureModel::new(config, (forward()).scene(), seed).unwrap();
    let mut rng = Rng::new(seed + 1);
    for p in m.params.iter_mut() {
        *p += 0.2 * rng.normal();
    }
    m
}

/// Rays of the training views in the model's space, spread over each image.
fn rays(model: &CaptureModel, count: usize) -> Vec<TrainRay> {
    let ds = forward();
    (0..count)
        .map(|k| {
            let image = ds.train[k % ds.train.len()];
            let f = &ds.frames[image];
            let (i, j) = ((3 + 5 * k) as u32 % 16, (2 + 7 * k) as u32 % 12);
            TrainRay {
                ray: model.scene.to_model(&f.camera.pixel_ray(i, j)),
                target: f.image.rgb_on(i, j, ds.background),
                background: ds.background,
                index: k as u64,
                image: image as u32,
                weight: 1.0,
            }
        })
        .collect()
}

/// The pass's gradient through the NDC map (the main field and both
/// proposal networks, with the selector zeroing what lies before the near
/// plane) matches central differences of its loss.
#[test]
fn the_whole_pass_in_ndc_matches_finite_differences_with_frozen_samples() {
    let m = perturbed(3);
    assert!(matches!(m.field.space(), SpaceMap::Ndc(_)));
    let mut ps = ParamLayout::default();
    layout(&mut ps, &m.config);
    let settings = PassSettings { cull: None, interlevel: 50.0, distortion: 0.01, pose: None, ..m.pass_settings(1) };
    let how = m.config.resampling(0).unwrap();
    let checked = check_pass_gradients(m.nets(), &ps.names, &settings, &rays(&m, 6), &mut Drawn::jittered(how, 5, 9));
    let names: Vec<&str> = checked.largest.iter().map(|(n, _)| n.as_str()).collect();
    assert!(names.contains(&"proposal0.hashgrid") && names.contains(&"proposal1.hashgrid"), "{names:?}");
    for (name, largest) in &checked.largest {
        assert!(*largest > 1e-3, "{name}: every gradient checked is tiny ({largest}): {:?}", checked.largest);
    }
}

/// An NDC model trains (finite loss, a gradient) and renders finite
/// colours and depths for the held-out views' rays, and for rays that
/// start behind the reference camera or look away from the frustum.
#[test]
fn an_ndc_model_trains_and_renders_finite_values() {
    let m = perturbed(4);
    let train = rays(&m, 8);
    let mut grads = vec![0.0; m.params.len()];
    let stats = m.train_rays(&train, &StepCtx { seed: 1, step: 2, batch_rays: 8 }, &mut grads);
    assert!(stats.loss.is_finite() && stats.loss > 0.0 && stats.rays == 8, "{stats:?}");
    assert!(grads.iter().all(|g| g.is_finite()) && grads.iter().any(|&g| g != 0.0));

    let ds = forward();
    let cam = &ds.frames[ds.test[0]].camera;
    let mut plain: Vec<Ray> = (0..12).map(|k| m.scene.to_model(&cam.pixel_ray(k, k % 12))).collect();
    // Looking back at the cameras from far in front, and starting far
    // behind them: through the frustum's outside.
    let o = plain[0].origin;
    plain.push(Ray { origin: o - plain[0].dir * -50.0, dir: plain[0].dir * -1.0 });
    plain.push(Ray { origin: o - plain[0].dir * 50.0, dir: plain[0].dir });
    let mut out = vec![RayOutput::default(); plain.len()];
    let r = m.render_rays(&plain, [1.0; 3], &RenderOptions::default(), &mut out);
    assert_eq!(r.rays, 14);
    for o in &out {
        assert!(o.rgb.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)), "{o:?}");
        assert!(o.depth.is_finite() && o.opacity.is_finite(), "{o:?}");
    }
}
