//! Camera paths: keyframes (pose, field of view, time) interpolated into a
//! smooth fly-through. Positions and fields of view follow a Catmull-Rom
//! spline and rotations its spherical analogue, both evaluated with the
//! Barry-Goldman pyramid (three levels of linear interpolation over the
//! keyframes' own times; slerp in place of lerp for rotations). So:
//!
//! - the path passes through every keyframe exactly at its time;
//! - positions are C1 (continuous velocity) and rotations turn smoothly
//!   through keyframes, without the kinks of piecewise slerp;
//! - motion that is linear in time (a straight line at constant speed, a
//!   turn about a fixed axis at constant angular speed) is reproduced
//!   exactly, whatever the spacing of the keyframes: the end segments use
//!   phantom keyframes extrapolated from the last two, so two keyframes
//!   give a straight move and a slerp.
//!
//! Rotations are interpolated as the keyframes' quaternions signed into
//! one hemisphere, each level taking them as given: choosing the shorter
//! arc afresh at each level would make the path jump where the choice flips.

use serde::{Deserialize, Serialize};

use super::quat::Quat;

/// One keyframe: a camera-to-world pose (3x4, rows, OpenGL convention), a
/// horizontal field of view in degrees, and its time in seconds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Keyframe {
    pub c2w: [[f32; 4]; 3],
    pub fov: f32,
    pub time: f64,
}

/// Why keyframes do not make a path.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum PathError {
    #[error("a camera path needs at least one keyframe")]
    Empty,
    #[error("a camera path has at most {max} keyframes, got {got}")]
    TooMany { max: usize, got: usize },
    #[error("keyframe {index}: time {time} is not finite")]
    Time { index: usize, time: f64 },
    #[error("keyframe {index}: time {time} is not after the previous keyframe's ({previous})")]
    NotIncreasing { index: usize, time: f64, previous: f64 },
    #[error("keyframe {index}: the pose is not a rigid transform ({reason})")]
    Pose { index: usize, reason: &'static str },
    #[error("keyframe {index}: field of view {fov} is not between 1 and 179 degrees")]
    Fov { index: usize, fov: f32 },
}

/// A checked list of keyframes in time order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "Vec<Keyframe>", into = "Vec<Keyframe>")]
pub struct CameraPath {
    keys: Vec<Keyframe>,
    /// The keyframes' rotations, each in the hemisphere of the one before
    /// (q and -q are the same rotation; interpolation needs one of them).
    #[serde(skip)]
    rotations: Vec<Quat>,
}

/// Most keyframes in one path.
pub const MAX_KEYFRAMES: usize = 10_000;

impl TryFrom<Vec<Keyframe>> for CameraPath {
    type Error = PathError;
    fn try_from(keys: Vec<Keyframe>) -> Result<Self, PathError> {
        CameraPath::new(keys)
    }
}

impl From<CameraPath> for Vec<Keyframe> {
    fn from(p: CameraPath) -> Self {
        p.keys
    }
}

/// Checks that the rotation part of `m` is orthonormal with determinant 1.
fn rotation_of(m: &[[f32; 4]; 3]) -> Result<[[f64; 3]; 3], &'static str> {
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err("a number is not finite");
    }
    let r = [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[i][j] as f64));
    for a in 0..3 {
        for b in 0..3 {
            let dot: f64 = (0..3).map(|k| r[k][a] * r[k][b]).sum();
            if (dot - if a == b { 1.0 } else { 0.0 }).abs() > 1e-3 {
                return Err("the rotation is not orthonormal");
            }
        }
    }
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    if det < 0.0 {
        return Err("the rotation is a reflection");
    }
    Ok(r)
}

impl CameraPath {
    /// Checks the keyframes: at least one, at most [`MAX_KEYFRAMES`], finite
    /// strictly increasing times, rigid poses, fields of view in (1, 179).
    pub fn new(keys: Vec<Keyframe>) -> Result<Self, PathError> {
        if keys.is_empty() {
            return Err(PathError::Empty);
        }
        if keys.len() > MAX_KEYFRAMES {
            return Err(PathError::TooMany { max: MAX_KEYFRAMES, got: keys.len() });
        }
        let mut rotations: Vec<Quat> = Vec::with_capacity(keys.len());
        for (index, k) in keys.iter().enumerate() {
            if !k.time.is_finite() {
                return Err(PathError::Time { index, time: k.time });
            }
            if index > 0 && k.time <= keys[index - 1].time {
                return Err(PathError::NotIncreasing { index, time: k.time, previous: keys[index - 1].time });
            }
            if !(k.fov.is_finite() && k.fov > 1.0 && k.fov < 179.0) {
                return Err(PathError::Fov { index, fov: k.fov });
            }
            let q = Quat::from_matrix(rotation_of(&k.c2w).map_err(|reason| PathError::Pose { index, reason })?);
            let q = match rotations.last() {
                Some(p) if p.dot(q) < 0.0 => q.negated(),
                _ => q,
            };
            rotations.push(q);
        }
        Ok(CameraPath { keys, rotations })
    }

    /// Keyframes at times 0, 1, 2, ... seconds.
    pub fn evenly_timed(poses: Vec<([[f32; 4]; 3], f32)>) -> Result<Self, PathError> {
        Self::new(poses.into_iter().enumerate().map(|(i, (c2w, fov))| Keyframe { c2w, fov, time: i as f64 }).collect())
    }

    pub fn keyframes(&self) -> &[Keyframe] {
        &self.keys
    }

    /// The first and last keyframe's times.
    pub fn span(&self) -> (f64, f64) {
        (self.keys[0].time, self.keys[self.keys.len() - 1].time)
    }

    /// The times of `frames` frames spread evenly from the first keyframe
    /// to the last, both included (one frame: the first keyframe).
    pub fn frame_time(&self, k: u32, frames: u32) -> f64 {
        let (a, b) = self.span();
        if frames <= 1 { a } else { a + (b - a) * k as f64 / (frames - 1) as f64 }
    }

    /// The pose and horizontal field of view at time `t` (clamped to the
    /// keyframes' span).
    pub fn at(&self, t: f64) -> ([[f32; 4]; 3], f32) {
        let n = self.keys.len();
        let (a, b) = self.span();
        let t = t.clamp(a, b);
        if n == 1 {
            return (self.keys[0].c2w, self.keys[0].fov);
        }
        // The segment [i, i + 1] holding t, and its neighbours (phantoms
        // past the ends, extrapolated linearly from the end segment).
        let i = self.keys.partition_point(|k| k.time <= t).clamp(1, n - 1) - 1;
        let key = |j: isize| -> (f64, [f64; 3], Quat, f64) {
            let at = |j: usize| {
                let k = &self.keys[j];
                (k.time, [k.c2w[0][3], k.c2w[1][3], k.c2w[2][3]].map(f64::from), self.rotations[j], k.fov as f64)
            };
            if j < 0 {
                let ((t0, p0, q0, f0), (t1, p1, q1, f1)) = (at(0), at(1));
                (2.0 * t0 - t1, [0, 1, 2].map(|c| 2.0 * p0[c] - p1[c]), q0.slerp_as_given(q1, -1.0), 2.0 * f0 - f1)
            } else if j as usize >= n {
                let ((t0, p0, q0, f0), (t1, p1, q1, f1)) = (at(n - 2), at(n - 1));
                (2.0 * t1 - t0, [0, 1, 2].map(|c| 2.0 * p1[c] - p0[c]), q0.slerp_as_given(q1, 2.0), 2.0 * f1 - f0)
            } else {
                at(j as usize)
            }
        };
        let ks = [-1isize, 0, 1, 2].map(|d| key(i as isize + d));
        let times = ks.map(|k| k.0);
        let position = [0, 1, 2].map(|c| barry_goldman(ks.map(|k| k.1[c]), times, t, |x, y, u| x + (y - x) * u));
        let rotation = barry_goldman(ks.map(|k| k.2), times, t, |x: Quat, y, u| x.slerp_as_given(y, u));
        let fov = barry_goldman(ks.map(|k| k.3), times, t, |x, y, u| x + (y - x) * u).clamp(1.5, 178.5);
        let r = rotation.to_matrix();
        let c2w = [0, 1, 2].map(|row| [r[row][0], r[row][1], r[row][2], position[row]].map(|v| v as f32));
        (c2w, fov as f32)
    }
}

/// The Catmull-Rom value at `t` in `[t[1], t[2]]` of four values at times
/// `t`, by the Barry-Goldman pyramid with `lerp(a, b, u)` as the one
/// interpolation (`u` = 0 gives `a`, 1 gives `b`; any real `u`).
fn barry_goldman<T: Copy>(p: [T; 4], t: [f64; 4], x: f64, lerp: impl Fn(T, T, f64) -> T) -> T {
    let u = |a: usize, b: usize| (x - t[a]) / (t[b] - t[a]);
    let a1 = lerp(p[0], p[1], u(0, 1));
    let a2 = lerp(p[1], p[2], u(1, 2));
    let a3 = lerp(p[2], p[3], u(2, 3));
    let b1 = lerp(a1, a2, u(0, 2));
    let b2 = lerp(a2, a3, u(1, 3));
    lerp(b1, b2, u(1, 2))
}

#[cfg(test)]
#[path = "path_tests.rs"]
mod tests;
