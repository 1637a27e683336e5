//! NeRF synthetic ("Blender") datasets: `transforms_{train,val,test}.json`.
//!
//! Each file has `camera_angle_x` and `frames[]` with `file_path` (relative
//! to the root, `.png` implied when there is no extension) and a 4x4
//! OpenGL-convention `transform_matrix`. The focal length follows from the
//! decoded image width (`0.5 * w / tan(0.5 * camera_angle_x)`); `fl_x`,
//! `fl_y`, `cx`, `cy` override it when present (top level or per frame).
//! `near`/`far` default to 2 and 6, the box is `[-1.5, 1.5]^3`.

use std::path::{Path, PathBuf};

use super::images::decode_all;
use super::json::{self, Obj};
use super::validate::{check_shared_size, warnings};
use super::{Dataset, DatasetError, DatasetFormat, Frame, LoadOptions, MaskUse, Split};
use crate::engine::geometry::math::{Aabb, Vec3};

pub const DEFAULT_NEAR: f32 = 2.0;
pub const DEFAULT_FAR: f32 = 6.0;
pub const HALF_EXTENT: f32 = 1.5;

/// The split file of `split` under `root`.
pub fn split_file(root: &Path, split: Split) -> PathBuf {
    root.join(format!("transforms_{}.json", split.name()))
}

/// The split files listed in `opts.splits` (all when empty) that exist,
/// read: at least one must.
fn split_files(root: &Path, opts: &LoadOptions) -> Result<Vec<(Split, PathBuf, Obj)>, DatasetError> {
    let wanted: Vec<Split> =
        Split::ALL.into_iter().filter(|s| opts.splits.is_empty() || opts.splits.contains(s)).collect();
    let mut docs: Vec<(Split, PathBuf, Obj)> = Vec::new();
    for &split in &wanted {
        let path = split_file(root, split);
        if path.is_file() {
            let top = json::read_object(&path)?;
            docs.push((split, path, top));
        }
    }
    if docs.is_empty() {
        let names: Vec<String> = wanted.iter().map(|s| format!("transforms_{}.json", s.name())).collect();
        return Err(DatasetError::Invalid {
            path: root.to_path_buf(),
            message: format!("none of the requested split files exists ({})", names.join(", ")),
        });
    }
    Ok(docs)
}

/// Loads the split files listed in `opts.splits` (an empty list means all)
/// that exist; at least one must. Frames are ordered train, val, test.
pub fn load(root: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    let docs = split_files(root, opts)?;

    // Pass 1: poses and image paths (cheap checks before any decoding).
    struct Entry<'a> {
        split: Split,
        json: &'a Path,
        top: &'a Obj,
        frame: &'a Obj,
        index: usize,
        c2w: [[f32; 4]; 3],
    }
    let mut entries = Vec::new();
    let mut paths = Vec::new();
    let (mut near, mut far) = (None, None);
    for (split, path, top) in &docs {
        for (index, frame) in json::frames(top, path)?.into_iter().enumerate() {
            let c2w = json::pose(frame, index, path)?;
            let fp = json::file_path(frame, index, path)?;
            paths.push((json::image_path(root, fp), path.clone()));
            entries.push(Entry { split: *split, json: path, top, frame, index, c2w });
        }
        near = near.or(json::opt_number(top, "near", "near", path)?);
        far = far.or(json::opt_number(top, "far", "far", path)?);
    }
    let near = near.map_or(DEFAULT_NEAR, |v| v as f32);
    let far = far.map_or(DEFAULT_FAR, |v| v as f32);
    if !(near >= 0.0 && far > near && far.is_finite()) {
        return Err(DatasetError::Invalid {
            path: docs[0].1.clone(),
            message: format!("need 0 <= near < far, got near {near}, far {far}"),
        });
    }

    // Pass 2: decode in parallel, then build the cameras in order.
    let images = decode_all(&paths)?;
    let mut ds = Dataset {
        format: DatasetFormat::Blender,
        root: root.to_path_buf(),
        frames: Vec::with_capacity(entries.len()),
        train: Vec::new(),
        val: Vec::new(),
        test: Vec::new(),
        near,
        far,
        aabb: Aabb { min: Vec3::splat(-HALF_EXTENT), max: Vec3::splat(HALF_EXTENT) },
        background: opts.background,
        warnings: Vec::new(),
        masks: MaskUse::Off,
        mask_folder: None,
    };
    for ((e, image), (path, _)) in entries.iter().zip(images).zip(paths) {
        let camera = json::camera(e.top, e.frame, e.index, &image, &path, e.json, e.c2w, false)?;
        let k = ds.frames.len();
        match e.split {
            Split::Train => ds.train.push(k),
            Split::Val => ds.val.push(k),
            Split::Test => ds.test.push(k),
        }
        ds.frames.push(Frame { name: json::frame_name(&path), path, camera, image, mask: None });
    }
    check_shared_size(
        ds.frames
            .iter()
            .zip(&entries)
            .map(|(f, e)| (f.path.as_path(), f.image.width, f.image.height, json::has_frame_intrinsics(e.frame))),
    )?;
    ds.warnings = warnings(&ds);
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::super::testutil::*;
    use super::*;
    use serde_json::json;

    fn write_split(root: &Path, split: Split, v: serde_json::Value) {
        std::fs::write(split_file(root, split), serde_json::to_string_pretty(&v).unwrap()).unwrap();
    }

    fn frames(dir: &str, n: usize) -> Vec<serde_json::Value> {
        (0..n)
            .map(|i| {
                json!({
                    "file_path": format!("./{dir}/r_{i}"),
                    "rotation": 0.1,
                    "transform_matrix": mat4(&orbit_pose(i as f64 * 0.7, 4.0))
                })
            })
            .collect()
    }

    /// train (3 frames), val (2), test (2) of 4x3 RGBA PNGs.
    fn synthetic(root: &Path) {
        for (split, n) in [(Split::Train, 3), (Split::Val, 2), (Split::Test, 2)] {
            for i in 0..n {
                write_png(&root.join(split.name()).join(format!("r_{i}.png")), 4, 3, true);
            }
            write_split(root, split, json!({ "camera_angle_x": 0.69, "frames": frames(split.name(), n) }));
        }
    }

    #[test]
    fn blender_loads_splits_and_intrinsics() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        synthetic(root);
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        assert_eq!(ds.format, DatasetFormat::Blender);
        assert_eq!(ds.frames.len(), 7);
        assert_eq!((ds.train.clone(), ds.val.clone(), ds.test.clone()), (vec![0, 1, 2], vec![3, 4], vec![5, 6]));
        let f = &ds.frames[5];
        assert_eq!(f.name, "r_0");
        assert_eq!(f.path, root.join("test").join("r_0.png"));
        let c = &f.camera;
        let focal = 0.5 * 4.0 / (0.5f32 * 0.69).tan();
        assert!((c.fx - focal).abs() < 1e-4 && (c.fy - focal).abs() < 1e-4);
        assert_eq!((c.width, c.height, c.cx, c.cy), (4, 3, 2.0, 1.5));
        assert!(c.distortion.is_identity());
        let want = orbit_pose(0.0, 4.0);
        for (got, want) in c.c2w.iter().flatten().zip(want.iter().flatten()) {
            assert!((*got as f64 - want).abs() < 1e-6);
        }
        assert!(f.image.has_alpha && f.image.width == 4 && f.image.rgba.len() == 48);
        assert_eq!((ds.near, ds.far), (2.0, 6.0));
        assert_eq!(ds.aabb.max, Vec3::splat(1.5));
        assert_eq!(ds.background, [1.0; 3]);
        assert!(ds.warnings.iter().any(|w| w.contains("only 3 training views")), "{:?}", ds.warnings);

        // Only the requested splits; a missing split file is skipped.
        std::fs::remove_file(split_file(root, Split::Val)).unwrap();
        let opts = LoadOptions { background: [0.0; 3], splits: vec![Split::Test, Split::Val], ..Default::default() };
        let ds = Dataset::load(root, &opts).unwrap();
        assert_eq!((ds.frames.len(), ds.train.len(), ds.test.clone()), (2, 0, vec![0, 1]));
        assert_eq!(ds.background, [0.0; 3]);
        let opts = LoadOptions { splits: vec![Split::Val], ..Default::default() };
        assert!(matches!(Dataset::load(root, &opts), Err(DatasetError::Invalid { .. })));
    }

    #[test]
    fn blender_extensions_overrides_and_near_far() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        write_png(&root.join("a.png"), 4, 3, false);
        write_png(&root.join("imgs/b.PNG"), 4, 3, false);
        write_jpg(&root.join("c.jpg"), 4, 3);
        let pose = mat4(&orbit_pose(0.3, 3.0));
        write_split(
            root,
            Split::Train,
            json!({
                "camera_angle_x": 0.5, "near": 0.5, "far": 9.0,
                "frames": [
                    { "file_path": "a", "transform_matrix": pose },
                    { "file_path": "./imgs/b.PNG", "transform_matrix": pose, "fl_x": 7.0, "cx": 1.0 },
                    { "file_path": "c.jpg", "transform_matrix": pose },
                ]
            }),
        );
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        let names: Vec<&str> = ds.frames.iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["a", "b", "c"]);
        assert_eq!(ds.frames[1].path, root.join("imgs/b.PNG"));
        assert!(!ds.frames[0].image.has_alpha && ds.frames[0].image.rgba[3] == 255);
        let c1 = &ds.frames[1].camera;
        assert_eq!((c1.fx, c1.fy, c1.cx, c1.cy), (7.0, 7.0, 1.0, 1.5));
        assert_eq!((ds.near, ds.far), (0.5, 9.0));
    }

    #[test]
    fn blender_errors() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        synthetic(root);
        let opts = LoadOptions::default();
        let train = split_file(root, Split::Train);
        let load = || Dataset::load(root, &opts);

        // Missing image names the image and the JSON.
        std::fs::remove_file(root.join("val/r_1.png")).unwrap();
        match load() {
            Err(DatasetError::MissingImage { path, referenced_by }) => {
                assert_eq!(path, root.join("val/r_1.png"));
                assert_eq!(referenced_by, split_file(root, Split::Val));
            }
            other => panic!("{other:?}"),
        }
        write_png(&root.join("val/r_1.png"), 4, 3, true);

        // Images sharing intrinsics must share a size.
        write_png(&root.join("test/r_1.png"), 5, 3, true);
        assert!(matches!(load(), Err(DatasetError::SizeMismatch { got_w: 5, want_w: 4, .. })));
        write_png(&root.join("test/r_1.png"), 4, 3, true);
        assert!(load().is_ok());

        // JSON size keys must match the image.
        let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&train).unwrap()).unwrap();
        v["w"] = json!(8);
        write_split(root, Split::Train, v.clone());
        assert!(matches!(load(), Err(DatasetError::SizeMismatch { want_w: 8, got_w: 4, .. })));

        // Malformed JSON.
        std::fs::write(&train, "{ \"camera_angle_x\": 0.6, \"frames\": [ ").unwrap();
        match load() {
            Err(DatasetError::Json { path, message }) => {
                assert_eq!(path, train);
                assert!(message.contains("EOF"), "{message}");
            }
            other => panic!("{other:?}"),
        }
        std::fs::write(&train, "[1, 2]").unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { .. })));

        // Missing keys name the key.
        let base = json!({ "camera_angle_x": 0.69, "frames": frames("train", 3) });
        for (edit, key) in [
            (json!({ "frames": frames("train", 3) }), "camera_angle_x"),
            (json!({ "camera_angle_x": 0.69 }), "frames"),
            (
                json!({ "camera_angle_x": 0.69, "frames": [{ "transform_matrix": mat4(&orbit_pose(0.0, 4.0)) }] }),
                "file_path",
            ),
            (json!({ "camera_angle_x": 0.69, "frames": [{ "file_path": "./train/r_0" }] }), "transform_matrix"),
            (json!({ "camera_angle_x": 0.69, "frames": [] }), "empty"),
            (json!({ "camera_angle_x": "wide", "frames": frames("train", 3) }), "camera_angle_x"),
            (
                json!({ "camera_angle_x": 0.69, "frames": [{ "file_path": "./train/r_0", "transform_matrix": [[1, 0], [0, 1]] }] }),
                "transform_matrix",
            ),
        ] {
            write_split(root, Split::Train, edit);
            match load() {
                Err(DatasetError::Invalid { path, message }) => {
                    assert_eq!(path, train);
                    assert!(message.contains(key), "{message} should name {key}");
                }
                other => panic!("{key}: {other:?}"),
            }
        }

        // Non-rigid pose names the frame.
        let mut v = base.clone();
        v["frames"][2]["transform_matrix"][0][0] = json!(2.0);
        write_split(root, Split::Train, v);
        match load() {
            Err(DatasetError::BadPose { frame: 2, path, message }) => {
                assert_eq!(path, train);
                assert!(message.contains("orthonormal"));
            }
            other => panic!("{other:?}"),
        }
        // A number too large for f64 is a JSON error, not a panic.
        std::fs::write(
            &train,
            serde_json::to_string(&base).unwrap().replacen("\"rotation\":0.1", "\"rotation\":1e999", 1),
        )
        .unwrap();
        assert!(matches!(load(), Err(DatasetError::Json { .. })));
        write_split(root, Split::Train, base);
        assert!(load().is_ok());
    }
}
