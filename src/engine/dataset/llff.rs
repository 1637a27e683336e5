//! LLFF forward-facing datasets: `poses_bounds.npy` plus an image folder.
//!
//! The image folder is the first that exists of `images_8`, `images_4`,
//! `images_2`, `images` (the smallest standard downsample first). Its PNG /
//! JPEG files (case-insensitive extensions), sorted by name, pair with the
//! rows of `poses_bounds.npy` (N x 17 float64) in order.
//!
//! Conventions follow the NeRF loader (`load_llff.py` in bmild/nerf): each
//! row is a 3x5 matrix (row-major) whose column 4 is `[H, W, focal]` at full
//! resolution, followed by the view's near/far depth bounds. The focal length
//! is scaled by `image_width / W`; the rotation columns are reordered from
//! [down, right, backwards] to [right, up, backwards]; translations and
//! bounds are scaled by `1 / (0.75 * min bound)`; the poses are recentred on
//! their average pose. Then `near = 0.9 * min bound`, `far = max bound`, and
//! the box holds the camera centres and the points at depths `near` and
//! `far` along every camera's four corner rays, grown by 5% of its size on
//! each side. Every 8th image (index % 8 == 0) is held out as `val` and
//! `test`.

use std::path::{Path, PathBuf};

use super::images::{decode_all, list_images};
use super::npy::{NpyArray, parse_npy};
use super::validate::{check_pose, check_shared_size, unsplit};
use super::{Dataset, DatasetError, DatasetFormat, Frame, LoadOptions};
use crate::engine::geometry::camera::{Camera, Distortion};
use crate::engine::geometry::math::{Aabb, Vec3};

/// Image folders in order of preference.
pub const IMAGE_DIRS: [&str; 4] = ["images_8", "images_4", "images_2", "images"];
/// NeRF's `bd_factor`: the nearest bound ends up at `1 / BD_FACTOR`.
pub const BD_FACTOR: f64 = 0.75;
/// How much the box grows on each side, relative to its size.
pub const BOX_MARGIN: f32 = 0.05;

type Pose = [[f64; 4]; 3];

pub fn load(root: &Path, opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    let npy_path = root.join("poses_bounds.npy");
    let invalid = |message: String| DatasetError::Invalid { path: npy_path.clone(), message };
    let bytes = std::fs::read(&npy_path).map_err(|e| DatasetError::Io { path: npy_path.clone(), source: e })?;
    let arr = parse_npy(&bytes, &npy_path)?;
    let n = match arr.shape[..] {
        [0, 17] => return Err(invalid("no rows: the dataset has no frames".into())),
        [n, 17] => n,
        _ => return Err(invalid(format!("shape {:?}, expected (N, 17)", arr.shape))),
    };

    // Image folder and files.
    let dir = IMAGE_DIRS.iter().map(|d| root.join(d)).find(|p| p.is_dir()).ok_or_else(|| DatasetError::Invalid {
        path: root.to_path_buf(),
        message: format!("no image folder (looked for {})", IMAGE_DIRS.join(", ")),
    })?;
    let files = list_images(&dir)?;
    if files.len() != n {
        return Err(DatasetError::Invalid {
            path: dir.clone(),
            message: format!("{} images (png/jpg/jpeg) but poses_bounds.npy has {n} rows", files.len()),
        });
    }

    let Rows { mut poses, hwf, near: bmin, far: bmax } = read_rows(&arr, n, &npy_path)?;
    let sc = 1.0 / (bmin * BD_FACTOR);
    for p in &mut poses {
        for r in p.iter_mut() {
            r[3] *= sc;
        }
    }
    let (bmin, bmax) = (bmin * sc, bmax * sc);
    let poses = recenter(&poses)
        .ok_or_else(|| invalid("cannot recentre the poses: the average camera orientation is degenerate".into()))?;

    let (frames, extra_warnings) = frames(files, &poses, &hwf, &npy_path)?;
    check_shared_size(frames.iter().map(|f| (f.path.as_path(), f.image.width, f.image.height, false)))?;

    let near = (0.9 * bmin) as f32;
    let far = bmax as f32;
    let aabb = frustum_box(&frames, near, far);
    if !(aabb.min.is_finite() && aabb.max.is_finite() && near > 0.0 && far > near) {
        return Err(invalid(format!("degenerate scene bounds (near {near}, far {far})")));
    }
    Ok(unsplit(DatasetFormat::Llff, root, frames, (near, far, aabb), opts.background, extra_warnings))
}

/// The image files of `dir` sorted by name.
/// The poses (OpenGL convention), raw `[H, W, focal]` and the bounds of
/// every row of `poses_bounds.npy`.
struct Rows {
    poses: Vec<Pose>,
    hwf: Vec<(f64, f64, f64)>,
    near: f64,
    far: f64,
}

fn read_rows(arr: &NpyArray, n: usize, npy_path: &Path) -> Result<Rows, DatasetError> {
    let invalid = |message: String| DatasetError::Invalid { path: npy_path.to_path_buf(), message };
    let mut rows =
        Rows { poses: Vec::with_capacity(n), hwf: Vec::with_capacity(n), near: f64::INFINITY, far: f64::NEG_INFINITY };
    for i in 0..n {
        let row = arr.row(i).ok_or_else(|| invalid(format!("row {i} is missing")))?;
        let (pose, h, w, f, b0, b1) = parse_row(row).ok_or_else(|| invalid(format!("row {i} is short")))?;
        check_pose(&pose, npy_path, i)?;
        if !(h > 0.0 && w > 0.0 && f > 0.0 && h.is_finite() && w.is_finite() && f.is_finite()) {
            return Err(invalid(format!("row {i}: [H, W, focal] = [{h}, {w}, {f}] is not positive")));
        }
        if !(b0 > 0.0 && b1 >= b0 && b1.is_finite()) {
            return Err(invalid(format!("row {i}: bounds [{b0}, {b1}] are not 0 < near <= far")));
        }
        rows.near = rows.near.min(b0);
        rows.far = rows.far.max(b1);
        rows.poses.push(pose);
        rows.hwf.push((h, w, f));
    }
    Ok(rows)
}

/// The frames of the image `files` with their (recentred) `poses`: the
/// focal scales with each image's width; a first aspect-ratio mismatch
/// with `hwf` is returned as a warning.
fn frames(
    files: Vec<PathBuf>,
    poses: &[Pose],
    hwf: &[(f64, f64, f64)],
    npy_path: &Path,
) -> Result<(Vec<Frame>, Vec<String>), DatasetError> {
    let paths: Vec<(PathBuf, PathBuf)> = files.into_iter().map(|p| (p, npy_path.to_path_buf())).collect();
    let images = decode_all(&paths)?;
    let mut frames = Vec::with_capacity(paths.len());
    let mut warnings = Vec::new();
    for (i, (image, (path, _))) in images.into_iter().zip(paths).enumerate() {
        let (h, w, f) = hwf[i];
        let (iw, ih) = (image.width, image.height);
        let fx = (f * iw as f64 / w) as f32;
        if (ih as f64 / iw as f64 - h / w).abs() > 0.01 * (h / w) && warnings.is_empty() {
            warnings.push(format!(
                "{}: aspect ratio {iw}x{ih} differs from poses_bounds.npy ({w}x{h}); focal scaled by width",
                path.display()
            ));
        }
        let c2w = check_pose(&poses[i], npy_path, i)?;
        let camera = Camera {
            width: iw,
            height: ih,
            fx,
            fy: fx,
            cx: 0.5 * iw as f32,
            cy: 0.5 * ih as f32,
            distortion: Distortion::default(),
            c2w,
        };
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        frames.push(Frame { name, path, camera, image, mask: None });
    }
    Ok((frames, warnings))
}

/// Splits one row into the pose (reordered to OpenGL axes), `H`, `W`,
/// `focal` and the two bounds.
fn parse_row(row: &[f64]) -> Option<(Pose, f64, f64, f64, f64, f64)> {
    if row.len() < 17 {
        return None;
    }
    let m = |r: usize, c: usize| row[r * 5 + c];
    let mut pose = [[0.0; 4]; 3];
    for (r, out) in pose.iter_mut().enumerate() {
        // [down, right, backwards] -> [right, up, backwards].
        *out = [m(r, 1), -m(r, 0), m(r, 2), m(r, 3)];
    }
    Some((pose, m(0, 4), m(1, 4), m(2, 4), row[15], row[16]))
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn normalize(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (n.is_finite() && n > 1e-12).then(|| [v[0] / n, v[1] / n, v[2] / n])
}
fn col(p: &Pose, c: usize) -> [f64; 3] {
    [p[0][c], p[1][c], p[2][c]]
}

/// NeRF's `poses_avg`: centre = mean position, z = normalised sum of the
/// z axes, y from the summed up vectors (`viewmatrix`).
fn poses_avg(poses: &[Pose]) -> Option<Pose> {
    let mut centre = [0.0; 3];
    let (mut z, mut up) = ([0.0; 3], [0.0; 3]);
    for p in poses {
        for k in 0..3 {
            centre[k] += p[k][3];
            z[k] += p[k][2];
            up[k] += p[k][1];
        }
    }
    let n = poses.len() as f64;
    let centre = centre.map(|c| c / n);
    let z = normalize(z)?;
    let x = normalize(cross(up, z))?;
    let y = normalize(cross(z, x))?;
    Some([[x[0], y[0], z[0], centre[0]], [x[1], y[1], z[1], centre[1]], [x[2], y[2], z[2], centre[2]]])
}

/// NeRF's `recenter_poses`: every pose expressed in the frame of the average
/// pose (`inv(avg) @ pose`). The average is a rigid transform, so its
/// inverse is `[R^T | -R^T t]`.
fn recenter(poses: &[Pose]) -> Option<Vec<Pose>> {
    let avg = poses_avg(poses)?;
    let t = col(&avg, 3);
    Some(
        poses
            .iter()
            .map(|p| {
                let mut out = [[0.0; 4]; 3];
                for c in 0..4 {
                    let v = if c == 3 { sub(col(p, 3), t) } else { col(p, c) };
                    for (r, row) in out.iter_mut().enumerate() {
                        // (R^T v)[r] = column r of R dotted with v.
                        row[c] = avg[0][r] * v[0] + avg[1][r] * v[1] + avg[2][r] * v[2];
                    }
                }
                out
            })
            .collect(),
    )
}

/// Bounding box of the camera centres and the points at z-depths `near` and
/// `far` along each camera's four corner rays, grown by [`BOX_MARGIN`].
fn frustum_box(frames: &[Frame], near: f32, far: f32) -> Aabb {
    let mut lo = Vec3::splat(f32::INFINITY);
    let mut hi = Vec3::splat(f32::NEG_INFINITY);
    for f in frames {
        let c = &f.camera;
        let o = c.origin();
        lo = lo.min(o);
        hi = hi.max(o);
        for (u, v) in [(0.0, 0.0), (c.width as f32, 0.0), (0.0, c.height as f32), (c.width as f32, c.height as f32)] {
            let d = c.rotate(Vec3::new((u - c.cx) / c.fx, -(v - c.cy) / c.fy, -1.0));
            for depth in [near, far] {
                let p = o + d * depth;
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
    }
    let m = (hi - lo) * BOX_MARGIN;
    Aabb { min: lo - m, max: hi + m }
}

#[cfg(test)]
mod tests {
    use super::super::npy::npy_bytes;
    use super::super::testutil::*;
    use super::*;

    /// A poses_bounds row from a raw LLFF rotation (columns down, right,
    /// back), translation, [H, W, focal] and bounds.
    fn row(cols: [[f64; 3]; 3], t: [f64; 3], hwf: [f64; 3], b: [f64; 2]) -> Vec<f64> {
        let mut r = Vec::new();
        for k in 0..3 {
            r.extend_from_slice(&[cols[0][k], cols[1][k], cols[2][k], t[k], hwf[k]]);
        }
        r.extend_from_slice(&b);
        r
    }

    /// Raw LLFF columns that become the identity rotation after the reorder:
    /// right = col1 = +x, up = -col0 = +y, back = col2 = +z.
    const IDENT: [[f64; 3]; 3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];

    fn write_llff(root: &Path, dir: &str, rows: &[Vec<f64>], w: u32, h: u32) {
        for i in 0..rows.len() {
            write_png(&root.join(dir).join(format!("image{i:03}.png")), w, h, false);
        }
        let data: Vec<f64> = rows.iter().flatten().copied().collect();
        std::fs::write(root.join("poses_bounds.npy"), npy_bytes(&[rows.len(), 17], &data, 1)).unwrap();
    }

    #[test]
    fn llff_reorder_axes() {
        // Raw columns down = +x, right = +y, back = +z.
        let r =
            row([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [1.0, 2.0, 3.0], [30.0, 40.0, 50.0], [2.0, 8.0]);
        let (p, h, w, f, b0, b1) = parse_row(&r).unwrap();
        // New columns: right = old col1, up = -old col0, back = old col2.
        assert_eq!(p, [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]]);
        assert_eq!((h, w, f, b0, b1), (30.0, 40.0, 50.0, 2.0, 8.0));
        assert!(parse_row(&r[..16]).is_none());
        // Recentring two cameras with that rotation gives identity rotations
        // and positions relative to their mean.
        let mut q = p;
        q[0][3] = 3.0;
        let rc = recenter(&[p, q]).unwrap();
        for m in &rc {
            for (a, row) in m.iter().enumerate() {
                for (b, v) in row[..3].iter().enumerate() {
                    assert!((v - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12);
                }
            }
        }
        // World x offset of +-1 becomes -+1 along the average camera's y
        // (its y axis is world -x).
        assert!((rc[0][1][3] - 1.0).abs() < 1e-12 && (rc[1][1][3] + 1.0).abs() < 1e-12);
        assert!(rc[0][0][3].abs() < 1e-12 && rc[0][2][3].abs() < 1e-12);
    }

    #[test]
    fn llff_hand_computed_example() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let hwf = [30.0, 40.0, 50.0];
        let rows = vec![row(IDENT, [3.0, 0.0, 0.0], hwf, [2.0, 8.0]), row(IDENT, [0.0, 6.0, 0.0], hwf, [4.0, 10.0])];
        write_llff(root, "images_4", &rows, 4, 3);
        // A less preferred folder is ignored; a non-image file too.
        write_png(&root.join("images/zzz.png"), 8, 6, false);
        std::fs::write(root.join("images_4/notes.txt"), "x").unwrap();
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        assert_eq!(ds.format, DatasetFormat::Llff);
        assert_eq!(ds.frames.len(), 2);
        assert_eq!((ds.val.clone(), ds.test.clone(), ds.train.clone()), (vec![0], vec![0], vec![1]));
        let c0 = &ds.frames[0].camera;
        // focal 50 at W = 40 -> 5 at 4 pixels wide.
        assert_eq!((c0.width, c0.height, c0.fx, c0.fy, c0.cx, c0.cy), (4, 3, 5.0, 5.0, 2.0, 1.5));
        assert_eq!(ds.frames[1].name, "image001");
        assert_eq!(ds.frames[1].path, root.join("images_4/image001.png"));
        // sc = 1 / (2 * 0.75) = 2/3: positions (2, 0, 0) and (0, 4, 0), mean
        // (1, 2, 0), so recentred (1, -2, 0) and (-1, 2, 0).
        let want = [Vec3::new(1.0, -2.0, 0.0), Vec3::new(-1.0, 2.0, 0.0)];
        for (f, w) in ds.frames.iter().zip(want) {
            assert!((f.camera.origin() - w).norm() < 1e-5, "{:?}", f.camera.origin());
            assert!((f.camera.c2w[0][0] - 1.0).abs() < 1e-6 && (f.camera.c2w[2][2] - 1.0).abs() < 1e-6);
        }
        assert!((ds.near - 0.9 * 2.0 * 2.0 / 3.0).abs() < 1e-5);
        assert!((ds.far - 10.0 * 2.0 / 3.0).abs() < 1e-5);
        // Box: cameras look down -z; corner rays at depth far reach
        // z = -far and x = cam.x +- far * 2 / 5.
        let far = ds.far;
        let (lo_x, hi_x) = (-1.0 - far * 0.4, 1.0 + far * 0.4);
        let m = (hi_x - lo_x) * BOX_MARGIN;
        assert!((ds.aabb.min.x - (lo_x - m)).abs() < 1e-4 && (ds.aabb.max.x - (hi_x + m)).abs() < 1e-4);
        assert!((ds.aabb.max.z - far * BOX_MARGIN).abs() < 1e-4);
        assert!((ds.aabb.min.z - (-far - far * BOX_MARGIN)).abs() < 1e-4);
        assert!(ds.warnings.iter().any(|w| w.contains("training view")));
    }

    #[test]
    fn llff_folder_preference_and_holdout() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let rows: Vec<Vec<f64>> =
            (0..17).map(|i| row(IDENT, [i as f64 * 0.1, 0.0, 0.0], [24.0, 32.0, 40.0], [1.0, 5.0])).collect();
        write_llff(root, "images", &rows, 8, 6);
        write_llff(root, "images_2", &rows, 4, 3);
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        assert_eq!(ds.frames[0].image.width, 4);
        assert_eq!(ds.frames[0].camera.fx, 5.0);
        assert_eq!(ds.test, vec![0, 8, 16]);
        assert_eq!(ds.train.len(), 14);
        // JPEG with an upper-case extension counts; sorted by name.
        std::fs::remove_file(root.join("images_2/image003.png")).unwrap();
        write_jpg(&root.join("images_2/image003.JPG"), 4, 3);
        let ds = Dataset::load(root, &LoadOptions::default()).unwrap();
        assert_eq!(ds.frames[3].name, "image003");
        assert_eq!(ds.frames[4].name, "image004");
    }

    #[test]
    fn llff_errors() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let hwf = [30.0, 40.0, 50.0];
        let good: Vec<Vec<f64>> = (0..3).map(|i| row(IDENT, [i as f64, 0.0, 0.0], hwf, [2.0, 8.0])).collect();
        write_llff(root, "images_8", &good, 4, 3);
        let load = || Dataset::load(root, &LoadOptions::default());
        let npy = root.join("poses_bounds.npy");
        assert!(load().is_ok());

        // NaN pose names the row.
        let mut bad = good.clone();
        bad[1][3] = f64::NAN;
        write_llff(root, "images_8", &bad, 4, 3);
        match load() {
            Err(DatasetError::BadPose { frame: 1, message, path }) => {
                assert_eq!((message.as_str(), path), ("non-finite pose", npy.clone()))
            }
            other => panic!("{other:?}"),
        }
        // Non-rigid pose.
        let mut bad = good.clone();
        bad[2][0] = 0.5;
        write_llff(root, "images_8", &bad, 4, 3);
        assert!(matches!(load(), Err(DatasetError::BadPose { frame: 2, .. })));
        // Bad bounds and intrinsics.
        let mut bad = good.clone();
        bad[0][15] = 0.0;
        write_llff(root, "images_8", &bad, 4, 3);
        assert!(matches!(load(), Err(DatasetError::Invalid { message, .. }) if message.contains("bounds")));
        let mut bad = good.clone();
        bad[0][9] = -1.0;
        write_llff(root, "images_8", &bad, 4, 3);
        assert!(matches!(load(), Err(DatasetError::Invalid { .. })));

        // Truncated and garbage npy.
        write_llff(root, "images_8", &good, 4, 3);
        let bytes = std::fs::read(&npy).unwrap();
        std::fs::write(&npy, &bytes[..bytes.len() - 5]).unwrap();
        assert!(
            matches!(load(), Err(DatasetError::Invalid { message, path }) if message.contains("truncated") && path == npy)
        );
        std::fs::write(&npy, b"garbage garbage garbage").unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { .. })));
        std::fs::write(&npy, b"").unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { .. })));
        // Wrong shape, empty array.
        std::fs::write(&npy, npy_bytes(&[3, 15], &[0.0; 45], 1)).unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { message, .. }) if message.contains("(N, 17)")));
        std::fs::write(&npy, npy_bytes(&[0, 17], &[], 1)).unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { message, .. }) if message.contains("no rows")));

        // Image count must match the rows; image sizes must agree.
        write_llff(root, "images_8", &good, 4, 3);
        std::fs::remove_file(root.join("images_8/image002.png")).unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { message, .. }) if message.contains("2 images")));
        write_png(&root.join("images_8/image002.png"), 5, 3, false);
        assert!(matches!(load(), Err(DatasetError::SizeMismatch { got_w: 5, want_w: 4, .. })));
        std::fs::write(root.join("images_8/image002.png"), b"corrupt").unwrap();
        assert!(matches!(load(), Err(DatasetError::BadImage { .. })));

        // No image folder at all.
        std::fs::remove_dir_all(root.join("images_8")).unwrap();
        assert!(matches!(load(), Err(DatasetError::Invalid { message, .. }) if message.contains("images_8")));
    }

    #[test]
    fn unknown_format_and_missing_root() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(Dataset::load(dir.path(), &LoadOptions::default()), Err(DatasetError::UnknownFormat(_))));
        std::fs::write(dir.path().join("transforms_train.txt"), "{}").unwrap();
        assert!(matches!(Dataset::load(dir.path(), &LoadOptions::default()), Err(DatasetError::UnknownFormat(_))));
        assert!(matches!(
            Dataset::load(&dir.path().join("nope"), &LoadOptions::default()),
            Err(DatasetError::NotFound(_))
        ));
    }
}
