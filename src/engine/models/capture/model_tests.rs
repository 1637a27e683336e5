//! Unit tests of `capture.rs`: the model's normalisation, the whole training
//! pass of `capture-tiny` against finite differences, rendering against the
//! training pass's compositing, and the saved state.

use super::*;
use crate::engine::dataset::textured::TexturedScene;
use crate::engine::geometry::math::Vec3;
use crate::engine::models::capture::pass::tests::check_pass_gradients;
use crate::engine::models::config::ModelConfig;
use crate::engine::nn::adam::LrGroup;

fn scene() -> Scene {
    (TexturedScene { width: 16, height: 12, views: 8, fov: 0.9 }.dataset()).scene()
}

fn tiny() -> CaptureConfig {
    let ModelConfig::Capture(c) = ModelConfig::preset("capture-tiny").unwrap() else { unreachable!() };
    c
}

/// The training cameras' focus goes to the origin and their median
/// distance to `camera_radius`; normalising again changes nothing.
#[test]
fn the_scene_is_centred_on_the_cameras_focus() {
    let world = scene();
    let rig = world.rig.clone().expect("a ring of cameras has a rig");
    let mut config = tiny();
    config.camera_radius = 0.5;
    let s = capture_scene(&world, &config);
    assert_eq!((s.centre, s.scale), (rig.focus, 0.5 / rig.radius));
    assert_eq!((s.aabb_min, s.aabb_max, s.near, s.far), ([-1.0; 3], [1.0; 3], 0.05, 1000.0));
    assert_eq!(capture_scene(&s, &config), s, "idempotent: a checkpoint stores the normalised scene");
    let ds = TexturedScene { width: 16, height: 12, views: 8, fov: 0.9 }.dataset();
    let mut distances: Vec<f32> = ds
        .frames
        .iter()
        .map(|f| {
            let c = Vec3::new(f.camera.c2w[0][3], f.camera.c2w[1][3], f.camera.c2w[2][3]);
            s.to_model(&Ray { origin: c, dir: Vec3::new(0.0, 0.0, 1.0) }).origin.norm()
        })
        .collect();
    distances.sort_by(f32::total_cmp);
    assert!((distances[distances.len() / 2] - 0.5).abs() < 0.05, "{distances:?}");
    // Without a rig, the box normalisation stays.
    let plain = Scene { rig: None, ..world.clone() };
    let p = capture_scene(&plain, &config);
    assert_eq!((p.centre, p.scale), (world.centre, world.scale));
}

/// Rays from the dataset's cameras in the model's space, from images 0-2.
fn rays(model: &CaptureModel, count: usize) -> Vec<TrainRay> {
    let ds = TexturedScene { width: 16, height: 12, views: 8, fov: 0.9 }.dataset();
    (0..count)
        .map(|k| {
            let f = &ds.frames[k % 3];
            let (i, j) = ((3 + 5 * k) as u32 % 16, (2 + 3 * k) as u32 % 12);
            TrainRay {
                ray: model.scene.to_model(&f.camera.pixel_ray(i, j)),
                target: f.image.rgb_on(i, j, ds.background),
                background: ds.background,
                index: k as u64,
                image: (k % 3) as u32,
                weight: 1.0,
            }
        })
        .collect()
}

/// A `capture-tiny` model with its parameters moved off their initial
/// values (zero embeddings, tiny tables), so every range has a gradient.
fn perturbed(seed: u64) -> CaptureModel {
    let mut m = CaptureModel::new(tiny(), scene(), seed).unwrap();
    let mut rng = Rng::new(seed + 1);
    for p in m.params.iter_mut() {
        *p += 0.2 * rng.normal();
    }
    m
}

#[test]
fn the_whole_pass_of_capture_tiny_matches_finite_differences_with_frozen_samples() {
    let m = perturbed(3);
    let mut ps = ParamLayout::default();
    let _ = layout(&mut ps, &m.config);
    let settings = PassSettings {
        cull: None,
        // Strong, so the proposals' gradients stand well above rounding.
        interlevel: 50.0,
        distortion: 0.01,
        pose: None,
        ..m.pass_settings(1)
    };
    // Step 0: the weights' exponent is 0, so every level spreads over the
    // whole ray and no proposal bounds the final weights trivially.
    let how = m.config.resampling(0).unwrap();
    let checked = check_pass_gradients(m.nets(), &ps.names, &settings, &rays(&m, 6), &mut Drawn::jittered(how, 5, 9));
    let names: Vec<&str> = checked.largest.iter().map(|(n, _)| n.as_str()).collect();
    assert!(names.contains(&"appearance.embedding") && names.contains(&"proposal1.hashgrid"), "{names:?}");
    // Each range has gradients over 3x the check's absolute tolerance.
    for (name, largest) in &checked.largest {
        assert!(*largest > 1e-3, "{name}: every gradient checked is tiny ({largest}): {:?}", checked.largest);
    }
}

/// Rendering (rounds, termination and dropping off) composites the final
/// samples exactly as the training pass does, with the mean appearance of
/// the images seen: rendered colours as targets give a zero colour loss.
#[test]
fn rendering_composites_as_training_does() {
    let mut m = perturbed(7);
    // Exactly: the half-precision tables are for speed (tested below).
    m.config.half_render = false;
    m.config.min_transmittance = 0.0;
    m.config.max_dropped_weight = 0.0;
    m.seen[1].store(true, Ordering::Relaxed);
    m.step = 40;
    let mut train = rays(&m, 9);
    for r in &mut train {
        r.image = 1;
    }
    let plain: Vec<Ray> = train.iter().map(|r| r.ray).collect();
    let mut out = vec![RayOutput::default(); plain.len()];
    let stats = m.render_rays(&plain, [1.0; 3], &RenderOptions::default(), &mut out);
    assert_eq!((stats.rays, stats.samples), (9, 9 * 8));
    for (r, o) in train.iter_mut().zip(&out) {
        assert!(o.opacity == 1.0, "the last interval is opaque: {o:?}");
        r.target = o.rgb;
    }
    let settings = PassSettings { cull: None, interlevel: 1.0, distortion: 0.0, pose: None, ..m.pass_settings(9) };
    let how = m.config.resampling(40).unwrap();
    let mut grads = vec![0.0; m.params.len()];
    let p = capture_pass(m.nets(), &settings, &train, &mut Drawn::centred(how), &mut Default::default(), &mut grads);
    assert!(p.sq_err < 1e-12, "{p:?}");
    // Another image's appearance is another colour.
    for r in &mut train {
        r.image = 2;
    }
    let q = capture_pass(m.nets(), &settings, &train, &mut Drawn::centred(how), &mut Default::default(), &mut grads);
    assert!(q.sq_err > 1e-6, "{q:?}");
}

/// Rendering from the half-precision tables (`half_render`, the default)
/// gives the colours of the f32 tables to within their rounding, and the
/// tables follow the parameters: after `params_mut`, a render reads the new
/// values, not the tables of the old ones.
#[test]
fn half_precision_renders_follow_the_parameters() {
    let mut m = perturbed(7);
    m.seen[1].store(true, Ordering::Relaxed);
    m.step = 40;
    let plain: Vec<Ray> = rays(&m, 64).iter().map(|r| r.ray).collect();
    let render = |m: &mut CaptureModel, half: bool| {
        m.params_mut();
        m.config.half_render = half;
        let mut out = vec![RayOutput::default(); plain.len()];
        m.render_rays(&plain, [1.0; 3], &RenderOptions::default(), &mut out);
        out.iter().flat_map(|o| o.rgb).collect::<Vec<f32>>()
    };
    let largest = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    let full = render(&mut m, false);
    let half = render(&mut m, true);
    if !crate::engine::nn::hashgrid::half_tables_supported() {
        assert_eq!(full, half, "no half tables on this CPU: the same f32 render");
        return;
    }
    assert!(m.render_tables().main.is_some() && m.render_tables().proposals.iter().all(Option::is_some));
    let d = largest(&full, &half);
    assert!(d > 0.0 && d < 5e-3, "half against f32: largest difference {d}");
    // New parameters: the next render rebuilds the tables.
    let mut rng = Rng::new(77);
    m.params_mut().iter_mut().for_each(|p| *p += 0.2 * rng.normal());
    let half2 = render(&mut m, true);
    let full2 = render(&mut m, false);
    assert!(largest(&full2, &half2) < 5e-3, "stale tables: {}", largest(&full2, &half2));
    assert!(largest(&full, &full2) > 0.05, "the new parameters change the render");
}

/// A view rendered with an image's appearance ([`RenderOptions::image`])
/// composites as training on that image does; the default options are the
/// mean appearance, and another image's appearance is another colour.
#[test]
fn rendering_with_an_images_appearance_is_that_images_colour() {
    let mut m = perturbed(9);
    // Exactly: the half-precision tables are for speed (tested below).
    m.config.half_render = false;
    m.config.min_transmittance = 0.0;
    m.config.max_dropped_weight = 0.0;
    m.seen[1].store(true, Ordering::Relaxed);
    m.seen[2].store(true, Ordering::Relaxed);
    m.step = 40;
    let mut train = rays(&m, 9);
    let plain: Vec<Ray> = train.iter().map(|r| r.ray).collect();
    let render = |options: &RenderOptions| {
        let mut out = vec![RayOutput::default(); plain.len()];
        m.render_rays(&plain, [1.0; 3], options, &mut out);
        out
    };
    let two = render(&RenderOptions { image: Some(2) });
    for (r, o) in train.iter_mut().zip(&two) {
        (r.target, r.image) = (o.rgb, 2);
    }
    let settings = PassSettings { cull: None, interlevel: 1.0, distortion: 0.0, pose: None, ..m.pass_settings(9) };
    let how = m.config.resampling(40).unwrap();
    let mut grads = vec![0.0; m.params.len()];
    let p = capture_pass(m.nets(), &settings, &train, &mut Drawn::centred(how), &mut Default::default(), &mut grads);
    assert!(p.sq_err < 1e-12, "{p:?}");
    let one = render(&RenderOptions { image: Some(1) });
    let differs = |a: &[RayOutput], b: &[RayOutput]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (0..3).map(|c| (x.rgb[c] - y.rgb[c]).abs()).fold(0.0, f32::max))
            .fold(0.0, f32::max)
    };
    assert!(differs(&one, &two) > 1e-3, "{}", differs(&one, &two));
    // The default options: the mean of images 1 and 2, as `render_rays`.
    let mean = render(&RenderOptions::default());
    let mut plain_out = vec![RayOutput::default(); plain.len()];
    m.render_rays(&plain, [1.0; 3], &RenderOptions::default(), &mut plain_out);
    assert_eq!(mean, plain_out);
    assert!(differs(&mean, &one) > 1e-4 && differs(&mean, &two) > 1e-4);
}

/// Rays without a finite origin or direction render as the background.
#[test]
fn unsamplable_rays_render_the_background() {
    let m = perturbed(2);
    let good = rays(&m, 2)[0].ray;
    let rays = [
        Ray { origin: Vec3::new(f32::NAN, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) },
        good,
        Ray { origin: Vec3::new(0.0, 0.0, 0.0), dir: Vec3::new(0.0, f32::INFINITY, 0.0) },
    ];
    let mut out = vec![RayOutput::default(); 3];
    let stats = m.render_rays(&rays, [0.2, 0.4, 0.6], &RenderOptions::default(), &mut out);
    let miss = RayOutput { rgb: [0.2, 0.4, 0.6], depth: 0.0, opacity: 0.0, median: 0.0 };
    assert_eq!((out[0], out[2]), (miss, miss));
    assert!(out[1].opacity > 0.99 && out[1].rgb.iter().all(|c| c.is_finite()), "{:?}", out[1]);
    assert_eq!(stats.rays, 3);
}

/// Training marks the images it sees; the record is the model's saved
/// state, and a missing or mis-sized record is an error.
#[test]
fn the_images_seen_are_saved_and_restored() {
    let m = perturbed(4);
    let mut train = rays(&m, 4);
    train[0].image = 3;
    train[1].image = 5;
    train[2].image = 3;
    train[3].image = 1_000_000; // beyond the table: trained without an embedding
    let ctx = StepCtx { seed: 0, step: 0, batch_rays: 4 };
    let stats = m.train_rays(&train, &ctx, &mut vec![0.0; m.params.len()]);
    assert!(stats.loss.is_finite() && stats.rays == 4, "{stats:?}");
    assert_eq!(m.seen_images(), vec![3, 5]);
    let mean = m.mean_embedding();
    let e = |i| m.field.appearance().embedding(&m.params, i).unwrap().to_vec();
    for (a, (x, y)) in mean.iter().zip(e(3).iter().zip(&e(5))) {
        assert!((a - 0.5 * (x + y)).abs() < 1e-6);
    }
    let state = m.state_tensors();
    let mut fresh = CaptureModel::from_parts(tiny(), m.scene.clone(), m.params.clone()).unwrap();
    assert!(fresh.seen_images().is_empty());
    let mut saved = state.clone();
    fresh.restore_state(&mut |name| saved.iter_mut().find(|(n, _)| n == name).map(|(_, v)| v.clone()), 77).unwrap();
    assert_eq!((fresh.seen_images(), fresh.step), (vec![3, 5], 77));
    assert_eq!(fresh.state_tensors(), state);
    let missing = fresh.restore_state(&mut |_| None, 1).unwrap_err();
    assert!(missing.to_string().contains("appearance.seen"), "{missing}");
    let short = fresh.restore_state(&mut |_| Some(vec![0.0; 3]), 1).unwrap_err();
    assert!(matches!(short, ModelError::Size { expected: 2000, found: 3, .. }), "{short}");
    let wrong = CaptureModel::from_parts(tiny(), m.scene.clone(), vec![0.0; 5]);
    assert!(wrong.is_err());
}

/// Training evaluates every proposal level of every samplable ray in full:
/// `coarse_samples + fine_samples` proposal samples per ray (16 + 8 for
/// `capture-tiny`). Rendering stops a ray's proposal samples behind opaque
/// matter, in rounds of 8 per level: at most as many, at least each
/// level's first round. Rays that cannot be sampled have none. With one
/// level, only the coarse ones.
#[test]
fn proposal_samples_are_counted_as_the_config_implies() {
    let m = perturbed(5);
    let per_ray = (m.config.proposal.coarse_samples + m.config.proposal.fine_samples) as u64;
    assert_eq!(per_ray, 24);
    let train = rays(&m, 7);
    let ctx = StepCtx { seed: 1, step: 3, batch_rays: 7 };
    let stats = m.train_rays(&train, &ctx, &mut vec![0.0; m.params.len()]);
    assert_eq!((stats.rays, stats.proposal_samples), (7, 7 * per_ray), "{stats:?}");
    assert!(stats.samples <= 7 * 8, "{stats:?}");

    let mut plain: Vec<Ray> = train.iter().map(|r| r.ray).collect();
    plain.push(Ray { origin: Vec3::new(f32::NAN, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) });
    let mut out = vec![RayOutput::default(); plain.len()];
    let rendered = m.render_rays(&plain, [1.0; 3], &RenderOptions::default(), &mut out);
    assert_eq!(rendered.rays, 8, "{rendered:?}");
    assert!((7 * (8 + 8)..=7 * per_ray).contains(&rendered.proposal_samples), "{rendered:?}");

    let mut one_level = tiny();
    one_level.proposal.fine_samples = 0;
    let one = CaptureModel::new(one_level, scene(), 2).unwrap();
    let stats = one.train_rays(&rays(&one, 5), &ctx, &mut vec![0.0; one.params.len()]);
    assert_eq!(stats.proposal_samples, 5 * 16, "{stats:?}");
}

/// Pose refinement off lays out the parameters of before it existed, with
/// no learning-rate group and no saved centres; on, 6 rows per image come
/// last, learning at `pose_lr_scale`.
#[test]
fn pose_rows_come_last_and_only_when_on() {
    let off = CaptureModel::new(tiny(), scene(), 1).unwrap();
    let on = CaptureModel::new(CaptureConfig { pose_refine: true, pose_lr_scale: 0.25, ..tiny() }, scene(), 1).unwrap();
    let (mut a, mut b) = (ParamLayout::default(), ParamLayout::default());
    assert!(layout(&mut a, &off.config).pose.is_none());
    let pose = layout(&mut b, &on.config).pose.expect("rows with pose_refine");
    assert_eq!(b.names[..b.names.len() - 1], a.names[..], "the networks are laid out as without poses");
    assert_eq!(pose.range, a.len..a.len + 6 * 2000);
    assert_eq!(on.params[..a.len], off.params[..], "the same seed initialises the networks alike");
    assert!(on.params[a.len..].iter().all(|&p| p == 0.0), "corrections start at zero");
    assert!(off.lr_groups().is_empty() && off.pose_report().is_none());
    assert_eq!(on.lr_groups(), vec![LrGroup { range: pose.range, scale: 0.25 }]);
    assert_eq!(off.state_tensors().len(), 1);
    // Old checkpoints' configurations have neither field: off, at 0.1.
    let mut json = serde_json::to_value(tiny()).unwrap();
    let fields = json.as_object_mut().unwrap();
    fields.remove("pose_refine");
    fields.remove("pose_lr_scale");
    let old: CaptureConfig = serde_json::from_value(json).unwrap();
    assert_eq!((old.pose_refine, old.pose_lr_scale), (false, 0.1));
    let ModelConfig::Capture(preset) = ModelConfig::preset("capture").unwrap() else { unreachable!() };
    assert!(!preset.pose_refine, "off in the capture preset (measured: it lowered held-out PSNR on fox and gold_cape)");
}

/// Training records each image's camera centre (saved and restored with
/// the model); the report and the common drift come from the corrections
/// of the images trained on. Held-out poses move by that drift: not at all
/// with zero corrections, and by a pure translation `t_g` (world units
/// `t_g / scale`) when every image moved by it.
#[test]
fn centres_drift_and_heldout_poses() {
    let mut m = CaptureModel::new(CaptureConfig { pose_refine: true, ..tiny() }, scene(), 2).unwrap();
    let train = rays(&m, 6);
    m.train_rays(&train, &StepCtx { seed: 0, step: 0, batch_rays: 6 }, &mut vec![0.0; m.params.len()]);
    let c2w = [[1.0, 0.0, 0.0, 0.5], [0.0, 0.0, -1.0, -2.0], [0.0, 1.0, 0.0, 0.25]];
    assert_eq!(m.heldout_pose(c2w), c2w, "no drift at zero corrections");
    let centres = m.trained_centres();
    assert_eq!(centres.iter().map(|c| c.0).collect::<Vec<_>>(), vec![0, 1, 2]);
    for (i, c) in &centres {
        let o = train.iter().find(|r| r.image == *i).unwrap().ray.origin;
        assert_eq!(c.map(|v| v as f32), [o.x, o.y, o.z]);
    }
    // Every trained image moved by the same translation; image 7 (never
    // trained on) by something else, which must not count.
    let pose = m.pose.clone().unwrap();
    for i in 0..3 {
        m.params[pose.row(i).unwrap()].copy_from_slice(&[0.02, -0.01, 0.03, 0.0, 0.0, 0.0]);
    }
    m.params[pose.row(7).unwrap()].copy_from_slice(&[1.0, 1.0, 1.0, 0.5, 0.5, 0.5]);
    let report = m.pose_report().unwrap();
    assert_eq!(report.images, 3);
    let pct = 100.0 * (0.02f64.powi(2) + 0.01f64.powi(2) + 0.03f64.powi(2)).sqrt();
    assert!((report.raw.translation_max_pct - pct).abs() < 1e-4 && report.relative.translation_max_pct < 1e-4);
    let moved = m.heldout_pose(c2w);
    let s = m.scene.scale;
    for (a, t) in [0.02f32, -0.01, 0.03].into_iter().enumerate() {
        assert!((moved[a][3] - (c2w[a][3] + t / s)).abs() < 1e-5, "{moved:?}");
        assert_eq!(moved[a][..3], c2w[a][..3], "no rotation");
    }
    // The centres come back with the model's state; without them, an error.
    let state = m.state_tensors();
    let mut fresh = CaptureModel::from_parts(m.config.clone(), m.scene.clone(), m.params.clone()).unwrap();
    let mut saved = state.clone();
    fresh.restore_state(&mut |name| saved.iter_mut().find(|(n, _)| n == name).map(|(_, v)| v.clone()), 3).unwrap();
    assert_eq!((fresh.trained_centres(), fresh.pose_report()), (centres, Some(report)));
    let only_seen =
        &mut |name: &str| state.iter().find(|(n, _)| n == name && name != "pose.centres").map(|(_, v)| v.clone());
    let missing = fresh.restore_state(only_seen, 3).unwrap_err();
    assert!(missing.to_string().contains("pose.centres"), "{missing}");
}

/// A deferred part leaves the main grid's gradient out of its buffer and
/// in its record; scattered, the record gives the grid what `train_rays`
/// gives, bit for bit for one part (several chunks of rays), and within
/// rounding for parts summed. The other parameters' gradients are the same
/// bits, and the statistics are equal. With pose refinement nothing is
/// deferred.
#[test]
fn deferred_grid_gradients_scatter_to_what_train_rays_gives() {
    let m = CaptureModel::new(CaptureConfig { chunk_rays: 4, ..tiny() }, scene(), 0).unwrap();
    let m = CaptureModel::from_parts(m.config.clone(), m.scene.clone(), perturbed(6).params).unwrap();
    let deferred = m.deferred().map(|d| d.grid()).expect("the main grid is deferred");
    let grid = deferred.params.clone();
    assert_eq!(grid, m.field.grid().params.clone());
    let train = rays(&m, 11);
    let ctx = StepCtx { seed: 2, step: 5, batch_rays: 11 };
    let n = m.params.len();
    let mut direct = vec![0.0f32; n];
    let stats = m.train_rays(&train, &ctx, &mut direct);
    let mut part = vec![0.0f32; n];
    let mut record = GridRecord::default();
    let deferred_stats = DeferredGrid::train_rays_deferred(&m, &train, &ctx, &mut part, &mut record);
    assert_eq!(stats, deferred_stats);
    assert!(record.points() > 0);
    assert!(part[grid.clone()].iter().all(|v| *v == 0.0), "the grid's gradient is not in the buffer");
    assert!(direct[grid.clone()].iter().filter(|v| **v != 0.0).count() > 50);
    deferred.scatter(std::slice::from_ref(&record), &mut part);
    assert!(direct.iter().zip(&part).all(|(a, b)| a.to_bits() == b.to_bits()), "one part: the same bits");

    // Two parts: their buffers summed against one buffer and both records.
    let (a, b) = train.split_at(6);
    let (mut ga, mut gb) = (vec![0.0f32; n], vec![0.0f32; n]);
    m.train_rays(a, &ctx, &mut ga);
    m.train_rays(b, &ctx, &mut gb);
    let mut records = vec![GridRecord::default(); 2];
    let (mut da, mut db) = (vec![0.0f32; n], vec![0.0f32; n]);
    DeferredGrid::train_rays_deferred(&m, a, &ctx, &mut da, &mut records[0]);
    DeferredGrid::train_rays_deferred(&m, b, &ctx, &mut db, &mut records[1]);
    deferred.scatter(&records, &mut da);
    let scale = ga.iter().chain(&gb).fold(0.0f32, |s, v| s.max(v.abs()));
    for i in 0..n {
        let (want, got) = (ga[i] + gb[i], da[i] + db[i]);
        assert!((want - got).abs() <= 1e-6 * scale, "parameter {i}: {got} against {want}");
    }

    // Pose refinement: no deferral, the record stays empty.
    let posed = CaptureModel::new(CaptureConfig { pose_refine: true, ..tiny() }, scene(), 1).unwrap();
    assert!(posed.deferred().map(|d| d.grid()).is_none());
    let (mut g1, mut g2) = (vec![0.0f32; posed.params.len()], vec![0.0f32; posed.params.len()]);
    posed.train_rays(&train, &ctx, &mut g1);
    DeferredGrid::train_rays_deferred(&posed, &train, &ctx, &mut g2, &mut record);
    assert_eq!(record.points(), 0);
    assert!(g1.iter().zip(&g2).all(|(a, b)| a.to_bits() == b.to_bits()));
}

/// A thread whose scratch was left deferring (a pass that panicked between
/// `begin_deferring` and `end_deferring`) still trains `train_rays` in
/// full: the grid's gradient lands in the buffer, as on a fresh thread.
#[test]
fn a_scratch_left_deferring_does_not_keep_the_grid_gradient() {
    let m = perturbed(7);
    let train = rays(&m, 5);
    let ctx = StepCtx { seed: 1, step: 2, batch_rays: 5 };
    let mut want = vec![0.0f32; m.params.len()];
    m.train_rays(&train, &ctx, &mut want);
    assert!(want[m.field.grid().params.clone()].iter().any(|v| *v != 0.0));
    with_scratch(|s| m.field.begin_deferring(&mut s.pass.ctx, &mut GridRecord::default()));
    let mut got = vec![0.0f32; m.params.len()];
    m.train_rays(&train, &ctx, &mut got);
    assert!(want.iter().zip(&got).all(|(a, b)| a.to_bits() == b.to_bits()));
}
