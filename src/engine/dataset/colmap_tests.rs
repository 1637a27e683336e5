//! Unit tests of `colmap.rs` and `colmap_model.rs`: models written by the
//! test itself from the generated ball scene, in both formats.

use super::super::colmap_model::{Model, write};
use super::*;
use crate::engine::dataset::synthetic::{BallScene, colmap_pose};

/// The ball scene as a COLMAP model (one PINHOLE camera) with its images
/// written to `root/images`, sparse points on the ball and three strays.
fn ball_model(root: &Path) -> (Dataset, Model) {
    let ds = BallScene { size: 16, views: 10, ..Default::default() }.dataset();
    let c0 = &ds.frames[0].camera;
    let camera = CameraModel {
        id: 7,
        model: "PINHOLE",
        width: c0.width as u64,
        height: c0.height as u64,
        params: vec![c0.fx as f64, c0.fy as f64, c0.cx as f64, c0.cy as f64],
    };
    let mut images = Vec::new();
    for (k, f) in ds.frames.iter().enumerate() {
        let (qvec, tvec) = colmap_pose(&f.camera.c2w);
        let name = format!("img_{k:02}.png");
        let img = image::RgbaImage::from_raw(f.image.width, f.image.height, f.image.rgba.clone()).unwrap();
        std::fs::create_dir_all(root.join("images")).unwrap();
        img.save(root.join("images").join(&name)).unwrap();
        // COLMAP numbers images in its own order.
        images.push(ImagePose { id: 100 - k as u32, qvec, tvec, camera_id: 7, name });
    }
    images.reverse();
    let mut points: Vec<[f64; 3]> = (0..200)
        .map(|i| [0.5 * (i as f64 * 0.1).cos(), 0.5 * (i as f64 * 0.1).sin(), (i % 9) as f64 * 0.1 - 0.4])
        .collect();
    points.extend([[1000.0, 0.0, 0.0], [0.0, -900.0, 0.0], [0.0, 0.0, 5e6]]);
    (ds, Model { cameras: vec![camera], images, points })
}

fn load_dir(root: &Path) -> Result<Dataset, DatasetError> {
    Dataset::load(root, &LoadOptions::default())
}

#[test]
fn binary_and_text_models_load_to_the_cameras_they_were_made_from() {
    let tmp = tempfile::tempdir().unwrap();
    let (bin, txt) = (tmp.path().join("bin"), tmp.path().join("txt"));
    let (truth, model) = ball_model(&bin);
    ball_model(&txt);
    write(&model, &bin.join("sparse/0"), true).unwrap();
    write(&model, &txt.join("sparse/0"), false).unwrap();
    assert_eq!(colmap_model::read(&bin.join("sparse/0")).unwrap(), model);
    assert_eq!(colmap_model::read(&txt.join("sparse/0")).unwrap(), model);
    let (b, t) = (load_dir(&bin).unwrap(), load_dir(&txt).unwrap());
    assert_eq!((b.format, t.format), (DatasetFormat::Colmap, DatasetFormat::Colmap));
    assert_eq!(b.frames.len(), truth.frames.len());
    for ((fb, ft), want) in b.frames.iter().zip(&t.frames).zip(&truth.frames) {
        assert_eq!(fb.camera, ft.camera, "binary and text differ");
        let (g, w) = (&fb.camera, &want.camera);
        assert_eq!((g.width, g.height, g.fx, g.fy, g.cx, g.cy), (w.width, w.height, w.fx, w.fy, w.cx, w.cy));
        for r in 0..3 {
            for c in 0..4 {
                assert!((g.c2w[r][c] - w.c2w[r][c]).abs() < 1e-5, "{}: {:?} vs {:?}", fb.name, g.c2w, w.c2w);
            }
        }
        assert_eq!(fb.image, want.image);
    }
    // Every 8th image in name order is held out.
    assert_eq!(b.test, vec![0, 8]);
    assert_eq!(b.train.len() + b.test.len(), 14);
    // The box holds the cameras and the ball, not the stray points.
    let bx = b.aabb;
    for f in &b.frames {
        let o = f.camera.origin();
        assert!(o.x >= bx.min.x && o.y >= bx.min.y && o.z >= bx.min.z && o.x <= bx.max.x && o.z <= bx.max.z);
    }
    assert!(bx.max.x < 10.0 && bx.min.y > -10.0 && bx.max.z < 10.0, "{bx:?}");
}

#[test]
fn unregistered_photos_are_left_out_with_a_warning_and_missing_ones_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (_, model) = ball_model(root);
    write(&model, &root.join("sparse/0"), true).unwrap();
    std::fs::copy(root.join("images/img_00.png"), root.join("images/extra.png")).unwrap();
    let ds = load_dir(root).unwrap();
    assert_eq!(ds.frames.len(), 14);
    assert!(
        ds.warnings.iter().any(|w| w.contains("registered 14 of 15") && w.contains("extra.png")),
        "{:?}",
        ds.warnings
    );
    std::fs::remove_file(root.join("images/img_03.png")).unwrap();
    let e = load_dir(root).unwrap_err().to_string();
    assert!(e.contains("1 registered images are missing: img_03.png"), "{e}");
}

#[test]
fn unsupported_and_unknown_camera_models_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (_, mut model) = ball_model(root);
    model.cameras[0].model = "OPENCV_FISHEYE";
    model.cameras[0].params = vec![20.0, 20.0, 8.0, 8.0, 0.1, 0.0, 0.0, 0.0];
    write(&model, &root.join("sparse/0"), false).unwrap();
    let e = load_dir(root).unwrap_err().to_string();
    assert!(e.contains("OPENCV_FISHEYE is not supported"), "{e}");
    let cams = root.join("sparse/0/cameras.txt");
    std::fs::write(&cams, "7 PANORAMA 16 16 1 2 3\n").unwrap();
    assert!(load_dir(root).unwrap_err().to_string().contains("unknown camera model 'PANORAMA'"));
    std::fs::write(&cams, "7 PINHOLE 16 16 1 2 3\n").unwrap();
    let e = load_dir(root).unwrap_err().to_string();
    assert!(e.contains("PINHOLE has 4 parameters, found 3"), "{e}");
    // An image of a camera the model lacks.
    std::fs::write(&cams, "8 PINHOLE 16 16 20 20 8 8\n").unwrap();
    assert!(load_dir(root).unwrap_err().to_string().contains("uses camera 7, which the model lacks"));
}

#[test]
fn corrupt_binary_models_are_errors_at_every_length_and_count() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("sparse/0");
    let (_, model) = ball_model(tmp.path());
    write(&model, &dir, true).unwrap();
    for name in ["cameras.bin", "images.bin", "points3D.bin"] {
        let p = dir.join(name);
        let full = std::fs::read(&p).unwrap();
        // Every truncation is an error naming the file (never a panic).
        for len in (0..full.len()).step_by(7).chain([full.len() - 1]) {
            std::fs::write(&p, &full[..len]).unwrap();
            let e = colmap_model::read(&dir).unwrap_err().to_string();
            assert!(e.contains(name), "{name} cut at {len}: {e}");
        }
        // An absurd count is refused before anything is allocated.
        let mut absurd = full.clone();
        absurd[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        std::fs::write(&p, &absurd).unwrap();
        let e = colmap_model::read(&dir).unwrap_err().to_string();
        assert!(e.contains("but only"), "{name}: {e}");
        // Trailing bytes are an error too.
        let mut long = full.clone();
        long.push(0);
        std::fs::write(&p, &long).unwrap();
        assert!(colmap_model::read(&dir).unwrap_err().to_string().contains("after the last record"));
        std::fs::write(&p, &full).unwrap();
    }
    // An unknown model id.
    let p = dir.join("cameras.bin");
    let mut bad = std::fs::read(&p).unwrap();
    bad[12..16].copy_from_slice(&99i32.to_le_bytes());
    std::fs::write(&p, &bad).unwrap();
    assert!(colmap_model::read(&dir).unwrap_err().to_string().contains("unknown camera model id 99"));
}

/// The near bound is 0.9 times the nearest depth at which a camera sees
/// the sparse points: the ball's points lie within 0.65 of the centre, the
/// nearest camera 3.13 from it, and each camera sees the ring of radius 0.5
/// up to its nearest side. One stray point just in front of a camera is
/// passed over; a model without points has no near bound (0, as before).
#[test]
fn the_near_bound_is_llffs_from_the_sparse_points_each_camera_sees() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (truth, mut model) = ball_model(root);
    let near_cam = truth.frames.iter().map(|f| f.camera.origin().norm()).fold(f32::INFINITY, f32::min);
    assert!((near_cam - 3.13).abs() < 0.01, "{near_cam}");
    write(&model, &root.join("sparse/0"), true).unwrap();
    let near = load_dir(root).unwrap().near;
    assert!(near > 0.9 * (near_cam - 0.65) && near < 0.9 * (near_cam - 0.45), "near {near}");

    // A stray 0.2 in front of the first camera.
    let c = &truth.frames[0].camera;
    let stray = c.origin() + c.rotate(Vec3::new(0.0, 0.0, -1.0)) * 0.2;
    model.points.push([stray.x, stray.y, stray.z].map(f64::from));
    write(&model, &root.join("sparse/0"), true).unwrap();
    let with_stray = load_dir(root).unwrap().near;
    assert!(with_stray > 0.9 * (near_cam - 0.65) && with_stray <= near, "near {with_stray}");

    model.points.clear();
    write(&model, &root.join("sparse/0"), true).unwrap();
    assert_eq!(load_dir(root).unwrap().near, 0.0);
}

/// `near_bound` against one camera at the origin looking down -z whose
/// principal point is on the image's top edge, so only points below its
/// axis are in the image: points above it, outside the sides, behind the
/// camera or not finite are passed over, whatever their depth; of the 101
/// points in view (depths 2.00 to 3.00) the 1st percentile's depth is 2.01.
#[test]
fn the_near_bound_counts_only_points_in_a_cameras_image() {
    let identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
    let camera = Camera { cy: 0.0, ..Camera::from_fov(16, 16, 0.9, identity) };
    let mut points: Vec<[f64; 3]> = (0..=100).map(|i| [0.0, -0.1, -(2.0 + 0.01 * i as f64)]).collect();
    let decoys = [[0.0, 0.1, -0.5], [5.0, -0.1, -0.5], [0.0, -0.1, 0.5], [f64::NAN, 0.0, -0.5], [0.0, -5.0, -0.5]];
    for with_decoys in [false, true] {
        let mut all = points.clone();
        if with_decoys {
            all.extend(decoys);
        }
        let near = near_bound([&camera], &all).unwrap();
        assert!((near - 0.9 * 2.01).abs() < 1e-5, "decoys {with_decoys}: {near}");
    }
    // Below the percentile's reach, the nearest point counts.
    points.truncate(10);
    assert!((near_bound([&camera], &points).unwrap() - 0.9 * 2.0).abs() < 1e-5);
    assert_eq!(near_bound([&camera], &decoys), None);
    assert_eq!(near_bound([&camera], &[]), None);
}
