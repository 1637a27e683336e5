//! instant-ngp / nerfstudio datasets: one `transforms.json`.
//!
//! Intrinsics `fl_x fl_y cx cy w h` and OpenCV distortion `k1 k2 p1 p2` may
//! be given at the top level or per frame (per frame wins);
//! `camera_angle_x`/`camera_angle_y` are the fallback for the focal lengths
//! and `cx`, `cy` default to the image centre. `w`/`h`, when given, must
//! match the decoded image. `file_path` includes the extension and is
//! relative to the root; `transform_matrix` is used as is (OpenGL
//! convention, world units).
//!
//! Scene box: instant-ngp maps world `p` to `p * scale + offset` and its
//! scene is the unit cube grown by `aabb_scale` about `(0.5, 0.5, 0.5)`, so
//! in world units the box has centre `(0.5 - offset) / scale` and
//! half-extent `0.5 * aabb_scale / scale` (defaults: `aabb_scale` 1, `scale`
//! 0.33, `offset` `[0.5, 0.5, 0.5]`). `near` is 0 and `far` the box diagonal
//! plus the largest camera distance from the box centre, so the box always
//! cuts rays first. Every 8th frame (index % 8 == 0) is held out as both
//! `val` and `test`, the rest is `train`.

use std::path::Path;

use serde_json::Value;

use super::images::decode_all;
use super::json::{self, Obj};
use super::validate::{check_shared_size, unsplit};
use super::{Dataset, DatasetError, DatasetFormat, Frame, LoadOptions};
use crate::engine::geometry::math::{Aabb, Vec3};

pub const DEFAULT_SCALE: f64 = 0.33;
pub const DEFAULT_OFFSET: [f64; 3] = [0.5, 0.5, 0.5];
pub const DEFAULT_AABB_SCALE: f64 = 1.0;

/// Camera models with a pinhole projection that `k1 k2 p1 p2` describe.
const PINHOLE_MODELS: [&str; 5] = ["OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE", "SIMPLE_RADIAL"];

pub fn load(root: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    let path = root.join("transforms.json");
    let top = json::read_object(&path)?;
    let invalid = |message: String| DatasetError::Invalid { path: path.clone(), message };
    let mut extra_warnings = Vec::new();

    check_camera_model(&top, &path)?;
    let aabb_scale = json::opt_positive(&top, "aabb_scale", &path)?.unwrap_or(DEFAULT_AABB_SCALE);
    let scale = json::opt_positive(&top, "scale", &path)?.unwrap_or(DEFAULT_SCALE);
    let offset = offset(&top, &path)?;

    let frames = json::frames(&top, &path)?;
    let mut poses = Vec::with_capacity(frames.len());
    let mut paths = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        poses.push(json::pose(frame, i, &path)?);
        let fp = json::file_path(frame, i, &path)?;
        paths.push((json::image_path(root, fp), path.clone()));
        for k in ["k3", "k4"] {
            let v = match json::opt_number(frame, k, k, &path)? {
                Some(v) => Some(v),
                None => json::opt_number(&top, k, k, &path)?,
            };
            if v.is_some_and(|v| v != 0.0) {
                let w = format!("distortion coefficient {k} is not supported and is ignored");
                if !extra_warnings.contains(&w) {
                    extra_warnings.push(w);
                }
            }
        }
    }

    let images = decode_all(&paths)?;
    let mut out = Vec::with_capacity(frames.len());
    for (i, ((frame, image), (image_path, _))) in frames.iter().zip(images).zip(paths).enumerate() {
        let camera = json::camera(&top, frame, i, &image, &image_path, &path, poses[i], true)?;
        out.push(Frame { name: json::frame_name(&image_path), path: image_path, camera, image, mask: None });
    }
    check_shared_size(
        out.iter()
            .zip(&frames)
            .map(|(f, fr)| (f.path.as_path(), f.image.width, f.image.height, json::has_frame_intrinsics(fr))),
    )?;

    let centre = Vec3::new(
        ((0.5 - offset[0]) / scale) as f32,
        ((0.5 - offset[1]) / scale) as f32,
        ((0.5 - offset[2]) / scale) as f32,
    );
    let half = Vec3::splat((0.5 * aabb_scale / scale) as f32);
    let aabb = Aabb { min: centre - half, max: centre + half };
    if !(aabb.min.is_finite() && aabb.max.is_finite()) {
        return Err(invalid(format!("scene box is not finite (aabb_scale {aabb_scale}, scale {scale})")));
    }
    let cam_dist = out.iter().map(|f| (f.camera.origin() - centre).norm()).fold(0.0f32, f32::max);
    let far = (aabb.max - aabb.min).norm() + cam_dist;

    Ok(unsplit(DatasetFormat::Ngp, root, out, (0.0, far, aabb), opts.background, extra_warnings))
}

/// Refuses camera models other than pinhole (with OpenCV distortion).
fn check_camera_model(top: &Obj, path: &Path) -> Result<(), DatasetError> {
    let invalid = |message: String| DatasetError::Invalid { path: path.to_path_buf(), message };
    match top.get("camera_model") {
        None | Some(Value::Null) => {}
        Some(Value::String(m)) if PINHOLE_MODELS.iter().any(|p| m.eq_ignore_ascii_case(p)) => {}
        Some(m) => {
            return Err(invalid(format!(
                "unsupported camera_model {m} (only pinhole cameras with OpenCV k1 k2 p1 p2 distortion are supported)"
            )));
        }
    }
    if top.get("is_fisheye").and_then(Value::as_bool) == Some(true) {
        return Err(invalid("fisheye cameras (is_fisheye) are not supported".into()));
    }
    Ok(())
}

/// The `offset` of the scene box (Instant-NGP's default when absent).
fn offset(top: &Obj, path: &Path) -> Result<[f64; 3], DatasetError> {
    let invalid = |message: String| DatasetError::Invalid { path: path.to_path_buf(), message };
    Ok(match top.get("offset") {
        None | Some(Value::Null) => DEFAULT_OFFSET,
        Some(Value::Array(a)) if a.len() == 3 => {
            let mut o = [0.0; 3];
            for (dst, v) in o.iter_mut().zip(a) {
                *dst = v
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| invalid("'offset' is not an array of 3 numbers".into()))?;
            }
            o
        }
        Some(_) => return Err(invalid("'offset' is not an array of 3 numbers".into())),
    })
}

#[cfg(test)]
mod tests {
    use super::super::testutil::*;
    use super::*;
    use serde_json::json;

    fn write(root: &Path, v: &serde_json::Value) {
        std::fs::write(root.join("transforms.json"), serde_json::to_string(v).unwrap()).unwrap();
    }

    /// 10 frames of 4x3 JPEGs / PNGs with global intrinsics and distortion.
    fn fox_like(root: &Path) -> serde_json::Value {
        let mut frames = Vec::new();
        for i in 0..10 {
            let name = if i % 2 == 0 { format!("images/{i:04}.jpg") } else { format!("images/{i:04}.png") };
            if i % 2 == 0 {
                write_jpg(&root.join(&name), 4, 3);
            } else {
                write_png(&root.join(&name), 4, 3, false);
            }
            frames.push(
                json!({ "file_path": name, "sharpness": 30.0, "transform_matrix": mat4(&orbit_pose(i as f64, 3.0)) }),
            );
        }
        let v = json!({
            "camera_angle_x": 0.7, "camera_angle_y": 1.2,
            "fl_x": 3.5, "fl_y": 3.25, "cx": 1.75, "cy": 1.25, "w": 4.0, "h": 3.0,
            "k1": 0.05, "k2": -0.08, "p1": -0.001, "p2": 0.0002,
            "aabb_scale": 4,
            "frames": frames,
        });
        write(root, &v);
        v
    }

    #[test]
    fn ngp_loads_intrinsics_distortion_and_splits() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        fox_like(root);
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        assert_eq!(ds.format, DatasetFormat::Ngp);
        assert_eq!(ds.frames.len(), 10);
        assert_eq!(ds.val, vec![0, 8]);
        assert_eq!(ds.test, vec![0, 8]);
        assert_eq!(ds.train, vec![1, 2, 3, 4, 5, 6, 7, 9]);
        let f = &ds.frames[3];
        assert_eq!(f.name, "0003");
        assert_eq!(f.path, root.join("images/0003.png"));
        let c = &f.camera;
        assert_eq!((c.width, c.height, c.fx, c.fy, c.cx, c.cy), (4, 3, 3.5, 3.25, 1.75, 1.25));
        assert_eq!(
            c.distortion,
            crate::engine::geometry::camera::Distortion { k1: 0.05, k2: -0.08, p1: -0.001, p2: 0.0002 }
        );
        assert_eq!(c.origin(), Vec3::new((3.0 * 3f64.cos()) as f32, (3.0 * 3f64.sin()) as f32, 1.0));
        // Default scale 0.33 and offset 0.5: box centred on the origin.
        let half = 0.5 * 4.0 / 0.33;
        assert!((ds.aabb.max.x - half as f32).abs() < 1e-4 && (ds.aabb.min.z + half as f32).abs() < 1e-4);
        let cam_dist = (9.0f32 + 1.0).sqrt();
        let diag = 2.0 * half as f32 * 3f32.sqrt();
        assert_eq!(ds.near, 0.0);
        assert!((ds.far - (diag + cam_dist)).abs() < 1e-3, "{}", ds.far);
        assert!(ds.warnings.iter().any(|w| w.contains("training views")));
    }

    #[test]
    fn ngp_per_frame_overrides_fallbacks_and_box() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let mut v = fox_like(root);
        let top = v.as_object_mut().unwrap();
        for k in ["fl_x", "fl_y", "cx", "cy", "w", "h"] {
            top.remove(k);
        }
        top.insert("scale".into(), json!(0.5));
        top.insert("offset".into(), json!([0.5, 1.0, 0.0]));
        top.insert("aabb_scale".into(), json!(2));
        v["frames"][1]["fl_x"] = json!(9.0);
        v["frames"][1]["k1"] = json!(0.3);
        v["frames"][2]["cx"] = json!(0.5);
        // A frame with its own intrinsics may have another size.
        v["frames"][5]["file_path"] = json!("big.png");
        v["frames"][5]["w"] = json!(6);
        v["frames"][5]["h"] = json!(5);
        write_png(&root.join("big.png"), 6, 5, true);
        write(root, &v);
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        let c0 = &ds.frames[0].camera;
        let fx = 0.5 * 4.0 / (0.5f32 * 0.7).tan();
        let fy = 0.5 * 3.0 / (0.5f32 * 1.2).tan();
        assert!((c0.fx - fx).abs() < 1e-5 && (c0.fy - fy).abs() < 1e-5);
        assert_eq!((c0.cx, c0.cy), (2.0, 1.5));
        let c1 = &ds.frames[1].camera;
        assert_eq!((c1.fx, c1.distortion.k1, c1.distortion.k2), (9.0, 0.3, -0.08));
        assert!((c1.fy - fy).abs() < 1e-5);
        assert_eq!(ds.frames[2].camera.cx, 0.5);
        let c5 = &ds.frames[5].camera;
        assert_eq!((c5.width, c5.height, c5.cx, c5.cy), (6, 5, 3.0, 2.5));
        assert!(ds.frames[5].image.has_alpha);
        // centre = (0.5 - offset) / scale, half-extent = 0.5 * aabb_scale / scale.
        assert_eq!(ds.aabb.centre(), Vec3::new(0.0, -1.0, 1.0));
        assert_eq!(ds.aabb.half_extent(), Vec3::splat(2.0));

        // Without any focal information the error names the key.
        let top = v.as_object_mut().unwrap();
        top.remove("camera_angle_x");
        top.remove("camera_angle_y");
        write(root, &v);
        match Dataset::load(root, &LoadOptions::default()) {
            Err(DatasetError::Invalid { message, .. }) => {
                assert!(message.contains("fl_x"), "{message}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn ngp_errors() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let base = fox_like(root);
        let tj = root.join("transforms.json");
        let load = || Dataset::load(root, &LoadOptions::default());
        assert!(load().is_ok());

        // Global w/h must match each image.
        write_png(&root.join("images/0003.png"), 3, 4, false);
        match load() {
            Err(DatasetError::SizeMismatch { path, got_w: 3, got_h: 4, want_w: 4, want_h: 3 }) => {
                assert_eq!(path, root.join("images/0003.png"))
            }
            other => panic!("{other:?}"),
        }
        // Without w/h, images sharing intrinsics must share a size.
        let mut v = base.clone();
        v.as_object_mut().unwrap().remove("w");
        v.as_object_mut().unwrap().remove("h");
        write(root, &v);
        assert!(matches!(load(), Err(DatasetError::SizeMismatch { got_w: 3, want_w: 4, .. })));
        write_png(&root.join("images/0003.png"), 4, 3, false);
        assert!(load().is_ok());

        // Missing image.
        std::fs::remove_file(root.join("images/0004.jpg")).unwrap();
        match load() {
            Err(DatasetError::MissingImage { path, referenced_by }) => {
                assert_eq!((path, referenced_by), (root.join("images/0004.jpg"), tj.clone()));
            }
            other => panic!("{other:?}"),
        }
        write_jpg(&root.join("images/0004.jpg"), 4, 3);
        // An undecodable image.
        std::fs::write(root.join("images/0004.jpg"), b"\xff\xd8\xff garbage").unwrap();
        assert!(matches!(load(), Err(DatasetError::BadImage { .. })));
        write_jpg(&root.join("images/0004.jpg"), 4, 3);

        // Malformed values.
        for (key, value, needle) in [
            ("scale", json!(-1.0), "scale"),
            ("aabb_scale", json!("big"), "aabb_scale"),
            ("offset", json!([0.5, 0.5]), "offset"),
            ("camera_model", json!("OPENCV_FISHEYE"), "camera_model"),
            ("frames", json!({}), "frames"),
            ("frames", json!([]), "empty"),
            ("k1", json!(null), ""),
        ] {
            let mut v = base.clone();
            v[key] = value;
            write(root, &v);
            match load() {
                Ok(_) if needle.is_empty() => {}
                Err(DatasetError::Invalid { message, .. }) if !needle.is_empty() => {
                    assert!(message.contains(needle), "{message}")
                }
                other => panic!("{key}: {other:?}"),
            }
        }
        // A mirrored pose.
        let mut v = base.clone();
        v["frames"][7]["transform_matrix"][2][2] = json!(-v["frames"][7]["transform_matrix"][2][2].as_f64().unwrap());
        v["frames"][7]["transform_matrix"][2][0] = json!(-v["frames"][7]["transform_matrix"][2][0].as_f64().unwrap());
        v["frames"][7]["transform_matrix"][2][1] = json!(-v["frames"][7]["transform_matrix"][2][1].as_f64().unwrap());
        write(root, &v);
        assert!(matches!(load(), Err(DatasetError::BadPose { frame: 7, .. })));
        // Truncated JSON.
        let text = serde_json::to_string(&base).unwrap();
        std::fs::write(&tj, &text[..text.len() / 2]).unwrap();
        assert!(matches!(load(), Err(DatasetError::Json { path, .. }) if path == tj));
        // k3 is reported, not silently used.
        let mut v = base.clone();
        v["k3"] = json!(0.01);
        write(root, &v);
        assert!(load().unwrap().warnings.iter().any(|w| w.contains("k3")));
    }
}
