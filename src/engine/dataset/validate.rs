//! Pose and image validation shared by the loaders, and the non-fatal
//! warnings attached to a loaded dataset.

use std::path::Path;

use super::{Dataset, DatasetError, DatasetFormat, Frame, MaskUse, Split};
use crate::engine::geometry::math::{Aabb, Vec3};

/// Largest allowed deviation of any entry of `R^T R` from the identity.
pub const ORTHONORMAL_TOLERANCE: f64 = 1e-3;

/// Fewer training views than this produce a warning.
pub const MIN_TRAIN_VIEWS: usize = 10;

/// Checks a camera-to-world pose (rows of a 3x4 matrix, f64) and converts it
/// to f32: every entry finite, rotation orthonormal within
/// [`ORTHONORMAL_TOLERANCE`] and a proper rotation (determinant > 0).
/// `path` is the file the pose came from, `frame` its index there.
pub(super) fn check_pose(m: &[[f64; 4]; 3], path: &Path, frame: usize) -> Result<[[f32; 4]; 3], DatasetError> {
    let bad = |message: String| DatasetError::BadPose { path: path.to_path_buf(), frame, message };
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad("non-finite pose".into()));
    }
    let mut dev = 0.0f64;
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|r| m[r][a] * m[r][b]).sum();
            let want = if a == b { 1.0 } else { 0.0 };
            dev = dev.max((dot - want).abs());
        }
    }
    if dev.is_nan() || dev >= ORTHONORMAL_TOLERANCE {
        return Err(bad(format!("rotation not orthonormal (max deviation {dev:.3})")));
    }
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if det.is_nan() || det <= 0.0 {
        return Err(bad(format!("rotation is a reflection (determinant {det:.3})")));
    }
    let c2w = m.map(|row| row.map(|v| v as f32));
    if c2w.iter().flatten().any(|v| !v.is_finite()) {
        return Err(bad("pose does not fit in f32".into()));
    }
    Ok(c2w)
}

/// Checks that images which share intrinsics share one size: each entry is
/// `(image path, width, height, has per-frame intrinsics)`. Frames with
/// per-frame intrinsics may have any size; all others must match the first
/// of them.
pub(super) fn check_shared_size<'a>(
    frames: impl IntoIterator<Item = (&'a Path, u32, u32, bool)>,
) -> Result<(), DatasetError> {
    let mut want: Option<(u32, u32)> = None;
    for (path, w, h, per_frame) in frames {
        if per_frame {
            continue;
        }
        match want {
            None => want = Some((w, h)),
            Some((ww, wh)) if (ww, wh) != (w, h) => {
                return Err(DatasetError::SizeMismatch {
                    path: path.to_path_buf(),
                    got_w: w,
                    got_h: h,
                    want_w: ww,
                    want_h: wh,
                });
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// Non-fatal observations about a loaded dataset.
/// Every `HOLDOUT`-th frame of a format without splits (LLFF, instant-ngp,
/// COLMAP) is held out for evaluation (NeRF's `llffhold`).
pub(super) const HOLDOUT: usize = 8;

/// A dataset of a format without splits: every [`HOLDOUT`]-th frame held out
/// (as both `val` and `test`), the general warnings and then the loader's.
pub(super) fn unsplit(
    format: DatasetFormat,
    root: &Path,
    frames: Vec<Frame>,
    (near, far, aabb): (f32, f32, Aabb),
    background: [f32; 3],
    extra_warnings: Vec<String>,
) -> Dataset {
    let (held, train): (Vec<usize>, Vec<usize>) = (0..frames.len()).partition(|i| i % HOLDOUT == 0);
    let mut ds = Dataset {
        format,
        root: root.to_path_buf(),
        frames,
        train,
        val: held.clone(),
        test: held,
        near,
        far,
        aabb,
        background,
        warnings: Vec::new(),
        masks: MaskUse::Off,
        mask_folder: None,
    };
    ds.warnings = warnings(&ds);
    ds.warnings.extend(extra_warnings);
    ds
}

pub(super) fn warnings(ds: &Dataset) -> Vec<String> {
    let mut out = Vec::new();
    if ds.train.len() < MIN_TRAIN_VIEWS {
        out.push(format!(
            "only {} training view{} (at least {MIN_TRAIN_VIEWS} recommended): novel views will be poorly constrained",
            ds.train.len(),
            if ds.train.len() == 1 { "" } else { "s" }
        ));
    }
    // Cameras that all look at the box from within a narrow cone (forward
    // facing captures) leave the far side of the scene unobserved.
    let centre = ds.aabb.centre();
    let dirs: Vec<Vec3> = ds
        .split(Split::Train)
        .iter()
        .filter_map(|&i| ds.frames.get(i))
        .filter_map(|f| (f.camera.origin() - centre).normalized())
        .collect();
    if dirs.len() >= 2 {
        let mean = dirs.iter().fold(Vec3::splat(0.0), |a, &d| a + d);
        if let Some(mean) = mean.normalized() {
            let min_cos = dirs.iter().map(|d| d.dot(mean)).fold(f32::INFINITY, f32::min);
            // All within 45 degrees of the mean direction.
            if min_cos > std::f32::consts::FRAC_1_SQRT_2 {
                let spread = min_cos.clamp(-1.0, 1.0).acos().to_degrees();
                out.push(format!(
                    "training cameras do not surround the scene (all within {spread:.0} degrees of one direction from the box centre): the far side is unobserved"
                ));
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const ID: [[f64; 4]; 3] = [[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]];

    fn msg(r: Result<[[f32; 4]; 3], DatasetError>, want_frame: usize) -> String {
        match r {
            Err(DatasetError::BadPose { frame, message, .. }) => {
                assert_eq!(frame, want_frame);
                message
            }
            other => panic!("expected BadPose, got {other:?}"),
        }
    }

    #[test]
    fn pose_checks() {
        let p = Path::new("t.json");
        assert_eq!(check_pose(&ID, p, 0).unwrap()[1][3], 2.0);
        let mut nan = ID;
        nan[1][3] = f64::NAN;
        assert_eq!(msg(check_pose(&nan, p, 3), 3), "non-finite pose");
        let mut inf = ID;
        inf[0][0] = f64::INFINITY;
        assert_eq!(msg(check_pose(&inf, p, 1), 1), "non-finite pose");
        let mut scaled = ID;
        scaled[0][0] = 1.2;
        let m = msg(check_pose(&scaled, p, 5), 5);
        assert!(m.contains("not orthonormal") && m.contains("0.44"), "{m}");
        let mut sheared = ID;
        sheared[0][1] = 0.2;
        assert!(msg(check_pose(&sheared, p, 2), 2).contains("not orthonormal"));
        let mut mirror = ID;
        mirror[2][2] = -1.0;
        assert!(msg(check_pose(&mirror, p, 0), 0).contains("reflection"));
        let mut tiny = ID;
        tiny[0][0] = 1.0 + 1e-5;
        assert!(check_pose(&tiny, p, 0).is_ok());
        let mut huge = ID;
        huge[0][3] = 1e300;
        assert!(check_pose(&huge, p, 0).is_err());
    }

    #[test]
    fn shared_size() {
        let (a, b) = (Path::new("a.png"), Path::new("b.png"));
        assert!(check_shared_size([(a, 4, 3, false), (b, 4, 3, false)]).is_ok());
        assert!(check_shared_size([(a, 4, 3, false), (b, 8, 3, true)]).is_ok());
        match check_shared_size([(a, 4, 3, false), (b, 3, 4, false)]) {
            Err(DatasetError::SizeMismatch { path, got_w: 3, got_h: 4, want_w: 4, want_h: 3 }) => {
                assert_eq!(path, b)
            }
            other => panic!("{other:?}"),
        }
    }
}
