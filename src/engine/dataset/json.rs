//! Helpers shared by the two `transforms*.json` loaders (Blender and
//! instant-ngp/nerfstudio): reading the file, typed key access with errors
//! that name the key, poses, image paths and camera intrinsics.

use std::path::{Component, Path, PathBuf};

use serde_json::{Map, Value};

use super::images::has_image_extension;
use super::validate::check_pose;
use super::{DatasetError, Image};
use crate::engine::geometry::camera::{Camera, Distortion};

pub(super) type Obj = Map<String, Value>;

fn invalid(path: &Path, message: String) -> DatasetError {
    DatasetError::Invalid { path: path.to_path_buf(), message }
}

/// Reads and parses a JSON file whose top level must be an object.
pub(super) fn read_object(path: &Path) -> Result<Obj, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(|e| DatasetError::Io { path: path.to_path_buf(), source: e })?;
    let v: Value = serde_json::from_str(&text)
        .map_err(|e| DatasetError::Json { path: path.to_path_buf(), message: e.to_string() })?;
    match v {
        Value::Object(o) => Ok(o),
        _ => Err(invalid(path, "top level is not a JSON object".into())),
    }
}

/// The non-empty `frames` array of a transforms file, each entry an object.
pub(super) fn frames<'a>(top: &'a Obj, path: &Path) -> Result<Vec<&'a Obj>, DatasetError> {
    let arr = match top.get("frames") {
        None => return Err(invalid(path, "missing key 'frames'".into())),
        Some(Value::Array(a)) => a,
        Some(_) => return Err(invalid(path, "'frames' is not an array".into())),
    };
    if arr.is_empty() {
        return Err(invalid(path, "'frames' is empty: the dataset has no frames".into()));
    }
    arr.iter()
        .enumerate()
        .map(|(i, f)| match f {
            Value::Object(o) => Ok(o),
            _ => Err(invalid(path, format!("frames[{i}] is not an object"))),
        })
        .collect()
}

/// An optional number; present but not a number is an error naming `what`.
pub(super) fn opt_number(obj: &Obj, key: &str, what: &str, path: &Path) -> Result<Option<f64>, DatasetError> {
    match obj.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => match v.as_f64() {
            Some(x) if x.is_finite() => Ok(Some(x)),
            _ => Err(invalid(path, format!("'{what}' is not a finite number"))),
        },
    }
}

/// A number looked up in the frame first, then at the top level.
fn lookup(global: &Obj, frame: &Obj, key: &str, i: usize, path: &Path) -> Result<Option<f64>, DatasetError> {
    match opt_number(frame, key, &format!("frames[{i}].{key}"), path)? {
        Some(v) => Ok(Some(v)),
        None => opt_number(global, key, key, path),
    }
}

/// `frames[i].file_path` as a string.
pub(super) fn file_path<'a>(frame: &'a Obj, i: usize, path: &Path) -> Result<&'a str, DatasetError> {
    match frame.get("file_path") {
        None => Err(invalid(path, format!("missing key 'frames[{i}].file_path'"))),
        Some(Value::String(s)) if !s.is_empty() => Ok(s),
        Some(_) => Err(invalid(path, format!("'frames[{i}].file_path' is not a non-empty string"))),
    }
}

/// `frames[i].transform_matrix` (4x4, or 3x4 without the bottom row),
/// validated and converted to the rows of a 3x4 camera-to-world matrix.
pub(super) fn pose(frame: &Obj, i: usize, path: &Path) -> Result<[[f32; 4]; 3], DatasetError> {
    let bad = || invalid(path, format!("'frames[{i}].transform_matrix' is not a 4x4 array of numbers"));
    let rows = match frame.get("transform_matrix") {
        None => {
            return Err(invalid(path, format!("missing key 'frames[{i}].transform_matrix'")));
        }
        Some(Value::Array(rows)) => rows,
        Some(_) => return Err(bad()),
    };
    if rows.len() != 3 && rows.len() != 4 {
        return Err(bad());
    }
    let mut m = [[0.0f64; 4]; 3];
    for (r, row) in rows.iter().enumerate() {
        let row = match row {
            Value::Array(row) if row.len() == 4 => row,
            _ => return Err(bad()),
        };
        for (c, v) in row.iter().enumerate() {
            let x = v.as_f64().ok_or_else(bad)?;
            if let Some(dst) = m.get_mut(r).and_then(|mr| mr.get_mut(c)) {
                *dst = x;
            }
        }
    }
    check_pose(&m, path, i)
}

/// `root` joined with a relative path from a JSON file, without `.`
/// components (`./train/r_0` -> `root/train/r_0`). Absolute paths are kept.
pub(super) fn join_clean(root: &Path, rel: &str) -> PathBuf {
    let rel = Path::new(rel);
    if rel.is_absolute() {
        return rel.to_path_buf();
    }
    let mut out = root.to_path_buf();
    for c in rel.components() {
        if c != Component::CurDir {
            out.push(c);
        }
    }
    out
}

/// The image a `file_path` refers to. Paths with a PNG/JPEG extension are
/// used as they are; otherwise `.png` is implied (unless only the bare path
/// exists).
pub(super) fn image_path(root: &Path, file_path: &str) -> PathBuf {
    let p = join_clean(root, file_path);
    if has_image_extension(&p) {
        return p;
    }
    let mut with_png = p.clone().into_os_string();
    with_png.push(".png");
    let with_png = PathBuf::from(with_png);
    if !with_png.is_file() && p.is_file() { p } else { with_png }
}

/// The frame name: the image file's stem.
pub(super) fn frame_name(path: &Path) -> String {
    path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

/// Keys that make a frame's intrinsics its own.
const INTRINSIC_KEYS: [&str; 8] = ["fl_x", "fl_y", "camera_angle_x", "camera_angle_y", "cx", "cy", "w", "h"];

/// Whether a frame entry carries its own intrinsics (then its image may
/// differ in size from the others).
pub(super) fn has_frame_intrinsics(frame: &Obj) -> bool {
    INTRINSIC_KEYS.iter().any(|k| frame.contains_key(*k))
}

/// Builds frame `i`'s camera from the keys of the frame (first) and the top
/// level: `w`/`h` (checked against the decoded image), `fl_x`/`fl_y`, falling
/// back to `camera_angle_x` (and `camera_angle_y` when `use_angle_y`), `cx`/`cy`
/// (image centre by default) and `k1 k2 p1 p2`.
#[allow(clippy::too_many_arguments)]
pub(super) fn camera(
    global: &Obj,
    frame: &Obj,
    i: usize,
    image: &Image,
    image_path: &Path,
    path: &Path,
    c2w: [[f32; 4]; 3],
    use_angle_y: bool,
) -> Result<Camera, DatasetError> {
    let get = |k: &str| lookup(global, frame, k, i, path);
    let (w, h) = (image.width, image.height);
    let want_w = get("w")?;
    let want_h = get("h")?;
    for (k, v) in [("w", want_w), ("h", want_h)] {
        if let Some(v) = v
            && !(v >= 1.0 && v <= u32::MAX as f64)
        {
            return Err(invalid(path, format!("'{k}' for frame {i} is not a positive size ({v})")));
        }
    }
    let want = (want_w.map_or(w, |v| v.round() as u32), want_h.map_or(h, |v| v.round() as u32));
    if want != (w, h) {
        return Err(DatasetError::SizeMismatch {
            path: image_path.to_path_buf(),
            got_w: w,
            got_h: h,
            want_w: want.0,
            want_h: want.1,
        });
    }
    let angle = |k: &str| -> Result<Option<f64>, DatasetError> {
        match get(k)? {
            Some(a) if !(a > 0.0 && a < std::f64::consts::PI) => {
                Err(invalid(path, format!("'{k}' for frame {i} is not an angle in (0, pi) radians ({a})")))
            }
            a => Ok(a),
        }
    };
    let from_x = angle("camera_angle_x")?.map(|a| Camera::from_fov(w, h, a as f32, c2w).fx);
    let from_y =
        if use_angle_y { angle("camera_angle_y")?.map(|a| Camera::from_fov(h, w, a as f32, c2w).fx) } else { None };
    let fx = get("fl_x")?.map(|v| v as f32).or(from_x);
    let fy = get("fl_y")?.map(|v| v as f32).or(from_y);
    let (fx, fy) = match (fx, fy) {
        (Some(x), Some(y)) => (x, y),
        (Some(x), None) => (x, x),
        (None, Some(y)) => (y, y),
        (None, None) => {
            let keys = if use_angle_y { "'fl_x' or 'camera_angle_x'" } else { "'camera_angle_x' or 'fl_x'" };
            return Err(invalid(path, format!("missing key {keys} (focal length of frame {i})")));
        }
    };
    for (k, f) in [("fl_x", fx), ("fl_y", fy)] {
        if !(f.is_finite() && f > 0.0) {
            return Err(invalid(path, format!("focal length '{k}' of frame {i} is not positive ({f})")));
        }
    }
    let cx = get("cx")?.map_or(0.5 * w as f32, |v| v as f32);
    let cy = get("cy")?.map_or(0.5 * h as f32, |v| v as f32);
    let d = |k: &str| -> Result<f32, DatasetError> { Ok(get(k)?.unwrap_or(0.0) as f32) };
    let distortion = Distortion { k1: d("k1")?, k2: d("k2")?, p1: d("p1")?, p2: d("p2")? };
    let finite = [cx, cy, distortion.k1, distortion.k2, distortion.p1, distortion.p2].iter().all(|v| v.is_finite());
    if !finite {
        return Err(invalid(path, format!("intrinsics of frame {i} do not fit in f32")));
    }
    Ok(Camera { width: w, height: h, fx, fy, cx, cy, distortion, c2w })
}

/// An optional positive number at the top level.
pub(super) fn opt_positive(top: &Obj, key: &str, path: &Path) -> Result<Option<f64>, DatasetError> {
    match opt_number(top, key, key, path)? {
        Some(v) if v <= 0.0 => Err(invalid(path, format!("'{key}' must be positive ({v})"))),
        v => Ok(v),
    }
}
