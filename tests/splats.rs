//! Splats made from a trained model: baking a generated scene reaches a
//! stated held-out PSNR, renders views through the rasteriser, and the
//! `.ply` export is read back by an independent reader (`plyfile`, from
//! PyPI, which `scripts/setup` installs) with every field and value as
//! written.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod tiny;
}

use std::process::Command;
use std::sync::atomic::AtomicBool;

use common::tiny::in_pool;
use radiance::cli::SPLATS_FIELD_MIN_STEPS;
use radiance::engine::bake::{BakeSettings, bake};
use radiance::engine::dataset::Dataset;
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::dataset::textured::TexturedScene;
use radiance::engine::geometry::camera::Camera;
use radiance::engine::metrics::psnr;
use radiance::engine::models::Model;
use radiance::engine::models::RenderOptions;
use radiance::engine::models::config::ModelConfig;
use radiance::engine::models::splats::export::{self, Format};
use radiance::engine::models::training::Budget;
use radiance::engine::view::{render_view, render_view_with};

/// A textured ball on a textured ground from a ring of 24 cameras at 64x48.
fn dataset() -> Dataset {
    TexturedScene { width: 64, height: 48, views: 24, fov: 0.9 }.dataset()
}

/// Taken by every test here for its whole run: `train --model splats`
/// trains by the clock, and its field, given a third of 30 s, places
/// nothing when the other tests share the two cores with it.
static ALONE: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn alone() -> std::sync::MutexGuard<'static, ()> {
    ALONE.lock().unwrap_or_else(|e| e.into_inner())
}

/// Mean held-out PSNR of `model` on `ds`'s test views.
fn heldout_psnr(model: &dyn Model, ds: &Dataset) -> f64 {
    heldout_psnr_with(model, ds, |_| RenderOptions::default())
}

/// [`heldout_psnr`], each view rendered with the options `options` gives
/// its camera.
fn heldout_psnr_with(model: &dyn Model, ds: &Dataset, options: impl Fn(&Camera) -> RenderOptions) -> f64 {
    let views = ds.split(radiance::engine::dataset::Split::Test);
    let mut sum = 0.0;
    for &i in views {
        let f = &ds.frames[i];
        let v = render_view_with(model, &f.camera, ds.background, &options(&f.camera));
        let truth: Vec<f32> = (0..f.image.height)
            .flat_map(|j| (0..f.image.width).flat_map(move |i| f.image.rgb_on(i, j, ds.background)))
            .collect();
        sum += psnr(&v.rgb, &truth);
    }
    sum / views.len() as f64
}

#[test]
fn baking_a_trained_scene_keeps_its_heldout_psnr() {
    let _alone = alone();
    let ds = dataset();
    in_pool(2, || {
        let config = ModelConfig::preset("instant-tiny").unwrap();
        let mut t = common::tiny::trainer(&config, &ds, 3, 600);
        for _ in 0..600 {
            t.step();
        }
        let source = heldout_psnr(t.model.as_ref(), &ds);
        let mut settings = BakeSettings {
            budget: Budget { seconds: None, steps: Some(300) },
            initial: Some(20_000),
            ..Default::default()
        };
        // Degree 3, not the default 1: from this blurry source (its
        // geometry is off) the higher degrees carry what each view sees
        // of the texture. 300 steps on 2 threads: degree 0 20.16 dB, 1
        // 21.53, 3 25.29.
        settings.splats.sh_degree = 3;
        let mut reports = 0;
        let (splats, adam, steps) = bake(t.model.as_ref(), &ds, &settings, None, &AtomicBool::new(false), |p| {
            assert!(p.gaussians > 0 && p.psnr.is_finite());
            reports += 1;
        })
        .unwrap();
        assert_eq!((steps, reports), (300, 300));
        assert_eq!(adam.m.len(), splats.params().len());
        assert!(splats.looks().is_none(), "an instant source has one look, and so have its splats");
        let baked = heldout_psnr(&splats, &ds);
        println!("source {source:.2} dB, splats {baked:.2} dB, {} Gaussians", splats.layout().n);
        // Measured on 2 threads: source 19.69 dB, splats 27.45 dB (9376
        // Gaussians); the figures are deterministic on a thread count.
        assert!(source > 19.0, "the source trained: {source:.2} dB");
        assert!(baked >= 24.5, "splats {baked:.2} dB");
        assert!(baked >= source - 0.5, "splats {baked:.2} dB against the source's {source:.2} dB");

        // The first half of the steps at half size, which these 64x48
        // photos are too small to gain by (and are not fitted so by
        // default): measured 23.94 dB.
        settings.coarse_min_pixels = 0;
        let (coarse, _, _) = bake(t.model.as_ref(), &ds, &settings, None, &AtomicBool::new(false), |_| {}).unwrap();
        let coarse = heldout_psnr(&coarse, &ds);
        println!("splats fitted at half size first {coarse:.2} dB");
        assert!(coarse >= 23.5, "splats fitted at half size first {coarse:.2} dB");
    });
}

/// From a source with a per-photo appearance (the capture model), each
/// photo is fitted through its own colour correction, kept with the splats:
/// on a ring whose photos' exposure rises and falls around it, a held-out
/// view that takes its nearest training photo's look scores well above the
/// splats' own look, the corrections follow the exposures, and they come
/// back from the checkpoint's tensors to the bit.
#[test]
fn splats_from_a_capture_take_each_photos_look() {
    use radiance::engine::view::appearance::held_out_options;
    let _alone = alone();
    let mut ds = dataset();
    let n = ds.frames.len();
    ds.train = (0..n).filter(|k| k % 4 != 2).collect();
    ds.test = (0..n).filter(|k| k % 4 == 2).collect();
    ds.val = ds.test.clone();
    // Brighter and darker by turns, four photos at a time: a held-out photo
    // (the third of its four) shares its neighbours' exposure, which no
    // view-dependent colour of the splats can follow around the ring.
    let gain = |k: usize| if (k / 4).is_multiple_of(2) { 1.25 } else { 0.8 };
    for (k, f) in ds.frames.iter_mut().enumerate() {
        for p in f.image.rgba.chunks_exact_mut(4) {
            for c in &mut p[..3] {
                *c = (*c as f32 * gain(k)).round().min(255.0) as u8;
            }
        }
    }
    in_pool(2, || {
        let config = ModelConfig::preset("capture-tiny").unwrap();
        let mut t = common::tiny::trainer(&config, &ds, 3, 600);
        for _ in 0..600 {
            t.step();
        }
        let settings = BakeSettings {
            budget: Budget { seconds: None, steps: Some(300) },
            initial: Some(20_000),
            ..Default::default()
        };
        let (splats, _, _) = bake(t.model.as_ref(), &ds, &settings, None, &AtomicBool::new(false), |_| {}).unwrap();
        let looks = splats.looks().expect("a capture source's splats have looks");
        assert_eq!(looks.images, ds.train.iter().map(|&k| k as u32).collect::<Vec<_>>());
        let nearest = heldout_psnr_with(&splats, &ds, |camera| held_out_options(&splats, camera));
        let own = heldout_psnr(&splats, &ds);
        println!("held out: the nearest photo's look {nearest:.2} dB, the splats' own {own:.2} dB");

        // Measured: 13.53 dB against 13.14 (the splats fit each photo's
        // exposure partly with their view-dependent colours too).
        assert!(nearest > own + 0.2, "nearest {nearest:.2} dB, own {own:.2} dB");
        // Every brighter photo's correction draws a mid grey brighter than
        // every darker photo's (measured: 0.56-0.58 against 0.43-0.44).
        let grey = |k: &usize| looks.of(*k as u32).unwrap().map([0.5; 3]).iter().sum::<f32>() / 3.0;
        let (bright, dark): (Vec<usize>, Vec<usize>) = ds.train.iter().partition(|&&k| gain(k) > 1.0);
        let darkest_bright = bright.iter().map(grey).fold(f32::INFINITY, f32::min);
        let brightest_dark = dark.iter().map(grey).fold(0.0, f32::max);
        assert!(darkest_bright > brightest_dark + 0.05, "{darkest_bright} against {brightest_dark}");
        // Saved and taken back.
        let state = splats.state_tensors();
        let mut back = splats.keeping(&(0..splats.layout().n).collect::<Vec<_>>()).unwrap();
        back.set_looks(None);
        back.restore_state(&mut |name| state.iter().find(|(k, _)| k == name).map(|(_, v)| v.clone()), 300).unwrap();
        assert_eq!(back.looks(), splats.looks());
        let f = &ds.frames[ds.test[0]];
        let o = held_out_options(&back, &f.camera);
        assert!(o.image.is_some());
        let (a, b) = (
            render_view_with(&back, &f.camera, ds.background, &o),
            render_view_with(&splats, &f.camera, ds.background, &o),
        );
        assert!(a.rgb == b.rgb);
    });
}

#[test]
fn baking_a_splats_model_or_cancelling_is_refused() {
    let _alone = alone();
    let ds = dataset();
    let config = ModelConfig::preset("instant-tiny").unwrap();
    // Trained enough that its rays hit the ball (an untrained field may
    // hit nothing, which is an error of its own).
    let mut t = common::tiny::trainer(&config, &ds, 3, 100);
    for _ in 0..100 {
        t.step();
    }
    let settings =
        BakeSettings { budget: Budget { seconds: None, steps: Some(2) }, initial: Some(2_000), ..Default::default() };
    let (splats, _, _) = bake(t.model.as_ref(), &ds, &settings, None, &AtomicBool::new(false), |_| {}).unwrap();
    let e = bake(&splats, &ds, &settings, None, &AtomicBool::new(false), |_| {}).err().expect("refused");
    assert!(e.to_string().contains("cannot be baked"), "{e}");
    let e = bake(t.model.as_ref(), &ds, &settings, None, &AtomicBool::new(true), |_| {}).err().expect("cancelled");
    assert!(e.to_string().contains("cancelled"), "{e}");
}

/// A bake given the transient maps its source was trained with fits
/// nothing where they say training dropped the pixels: one training photo
/// painted magenta all over (a transient that fills its frame), masked out
/// whole, bakes the same splats as the clean photos masked the same way,
/// where without the maps the splats turn magenta at its camera. Maps of
/// other photos are refused.
#[test]
fn the_bake_leaves_out_what_training_dropped() {
    use radiance::engine::transient::{SavedPhoto, TransientMaps};
    let _alone = alone();
    let clean = dataset();
    let mut painted = clean.clone();
    let k0 = 2;
    let f0 = painted.train[k0];
    for p in painted.frames[f0].image.rgba.chunks_exact_mut(4) {
        p[..3].copy_from_slice(&[255, 0, 255]);
    }
    let photos: Vec<SavedPhoto> = clean
        .train
        .iter()
        .map(|&f| SavedPhoto {
            name: clean.frames[f].name.clone(),
            width: clean.frames[f].camera.width,
            height: clean.frames[f].camera.height,
        })
        .collect();
    // Each 64x48 photo has 16x12 cells of 4 pixels (TransientMaps::new).
    let per = 16 * 12;
    let n = per * photos.len();
    let mut flags = vec![0u8; n];
    flags[k0 * per..(k0 + 1) * per].fill(1);
    let maps = TransientMaps::from_saved(&photos, &vec![0.0; n], &vec![0.0; n], &flags).unwrap();
    assert_eq!(maps.report().photos[k0].share, 1.0);
    in_pool(2, || {
        let config = ModelConfig::preset("instant-tiny").unwrap();
        let mut t = common::tiny::trainer(&config, &clean, 3, 400);
        for _ in 0..400 {
            t.step();
        }
        let settings = BakeSettings {
            budget: Budget { seconds: None, steps: Some(200) },
            initial: Some(10_000),
            ..Default::default()
        };
        let no = AtomicBool::new(false);
        let frame = &clean.frames[f0];
        let truth: Vec<f32> = (0..frame.image.height)
            .flat_map(|j| (0..frame.image.width).flat_map(move |i| frame.image.rgb_on(i, j, clean.background)))
            .collect();
        let baked = |ds: &Dataset, dropped: Option<&TransientMaps>| {
            bake(t.model.as_ref(), ds, &settings, dropped, &no, |_| {}).unwrap().0
        };
        let at_photo = |s: &radiance::engine::models::splats::SplatsModel| {
            psnr(&render_view(s, &frame.camera, clean.background).rgb, &truth)
        };
        // What the painted photo holds cannot matter where it is masked.
        let (masked, masked_clean) = (baked(&painted, Some(&maps)), baked(&clean, Some(&maps)));
        assert!(masked.params() == masked_clean.params(), "the masked pixels were fitted");
        let (from_clean, masked, unmasked) =
            (at_photo(&baked(&clean, None)), at_photo(&masked), at_photo(&baked(&painted, None)));
        // Measured: 21.35, 19.29 and 17.34 dB (masked, the photo's view is
        // a new view to the splats: 2 dB under the view they were fitted to).
        println!(
            "the painted photo's view against the clean photo: baked from the clean photos {from_clean:.2} dB, \
             the painted photo masked {masked:.2} dB, not masked {unmasked:.2} dB"
        );
        assert!(masked > unmasked + 1.5, "masked {masked:.2} dB, not masked {unmasked:.2} dB");
        let mut other = photos.clone();
        other[0].name = "elsewhere".into();
        let wrong = TransientMaps::from_saved(&other, &vec![0.0; n], &vec![0.0; n], &flags).unwrap();
        let e = bake(t.model.as_ref(), &painted, &settings, Some(&wrong), &no, |_| {}).err().expect("refused");
        assert!(e.to_string().contains("transient masks are of other photos"), "{e}");
    });
}

/// `radiance bake` then `radiance export --format ply`, read back by
/// `plyfile`: every property of every Gaussian equals what the export
/// module writes (the model's values in world units).
#[test]
fn the_exported_ply_reads_back_in_plyfile() {
    let _alone = alone();
    let dir = tempfile::tempdir().unwrap();
    let ds_dir = dir.path().join("scene");
    BallScene { size: 32, views: 12, ..Default::default() }.write_blender(&ds_dir).unwrap();
    let bin = env!("CARGO_BIN_EXE_radiance");
    let run = |args: &[&str]| {
        let out = Command::new(bin).args(args).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let [m, s, ply, splat] =
        ["m.ckpt", "s.ckpt", "s.ply", "s.splat"].map(|f| dir.path().join(f).to_string_lossy().into_owned());
    let data = ds_dir.to_string_lossy().into_owned();
    run(&["train", "--data", &data, "--model", "instant-tiny", "--steps", "200", "--out", &m, "--threads", "2"]);
    run(&["bake", "--model", &m, "--data", &data, "--out", &s, "--steps", "20", "--sh-degree", "2", "--threads", "2"]);
    run(&["export", "--model", &s, "--format", "ply", "--out", &ply]);
    run(&["export", "--model", &s, "--format", "splat", "--out", &splat]);
    // With steps alone, a bake follows no clock: baked again, the same
    // Gaussians to the bit.
    let (s2, splat2) = (format!("{s}.again"), format!("{splat}.again"));
    run(&["bake", "--model", &m, "--data", &data, "--out", &s2, "--steps", "20", "--sh-degree", "2", "--threads", "2"]);
    run(&["export", "--model", &s2, "--format", "splat", "--out", &splat2]);
    assert_eq!(std::fs::read(&splat).unwrap(), std::fs::read(&splat2).unwrap(), "a bake of 20 steps is reproducible");
    // A model that is not splats is refused, naming the command to use.
    let out = Command::new(bin).args(["export", "--model", &m, "--format", "ply", "--out", &ply]).output().unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("radiance bake"));

    let restored = radiance::engine::train::persist::load(std::path::Path::new(&s)).unwrap();
    let model = export::splats_of(&*restored.model).expect("splats");
    // Export cleans floaters first (by default).
    let (cleaned, _) = radiance::engine::models::splats::cleanup::cleanup(model, &Default::default()).unwrap();
    let model = &cleaned;
    let mut mine = Vec::new();
    export::write(model, Format::Ply, &mut mine).unwrap();
    assert_eq!(std::fs::read(&ply).unwrap(), mine, "the CLI writes what the module writes");
    let n = model.layout().n;
    assert_eq!(std::fs::metadata(&splat).unwrap().len(), 32 * n as u64);

    // The independent reader: property names in order, and every value.
    let script = r#"
import sys, json
from plyfile import PlyData
d = PlyData.read(sys.argv[1])
v = d['vertex']
print(json.dumps({'names': [p.name for p in v.properties], 'rows': [[float(x) for x in r] for r in v.data]}))
"#;
    let out = Command::new("python3").args(["-c", script, &ply]).output().expect("python3");
    assert!(out.status.success(), "plyfile (pip install plyfile): {}", String::from_utf8_lossy(&out.stderr));
    let read: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let names: Vec<&str> = read["names"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
    let mut want = vec!["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        .into_iter()
        .map(String::from)
        .collect::<Vec<_>>();
    want.extend((0..24).map(|i| format!("f_rest_{i}")));
    want.push("opacity".into());
    want.extend((0..3).map(|i| format!("scale_{i}")));
    want.extend((0..4).map(|i| format!("rot_{i}")));
    assert_eq!(names, want);
    let rows = read["rows"].as_array().unwrap();
    assert_eq!(rows.len(), n);
    let scene = model.scene();
    let l = model.layout();
    for (i, row) in rows.iter().enumerate() {
        let r: Vec<f32> = row.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
        let g = l.get(model.params(), i);
        for c in 0..3 {
            assert_eq!(r[c], g.mean[c] * (1.0 / scene.scale) + scene.centre[c], "x y z");
            assert_eq!(r[3 + c], 0.0, "normals");
            assert_eq!(r[6 + c], g.sh_dc[c], "f_dc");
            for j in 1..9 {
                assert_eq!(r[9 + 8 * c + (j - 1)], g.sh_rest[3 * (j - 1) + c], "f_rest of channel {c}");
            }
            assert_eq!(r[34 + c], g.log_scale[c] - scene.scale.ln(), "scale");
        }
        assert_eq!(r[33], g.opacity_logit, "opacity");
        assert_eq!(&r[37..41], &g.rotation, "rot");
    }
}

/// `radiance train --model splats`: a field (auto's choice) trained for a
/// third of `--seconds` and kept beside the output, then splats fitted for
/// the rest; they render held-out views nearly as well as their field (the
/// demo object, 30 s on 2 threads, this test's build, 2-core EPYC: field
/// 35.44 and 36.30 dB in two runs, splats 35.20 and 35.06; CI's run of
/// bc6c19e: 35.93 and 35.03; a 2-core Xeon with AVX-512 at 42c41bf: 37.42
/// and 35.33). The field gains with the machine's speed and the splats stay
/// near 35 dB, so the bars are 32 dB and the field's score less 2 dB, the
/// field's counted at most 36 dB (a faster machine's field is no reason for
/// the splats to fall short), which an unfitted placement (about 18 dB) or
/// a broken fit does not reach. It trains by time only, and is not resumed.
#[test]
fn train_model_splats_fits_splats_from_a_field_it_trains_first() {
    let _alone = alone();
    let dir = tempfile::tempdir().unwrap();
    let ds_dir = dir.path().join("scene");
    BallScene::demo().write_blender(&ds_dir).unwrap();
    let data = ds_dir.to_string_lossy().into_owned();
    let bin = env!("CARGO_BIN_EXE_radiance");
    let run = |args: &[&str]| Command::new(bin).args(args).args(["--threads", "2"]).output().unwrap();
    let out = dir.path().join("s.ckpt");
    let o = run(&["train", "--data", &data, "--model", "splats", "--seconds", "30", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let field = dir.path().join("s.field.ckpt");
    let (splats, source) = (
        radiance::engine::train::persist::load(&out).unwrap(),
        radiance::engine::train::persist::load(&field).unwrap(),
    );
    assert_eq!((splats.model.kind(), source.model.kind()), ("splats", "instant"));
    // The field stops at its first step or checkpoint past 10 s (on a
    // starved machine one can come seconds late, still well short of
    // half), unless it had not made its fewest steps by then: then at
    // those steps.
    let (elapsed, steps, least) = (source.state.elapsed, source.state.step, SPLATS_FIELD_MIN_STEPS);
    let timed = (9.9..14.0).contains(&elapsed) && steps >= least;
    assert!(
        timed || (elapsed >= 9.9 && steps == least),
        "a third of 30 s, or {least} steps: {elapsed} s, {steps} steps"
    );
    let eval = |m: &std::path::Path| {
        let o = run(&["eval", "--model", m.to_str().unwrap(), "--data", &data, "--fit-steps", "0"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let text = String::from_utf8_lossy(&o.stdout).into_owned();
        let last = text.lines().rev().find(|l| l.contains(" views ")).unwrap().to_string();
        last.split("PSNR").nth(1).unwrap().split_whitespace().next().unwrap().parse::<f64>().unwrap()
    };
    let (psnr_splats, psnr_field) = (eval(&out), eval(&field));
    println!("train --model splats --seconds 30: field {psnr_field:.2} dB, splats {psnr_splats:.2} dB");
    assert!(
        psnr_splats > 32.0 && psnr_splats > psnr_field.min(36.0) - 2.0,
        "splats {psnr_splats:.2} dB, field {psnr_field:.2} dB"
    );

    for (args, says) in [
        (vec!["--steps", "10"], "--seconds"),
        (vec!["--seconds", "5", "--resume", out.to_str().unwrap()], "not resumed"),
    ] {
        let o = run(&[&["train", "--data", &data, "--model", "splats", "--out", "x.ckpt"][..], &args[..]].concat());
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(says), "{args:?}: {err}");
    }
}
