//! Unit tests of `appearance.rs`: parsing, the error's list of images, and
//! resolving each choice against a capture model (trained images only,
//! the nearest training camera) and a model without appearance.

use super::*;
use crate::engine::dataset::Dataset;
use crate::engine::dataset::textured::TexturedScene;
use crate::engine::models::config::ModelConfig;

/// The textured scene's 8 views with every 4th (0 and 4) held out.
fn dataset() -> Dataset {
    let mut ds = TexturedScene { width: 8, height: 6, views: 8, fov: 0.9 }.dataset();
    ds.train = vec![1, 2, 3, 5, 6, 7];
    ds.test = vec![0, 4];
    ds
}

/// A `capture-tiny` model of `ds` that has trained on `seen`.
fn capture(ds: &Dataset, seen: &[u32]) -> Box<dyn Model> {
    let mut m = ModelConfig::preset("capture-tiny").unwrap().build(ds.scene(), 1).unwrap();
    let mut flags = vec![0.0; 2000];
    for &i in seen {
        flags[i as usize] = 1.0;
    }
    m.restore_state(&mut |_| Some(flags.clone()), 10).unwrap();
    m
}

#[test]
fn choices_parse_and_print_back() {
    for (text, want) in [("mean", Appearance::Mean), ("nearest", Appearance::Nearest), ("17", Appearance::Image(17))] {
        assert_eq!(text.parse::<Appearance>(), Ok(want));
        assert_eq!(want.to_string(), text);
        let json = serde_json::to_value(want).unwrap();
        assert_eq!(json, serde_json::json!(text));
        assert_eq!(serde_json::from_value::<Appearance>(json).unwrap(), want);
    }
    assert_eq!("4294967295".parse::<Appearance>(), Ok(Appearance::Image(u32::MAX)));
    for bad in ["", "Mean", "-1", "1.5", "4294967296", " 3", "near"] {
        let e = bad.parse::<Appearance>().unwrap_err();
        assert!(e.contains(&format!("'{bad}'")), "{e}");
    }
    assert!(serde_json::from_value::<Appearance>(serde_json::json!("x")).is_err());
}

#[test]
fn index_ranges_join_runs() {
    assert_eq!(index_ranges(&[0, 1, 2, 4, 6, 7]), "0-2, 4, 6-7");
    assert_eq!(index_ranges(&[5]), "5");
    assert_eq!(index_ranges(&[]), "none");
    assert_eq!(index_ranges(&[u32::MAX - 1, u32::MAX]), format!("{}-{}", u32::MAX - 1, u32::MAX));
}

/// An index must be an image trained on; the error names those that were.
#[test]
fn an_image_must_have_been_trained_on() {
    let ds = dataset();
    let m = capture(&ds, &[1, 2, 3, 5, 6, 7]);
    let cam = &ds.frames[0].camera;
    assert_eq!(Appearance::Image(5).resolve(&*m, cam), Ok(RenderOptions { image: Some(5) }));
    assert_eq!(Appearance::Mean.resolve(&*m, cam), Ok(RenderOptions::default()));
    for image in [0, 4, 8, 99_999] {
        let e = Appearance::Image(image).resolve(&*m, cam).unwrap_err();
        assert_eq!(e, AppearanceError::NotTrained { image, valid: "1-3, 5-7".into() });
        assert!(e.to_string().contains("training images: 1-3, 5-7"), "{e}");
        assert_eq!(Appearance::Image(image).check(&*m), Err(e));
    }
    assert_eq!(Appearance::Image(5).check(&*m), Ok(()));
    // Before any training no image has an appearance of its own.
    let fresh = capture(&ds, &[]);
    let e = Appearance::Image(1).resolve(&*fresh, cam).unwrap_err();
    assert!(e.to_string().contains("training images: none"), "{e}");
}

/// `nearest` picks the training camera minimising `|c - c_i| / r + 1 - a . a_i`
/// (computed here independently, in f64, from the dataset's cameras).
#[test]
fn nearest_picks_the_closest_training_camera() {
    let ds = dataset();
    let m = capture(&ds, &[1, 2, 3, 5, 6, 7]);
    let radius = m.scene().rig.as_ref().unwrap().radius as f64;
    let pose = |c: &Camera| {
        let m = &c.c2w;
        ([m[0][3] as f64, m[1][3] as f64, m[2][3] as f64], [-m[0][2] as f64, -m[1][2] as f64, -m[2][2] as f64])
    };
    let by_hand = |cam: &Camera, allowed: &[u32]| {
        let (c, a) = pose(cam);
        let cost = |i: u32| {
            let (ci, ai) = pose(&ds.frames[i as usize].camera);
            let d = ((c[0] - ci[0]).powi(2) + (c[1] - ci[1]).powi(2) + (c[2] - ci[2]).powi(2)).sqrt();
            d / radius + 1.0 - (a[0] * ai[0] + a[1] * ai[1] + a[2] * ai[2])
        };
        allowed.iter().copied().min_by(|&x, &y| cost(x).total_cmp(&cost(y))).unwrap()
    };
    for f in &ds.frames {
        let got = Appearance::Nearest.resolve(&*m, &f.camera).unwrap().image.unwrap();
        assert_eq!(got, by_hand(&f.camera, &[1, 2, 3, 5, 6, 7]), "{}", f.name);
        assert_eq!(held_out_options(&*m, &f.camera), RenderOptions { image: Some(got) });
    }
    // A training camera is its own nearest; a held-out one on the ring a neighbour.
    assert_eq!(Appearance::Nearest.resolve(&*m, &ds.frames[6].camera).unwrap().image, Some(6));
    let n0 = Appearance::Nearest.resolve(&*m, &ds.frames[0].camera).unwrap().image.unwrap();
    assert!(n0 == 1 || n0 == 7, "{n0}");
    // Only images trained on are candidates; none trained on: the mean.
    let some = capture(&ds, &[2, 3]);
    let got = Appearance::Nearest.resolve(&*some, &ds.frames[0].camera).unwrap().image.unwrap();
    assert_eq!(got, by_hand(&ds.frames[0].camera, &[2, 3]));
    let fresh = capture(&ds, &[]);
    assert_eq!(Appearance::Nearest.resolve(&*fresh, &ds.frames[0].camera), Ok(RenderOptions::default()));
}

/// A model whose checkpoint kept no training cameras cannot pick the
/// nearest: an error for a user's choice, the mean for held-out scores.
#[test]
fn nearest_needs_the_training_cameras() {
    let ds = dataset();
    let mut scene = ds.scene();
    scene.rig.as_mut().unwrap().frames.clear();
    let mut m = ModelConfig::preset("capture-tiny").unwrap().build(scene, 1).unwrap();
    m.restore_state(&mut |_| Some(vec![1.0; 2000]), 1).unwrap();
    let cam = &ds.frames[0].camera;
    assert_eq!(Appearance::Nearest.resolve(&*m, cam), Err(AppearanceError::NoCameras));
    assert_eq!(Appearance::Nearest.check(&*m), Err(AppearanceError::NoCameras));
    assert!(AppearanceError::NoCameras.to_string().contains("'mean'"));
    assert_eq!(held_out_options(&*m, cam), RenderOptions::default());
}

/// Models without per-image appearance take every choice and ignore it.
#[test]
fn other_models_ignore_the_choice() {
    let ds = dataset();
    for preset in ["instant-tiny", "nerf-tiny"] {
        let m = ModelConfig::preset(preset).unwrap().build(ds.scene(), 1).unwrap();
        assert_eq!(m.appearance().map(|a| a.images()), None);
        for a in [Appearance::Mean, Appearance::Image(99_999), Appearance::Nearest] {
            assert_eq!(a.resolve(&*m, &ds.frames[0].camera), Ok(RenderOptions::default()), "{preset} {a}");
            assert_eq!(a.check(&*m), Ok(()));
        }
    }
}
