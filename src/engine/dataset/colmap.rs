//! COLMAP datasets: a sparse model in `sparse/0/` (or `sparse/`), binary or
//! text, and the photos in `images/` (or a downscaled `images_N/`, chosen as
//! the LLFF loader does).
//!
//! COLMAP stores each registered image's world-to-camera rotation (a unit
//! quaternion) and translation in OpenCV's camera axes (x right, y down, z
//! forward); cameras here are camera-to-world in OpenGL's (y up, z back), so
//! the pose is inverted and its y and z axes flipped. Photos COLMAP did not
//! register are left out with a warning. The scene box holds the cameras
//! and the sparse points between their 2nd and 98th percentiles on each
//! axis (a few stray points far away do not blow it up). The near bound is
//! 0.9 times the nearest depth at which a camera sees the sparse points, as
//! NeRF's LLFF loader takes it from `poses_bounds.npy` ([`near_bound`]).

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use super::colmap_model::{self, CameraModel, ImagePose};
use super::images::{decode_all, has_image_extension};
use super::llff::IMAGE_DIRS;
use super::validate::{check_pose, check_shared_size, unsplit};
use super::{Dataset, DatasetError, DatasetFormat, Frame, LoadOptions};
use crate::engine::geometry::camera::{Camera, Distortion};
use crate::engine::geometry::math::{Aabb, Vec3};

/// Where the model may be, in the order looked at.
pub const MODEL_DIRS: [&str; 2] = ["sparse/0", "sparse"];

/// The camera models this loader takes (the others are refused by name).
pub const SUPPORTED_MODELS: [&str; 5] = ["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"];

/// The lower and upper percentiles of the sparse points kept in the box.
const POINT_PERCENTILES: (f64, f64) = (0.02, 0.98);

/// The box grows by this fraction of its size on every side.
const BOX_MARGIN: f32 = 0.1;

/// The percentile of each camera's sparse-point depths taken as its
/// nearest. LLFF's `imgs2poses` takes the 0.1th percentile of the points
/// each image observes; the model's tracks are not read here, so all the
/// points in a camera's frustum count, and the 1st percentile passes over
/// a few more strays in front of it (with fewer than 51 points, the
/// nearest counts). A small near object with fewer than 1% of a camera's
/// points may fall in front of that camera's bound; the bound is the
/// least over all cameras.
const NEAR_PERCENTILE: f64 = 0.01;

/// The near bound is this fraction of the nearest depth (LLFF's 0.9).
const NEAR_FRACTION: f32 = 0.9;

/// The folder holding the model, if `root` has one.
pub fn model_dir(root: &Path) -> Option<PathBuf> {
    MODEL_DIRS.iter().map(|d| root.join(d)).find(|d| d.join("cameras.bin").is_file() || d.join("cameras.txt").is_file())
}

pub fn load(root: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    let dir = model_dir(root).ok_or_else(|| DatasetError::UnknownFormat(root.to_path_buf()))?;
    let model = colmap_model::read(&dir)?;
    let invalid = |message: String| DatasetError::Invalid { path: dir.clone(), message };
    if model.images.is_empty() {
        return Err(invalid("the model has no registered images".into()));
    }
    let image_dir =
        IMAGE_DIRS.iter().map(|d| root.join(d)).find(|p| p.is_dir()).ok_or_else(|| DatasetError::Invalid {
            path: root.to_path_buf(),
            message: format!("no image folder (looked for {})", IMAGE_DIRS.join(", ")),
        })?;
    let mut images = model.images.clone();
    // Held-out frames are every 8th in name order, whatever ids COLMAP gave.
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let mut extra_warnings = Vec::new();
    let files = image_files(&image_dir, &images, &dir, &mut extra_warnings)?;
    let cameras: HashMap<u32, &CameraModel> = model.cameras.iter().map(|c| (c.id, c)).collect();
    let decoded = decode_all(&files)?;
    let mut frames = Vec::with_capacity(images.len());
    for (i, ((pose, image), (path, _))) in images.iter().zip(decoded).zip(files).enumerate() {
        let cam = cameras.get(&pose.camera_id).ok_or_else(|| {
            invalid(format!("image '{}' uses camera {}, which the model lacks", pose.name, pose.camera_id))
        })?;
        let c2w = check_pose(&camera_to_world(pose), &dir, i)?;
        let camera =
            intrinsics(cam, image.width, image.height, c2w).map_err(|m| invalid(format!("camera {}: {m}", cam.id)))?;
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        frames.push(Frame { name, path, camera, image, mask: None });
    }
    check_shared_size(frames.iter().map(|f| (f.path.as_path(), f.image.width, f.image.height, false)))?;
    let aabb = scene_box(&frames, &model.points);
    if !(aabb.min.is_finite() && aabb.max.is_finite()) {
        return Err(invalid("the cameras and points give no finite scene box".into()));
    }
    let centre = aabb.centre();
    let cam_dist = frames.iter().map(|f| (f.camera.origin() - centre).norm()).fold(0.0f32, f32::max);
    let far = (aabb.max - aabb.min).norm() + cam_dist;
    let near = near_bound(frames.iter().map(|f| &f.camera), &model.points).filter(|&n| n < far).unwrap_or(0.0);
    Ok(unsplit(DatasetFormat::Colmap, root, frames, (near, far, aabb), opts.background, extra_warnings))
}

/// The file of each registered image (all must exist), and a warning
/// naming the photos of the folder COLMAP did not register.
fn image_files(
    image_dir: &Path,
    images: &[ImagePose],
    model_dir: &Path,
    warnings: &mut Vec<String>,
) -> Result<Vec<(PathBuf, PathBuf)>, DatasetError> {
    let files: Vec<(PathBuf, PathBuf)> =
        images.iter().map(|i| (image_dir.join(&i.name), model_dir.to_path_buf())).collect();
    let missing: Vec<&str> =
        images.iter().zip(&files).filter(|(_, f)| !f.0.is_file()).map(|(i, _)| i.name.as_str()).collect();
    if !missing.is_empty() {
        let shown = missing.iter().take(5).copied().collect::<Vec<_>>().join(", ");
        let more = if missing.len() > 5 { format!(" and {} more", missing.len() - 5) } else { String::new() };
        return Err(DatasetError::Invalid {
            path: image_dir.to_path_buf(),
            message: format!("{} registered images are missing: {shown}{more}", missing.len()),
        });
    }
    let registered: BTreeSet<&str> = images.iter().map(|i| i.name.as_str()).collect();
    let unregistered: Vec<String> = std::fs::read_dir(image_dir)
        .map_err(|e| DatasetError::Io { path: image_dir.to_path_buf(), source: e })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && has_image_extension(p))
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .filter(|n| !registered.contains(n.as_str()))
        .collect();
    if !unregistered.is_empty() {
        let total = unregistered.len() + images.len();
        warnings.push(format!(
            "COLMAP registered {} of {total} images; left out: {}",
            images.len(),
            unregistered.iter().take(5).cloned().collect::<Vec<_>>().join(", ")
        ));
    }
    Ok(files)
}

/// Camera-to-world in OpenGL axes from COLMAP's world-to-camera pose.
fn camera_to_world(p: &ImagePose) -> [[f64; 4]; 3] {
    let [w, x, y, z] = p.qvec;
    let n = (w * w + x * x + y * y + z * z).sqrt();
    let (w, x, y, z) = (w / n, x / n, y / n, z / n);
    // World-to-camera rotation R.
    let r = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    let t = p.tvec;
    let mut c2w = [[0.0; 4]; 3];
    for a in 0..3 {
        // Rotation R^T, with the camera's y and z axes flipped.
        for (b, sign) in [1.0, -1.0, -1.0].into_iter().enumerate() {
            c2w[a][b] = sign * r[b][a];
        }
        // Centre -R^T t.
        c2w[a][3] = -(0..3).map(|k| r[k][a] * t[k]).sum::<f64>();
    }
    c2w
}

/// Our camera for a COLMAP camera whose images are `width` x `height`
/// (a downscaled folder scales the intrinsics with the image).
fn intrinsics(c: &CameraModel, width: u32, height: u32, c2w: [[f32; 4]; 3]) -> Result<Camera, String> {
    let p = &c.params;
    let (fx, fy, cx, cy, d) = match c.model {
        "SIMPLE_PINHOLE" => (p[0], p[0], p[1], p[2], [0.0; 4]),
        "PINHOLE" => (p[0], p[1], p[2], p[3], [0.0; 4]),
        "SIMPLE_RADIAL" => (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0]),
        "RADIAL" => (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0]),
        "OPENCV" => (p[0], p[1], p[2], p[3], [p[4], p[5], p[6], p[7]]),
        other => {
            return Err(format!("camera model {other} is not supported (supported: {})", SUPPORTED_MODELS.join(", ")));
        }
    };
    if !(c.width > 0 && c.height > 0) {
        return Err(format!("size {}x{} is empty", c.width, c.height));
    }
    if !(fx > 0.0 && fy > 0.0 && [fx, fy, cx, cy].iter().chain(&d).all(|v| v.is_finite())) {
        return Err(format!("{} parameters {p:?} are not a camera", c.model));
    }
    let (sx, sy) = (width as f64 / c.width as f64, height as f64 / c.height as f64);
    Ok(Camera {
        width,
        height,
        fx: (fx * sx) as f32,
        fy: (fy * sy) as f32,
        cx: (cx * sx) as f32,
        cy: (cy * sy) as f32,
        distortion: Distortion { k1: d[0] as f32, k2: d[1] as f32, p1: d[2] as f32, p2: d[3] as f32 },
        c2w,
    })
}

/// The box around the cameras and the sparse points between their
/// percentiles on each axis, with a margin.
fn scene_box(frames: &[Frame], points: &[[f64; 3]]) -> Aabb {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for f in frames {
        lo = lo.min(f.camera.origin());
        hi = hi.max(f.camera.origin());
    }
    let finite: Vec<[f64; 3]> = points.iter().copied().filter(|p| p.iter().all(|v| v.is_finite())).collect();
    if !finite.is_empty() {
        let mut ends = [[0.0f32; 3]; 2];
        for axis in 0..3 {
            let mut v: Vec<f64> = finite.iter().map(|p| p[axis]).collect();
            v.sort_by(f64::total_cmp);
            let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize] as f32;
            ends[0][axis] = at(POINT_PERCENTILES.0);
            ends[1][axis] = at(POINT_PERCENTILES.1);
        }
        lo = lo.min(Vec3::from_array(ends[0]));
        hi = hi.max(Vec3::from_array(ends[1]));
    }
    let m = (hi - lo) * BOX_MARGIN;
    Aabb { min: lo - m, max: hi + m }
}

/// 0.9 times the smallest, over the cameras, of the [`NEAR_PERCENTILE`]
/// of the depths (along the optical axis) of the sparse points in front
/// of the camera and inside its image; `None` when no camera sees a point.
fn near_bound<'a>(cameras: impl IntoIterator<Item = &'a Camera>, points: &[[f64; 3]]) -> Option<f32> {
    let mut nearest = f32::INFINITY;
    let mut depths = Vec::new();
    for c in cameras {
        let o = c.origin();
        // The camera's axes in world space: right, up, and the optical axis.
        let (right, up, axis) = (
            c.rotate(Vec3::new(1.0, 0.0, 0.0)),
            c.rotate(Vec3::new(0.0, 1.0, 0.0)),
            c.rotate(Vec3::new(0.0, 0.0, -1.0)),
        );
        depths.clear();
        for p in points {
            let q = Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32) - o;
            let z = q.dot(axis);
            if !(z > 0.0 && z.is_finite()) {
                continue;
            }
            let u = c.cx + c.fx * q.dot(right) / z;
            let v = c.cy - c.fy * q.dot(up) / z;
            if (0.0..c.width as f32).contains(&u) && (0.0..c.height as f32).contains(&v) {
                depths.push(z);
            }
        }
        if !depths.is_empty() {
            depths.sort_by(f32::total_cmp);
            let k = ((depths.len() - 1) as f64 * NEAR_PERCENTILE).round() as usize;
            nearest = nearest.min(depths[k]);
        }
    }
    (nearest.is_finite() && nearest > 0.0).then_some(NEAR_FRACTION * nearest)
}

#[cfg(test)]
#[path = "colmap_tests.rs"]
mod tests;
