use super::super::synthetic::BallScene;
use super::super::testutil::write_mask;
use super::super::{LoadOptions, Split};
use super::*;

const SIZE: u32 = 16;

fn ball() -> BallScene {
    BallScene { size: SIZE, views: 8, ..Default::default() }
}

/// The ball as an LLFF dataset with its photos in `images_8/` (12 frames,
/// `img000` ... `img011`), no masks yet.
fn llff(root: &Path) {
    ball().write_llff(root).unwrap();
    std::fs::rename(root.join("images"), root.join("images_8")).unwrap();
}

/// Frame `k`'s test mask: columns left of `3 + k` inside (255), the rest
/// outside, so each frame's mask is told apart by its width.
fn stripe(k: usize) -> impl Fn(u32, u32) -> u8 {
    move |x, _| if (x as usize) < 3 + k { 255 } else { 0 }
}

fn write_masks(root: &Path, folder: &str, frames: usize) {
    for k in 0..frames {
        write_mask(&root.join(folder).join(format!("img{k:03}.png")), SIZE, SIZE, stripe(k));
    }
}

fn load(root: &Path, masks: MaskUse) -> Result<Dataset, DatasetError> {
    Dataset::load(root, &LoadOptions { masks, ..Default::default() })
}

#[test]
fn candidate_folders_follow_the_image_folder() {
    let r = Path::new("/d");
    assert_eq!(candidates(&r.join("images_8")), [r.join("masks_8"), r.join("masks")]);
    assert_eq!(candidates(&r.join("images_16")), [r.join("masks_16"), r.join("masks")]);
    assert_eq!(candidates(&r.join("images")), [r.join("masks")]);
    for other in ["images_", "images_x", "imagesx", "train", "photos_8"] {
        assert!(candidates(&r.join(other)).is_empty(), "{other}");
    }
}

#[test]
fn masks_match_images_by_stem_across_extensions() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    write_masks(root, "masks_8", 12);
    // Other extensions (any case) match by stem; JPEG masks are constant so
    // that compression keeps their value.
    std::fs::remove_file(root.join("masks_8/img004.png")).unwrap();
    write_mask(&root.join("masks_8/img004.JPG"), SIZE, SIZE, |_, _| 200);
    std::fs::remove_file(root.join("masks_8/img007.png")).unwrap();
    write_mask(&root.join("masks_8/img007.jpeg"), SIZE, SIZE, |_, _| 60);
    // Files that are not images, and masks of no image, are ignored; a
    // less preferred folder too.
    std::fs::write(root.join("masks_8/notes.txt"), "x").unwrap();
    write_mask(&root.join("masks_8/other.png"), 3, 3, |_, _| 0);
    write_mask(&root.join("masks/img000.png"), 5, 5, |_, _| 0);

    let ds = load(root, MaskUse::Score).unwrap();
    assert_eq!((ds.masks, ds.mask_folder.clone()), (MaskUse::Score, Some(root.join("masks_8"))));
    for (k, f) in ds.frames.iter().enumerate() {
        let m = f.mask.as_ref().unwrap();
        assert_eq!(m.len(), (SIZE * SIZE) as usize);
        match k {
            4 => assert!(m.iter().all(|&v| v.abs_diff(200) <= 2), "{k}: {m:?}"),
            7 => assert!(m.iter().all(|&v| v.abs_diff(60) <= 2), "{k}: {m:?}"),
            _ => {
                let want: Vec<u8> = (0..SIZE * SIZE).map(|p| stripe(k)(p % SIZE, p / SIZE)).collect();
                assert_eq!(m, &want, "frame {k}");
            }
        }
        // Scoring leaves the photos as they are.
        assert!(!f.image.has_alpha && f.image.rgba.chunks(4).all(|p| p[3] == 255));
    }

    // Without masks_8/, masks/ beside images_8/ is used.
    std::fs::remove_dir_all(root.join("masks_8")).unwrap();
    write_masks(root, "masks", 12);
    let ds = load(root, MaskUse::Score).unwrap();
    assert_eq!(ds.mask_folder, Some(root.join("masks")));
    assert_eq!(ds.frames[5].mask.as_ref().unwrap()[7], 255);
    assert_eq!(ds.frames[5].mask.as_ref().unwrap()[8], 0);
}

#[test]
fn a_mask_of_another_size_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    write_masks(root, "masks_8", 12);
    let bad = root.join("masks_8/img009.png");
    write_mask(&bad, SIZE, SIZE + 2, |_, _| 255);
    for masks in [MaskUse::Auto, MaskUse::Score, MaskUse::Ignore, MaskUse::Composite] {
        match load(root, masks) {
            Err(e @ DatasetError::SizeMismatch { .. }) => {
                let DatasetError::SizeMismatch { path, got_w, got_h, want_w, want_h } = &e else { unreachable!() };
                assert_eq!((path, *got_w, *got_h, *want_w, *want_h), (&bad, SIZE, SIZE + 2, SIZE, SIZE));
                assert!(e.to_string().contains("img009.png"), "{e}");
            }
            other => panic!("{masks}: {other:?}"),
        }
    }
    // `off` does not read the folder.
    let ds = load(root, MaskUse::Off).unwrap();
    assert!(ds.frames.iter().all(|f| f.mask.is_none()) && ds.masks == MaskUse::Off && ds.mask_folder.is_none());
}

#[test]
fn missing_masks_are_an_error_naming_the_first() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    write_masks(root, "masks_8", 12);
    std::fs::remove_file(root.join("masks_8/img003.png")).unwrap();
    std::fs::remove_file(root.join("masks_8/img010.png")).unwrap();
    match load(root, MaskUse::Auto) {
        Err(e @ DatasetError::MissingMask { .. }) => {
            let msg = e.to_string();
            let DatasetError::MissingMask { image, looked_in, missing, total } = e else { unreachable!() };
            assert_eq!((image, missing, total), (root.join("images_8/img003.png"), 2, 12));
            assert_eq!(looked_in, root.join("masks_8").display().to_string());
            assert!(msg.contains("img003.png") && msg.contains("2 of 12") && msg.contains("--masks off"), "{msg}");
        }
        other => panic!("{other:?}"),
    }
    assert!(load(root, MaskUse::Off).is_ok());

    // Two masks for one image are refused, naming both.
    write_masks(root, "masks_8", 12);
    write_mask(&root.join("masks_8/img002.jpg"), SIZE, SIZE, |_, _| 255);
    match load(root, MaskUse::Score) {
        Err(DatasetError::Invalid { path, message }) => {
            assert_eq!(path, root.join("masks_8"));
            assert!(message.contains("img002.png") && message.contains("img002.jpg"), "{message}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn composite_makes_the_frames_transparent_and_score_does_not() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    // Soft edges: a ramp across the image.
    for k in 0..12 {
        write_mask(&root.join(format!("masks_8/img{k:03}.png")), SIZE, SIZE, |x, _| (x * 17) as u8);
    }
    let plain = load(root, MaskUse::Off).unwrap();
    let ds = load(root, MaskUse::Composite).unwrap();
    assert_eq!(ds.masks, MaskUse::Composite);
    for (f, p) in ds.frames.iter().zip(&plain.frames) {
        let m = f.mask.as_ref().unwrap();
        assert!(f.image.has_alpha);
        for (k, (px, q)) in f.image.rgba.chunks(4).zip(p.image.rgba.chunks(4)).enumerate() {
            // Alpha is the mask, colour untouched.
            assert_eq!((px[3], m[k], &px[..3]), ((k as u32 % SIZE * 17) as u8, px[3], &q[..3]), "pixel {k}");
        }
        // On white, a pixel half inside is half the photo, half white.
        let c = f.image.rgb_on(8, 3, [1.0; 3]);
        let a = 8.0 * 17.0 / 255.0;
        let want = p.image.rgb_on(8, 3, [1.0; 3]).map(|v| v * a + (1.0 - a));
        assert!(c.iter().zip(want).all(|(x, y)| (x - y).abs() < 1e-6), "{c:?} {want:?}");
    }
    assert!(ds.scene().transparent);

    let ds = load(root, MaskUse::Score).unwrap();
    assert!(ds.frames.iter().all(|f| !f.image.has_alpha && f.mask.is_some()));
    assert!(!ds.scene().transparent);
    // Auto: the folder scores, and a warning says how to train with it.
    let auto = load(root, MaskUse::Auto).unwrap();
    assert_eq!(auto.masks, MaskUse::Score);
    let w = auto.warnings.iter().find(|w| w.starts_with("masks_8/")).expect("a warning about the masks");
    assert!(w.contains("--masks ignore") && w.contains("--masks composite"), "{w}");
    assert!(!plain.warnings.iter().any(|w| w.contains("masks")) && plain.masks == MaskUse::Off);
}

#[test]
fn a_mask_multiplies_into_an_alpha_channel() {
    let mut image = Image { width: 2, height: 1, rgba: vec![1, 2, 3, 255, 4, 5, 6, 128], has_alpha: true };
    composite(&mut image, &[128, 255]);
    assert_eq!(image.rgba, [1, 2, 3, 128, 4, 5, 6, 128]);
    composite(&mut image, &[0, 64]);
    assert_eq!(image.rgba, [1, 2, 3, 0, 4, 5, 6, 32]);
}

#[test]
fn the_alpha_channel_is_the_mask_when_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    ball().write_blender(root).unwrap();
    // A Blender scene never looks for a mask folder.
    write_masks(root, "masks", 12);
    let auto = load(root, MaskUse::Auto).unwrap();
    assert!(auto.masks == MaskUse::Off && auto.frames.iter().all(|f| f.mask.is_none()));
    assert!(auto.scene().transparent, "RGBA images composite as always");
    for masks in [MaskUse::Score, MaskUse::Ignore, MaskUse::Composite] {
        let ds = load(root, masks).unwrap();
        assert_eq!((ds.masks, ds.mask_folder.clone()), (masks, None));
        for f in &ds.frames {
            let alpha: Vec<u8> = f.image.rgba.chunks(4).map(|p| p[3]).collect();
            assert_eq!(f.mask.as_ref(), Some(&alpha));
        }
        assert_eq!(ds.frames[0].image, auto.frames[0].image);
    }

    // Opaque photos and no mask folder: asking for masks is an error.
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    assert_eq!(load(root, MaskUse::Auto).unwrap().masks, MaskUse::Off);
    match load(root, MaskUse::Ignore) {
        Err(DatasetError::Invalid { path, message }) => {
            assert_eq!(path, root);
            assert!(message.contains("masks_8/ or masks/") && message.contains("'ignore'"), "{message}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn colmap_and_ngp_find_masks_beside_images() {
    let dir = tempfile::tempdir().unwrap();
    let colmap = dir.path().join("colmap");
    ball().write_colmap(&colmap, true).unwrap();
    write_masks(&colmap, "masks", 12);
    let ds = load(&colmap, MaskUse::Auto).unwrap();
    assert_eq!(
        (ds.format, ds.masks, ds.mask_folder.clone()),
        (DatasetFormat::Colmap, MaskUse::Score, Some(colmap.join("masks")))
    );
    assert_eq!(ds.frames[2].mask.as_ref().unwrap()[4], 255);
    assert_eq!(ds.frames[2].mask.as_ref().unwrap()[5], 0);

    let ngp = dir.path().join("ngp");
    ball().write_ngp(&ngp).unwrap();
    // Its images are named r_0 ... r_11.
    for k in 0..12 {
        write_mask(&ngp.join(format!("masks/r_{k}.png")), SIZE, SIZE, stripe(k));
    }
    let ds = load(&ngp, MaskUse::Ignore).unwrap();
    assert_eq!((ds.format, ds.masks), (DatasetFormat::Ngp, MaskUse::Ignore));
    assert_eq!(ds.frames[11].mask.as_ref().unwrap()[13], 255);
    assert_eq!(ds.frames[11].mask.as_ref().unwrap()[14], 0);
}

#[test]
fn ignore_needs_a_training_pixel_inside() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    llff(root);
    write_masks(root, "masks_8", 12);
    // Frame 8 is held out; empty the masks of training frames 1 and 2.
    for k in [1, 2, 8] {
        write_mask(&root.join(format!("masks_8/img{k:03}.png")), SIZE, SIZE, |_, _| INSIDE - 1);
    }
    let ds = load(root, MaskUse::Ignore).unwrap();
    assert!(
        ds.warnings.iter().any(|w| w.contains("2 training images with an empty mask (img001, img002)")),
        "{:?}",
        ds.warnings
    );
    for k in ds.split(Split::Train).to_vec() {
        write_mask(&root.join(format!("masks_8/img{k:03}.png")), SIZE, SIZE, |_, _| 0);
    }
    match load(root, MaskUse::Ignore) {
        Err(DatasetError::Invalid { path, message }) => {
            assert_eq!(path, root.join("masks_8"));
            assert!(message.contains("nothing to train on"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    // Scoring with empty masks is allowed.
    assert!(load(root, MaskUse::Score).is_ok());
}

#[test]
fn mask_use_names_round_trip() {
    for m in MaskUse::ALL {
        assert_eq!(m.name().parse::<MaskUse>(), Ok(m));
        assert_eq!(serde_json::to_value(m).unwrap(), serde_json::json!(m.name()));
    }
    assert!("Ignore".parse::<MaskUse>().unwrap_err().contains("auto, score, ignore, composite or off"));
    assert_eq!(inside(&[0, 127, 128, 255]), [false, false, true, true]);
}
