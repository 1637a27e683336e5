//! Where a capture's cameras look, and from how far: the point every orbit
//! and default view turns around.
//!
//! The centre of a dataset's box is a poor centre for a real capture: a
//! COLMAP box spans the room's sparse points, and the object the user walked
//! around is rarely in its middle. The cameras say where the subject is: it
//! is the point nearest to all their optical axes (the least-squares point,
//! as multinerf's `focus_point_fn`). For a forward-facing capture (axes
//! nearly parallel) that point is ill-defined, and the focus is placed on
//! the mean axis at the depth the NeRF paper's spiral path focuses on.

use crate::engine::geometry::align::jacobi_eigen;
use crate::engine::geometry::camera::Orbit;
use crate::engine::geometry::math::Vec3;

/// Axes spread less than this (degrees from their mean) make a capture
/// forward-facing (LLFF's fern: 9.5; a hand-held walk-around such as fox: 52).
pub const FORWARD_FACING_SPREAD_DEG: f32 = 30.0;

/// Cameras that leave a gap of more than this (degrees of azimuth around
/// the focus) saw the subject from one side only: a full orbit would show
/// the side no photo saw, so default videos sweep across the cameras' arc
/// ([`CameraRig::arc_deg`]). Fox's hand-held cameras span 91 degrees (a gap
/// of 269); gold_cape's walk-around and ethiopian_head's turntable leave no
/// gap this wide.
pub const ARC_GAP_DEG: f32 = 120.0;

/// How the focus was found.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FocusFrom {
    /// The point nearest to all optical axes, in front of the cameras.
    Axes,
    /// The mean axis at the focus depth of the near and far bounds (axes
    /// too parallel to meet).
    FocusDepth,
    /// The centre of the dataset's box (neither of the above was usable).
    Box,
}

/// The training cameras' rig: the focus, the distance and direction they
/// see it from, and the frame of a small spiral for forward-facing captures.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraRig {
    /// The point the cameras look at (world units).
    pub focus: [f32; 3],
    pub focus_from: FocusFrom,
    /// Median distance of the cameras from the focus.
    pub radius: f32,
    /// Unit up vector: the cameras' mean up, or the normal of the plane they
    /// lie in when they form a ring around the focus.
    pub up: [f32; 3],
    /// Mean angle of the cameras above the focus's horizon, degrees.
    pub elevation_deg: f32,
    /// Unit vector perpendicular to `up` pointing from the focus towards the
    /// cameras (their mean direction, or the first camera's for a full
    /// ring): the direction of azimuth 0.
    pub front: [f32; 3],
    /// Largest angle between an optical axis and the mean axis, degrees.
    pub spread_deg: f32,
    /// Whether all cameras look the same way (`spread_deg` under 30).
    pub forward_facing: bool,
    /// A spiral through the cameras' own spread, around the mean camera.
    pub spiral: Spiral,
    /// The first training camera's image size and horizontal field of view
    /// (degrees); 0 when made from poses alone.
    #[serde(default)]
    pub image: [u32; 2],
    #[serde(default)]
    pub fov_deg: f32,
    /// Every training camera's centre and optical axis, by dataset frame
    /// index: a new view takes the appearance of the nearest one
    /// ([`CameraRig::nearest_frame`]). Empty in checkpoints from before it
    /// existed.
    #[serde(default)]
    pub frames: Vec<RigFrame>,
    /// When the cameras saw the subject from one side (they leave a gap of
    /// more than [`ARC_GAP_DEG`] around it): the azimuths they span,
    /// degrees, `[start, end]` with `start < end`, in the convention of
    /// [`CameraRig::orbit`] (0 towards `front`, increasing towards `up x
    /// front`). `None` when they go all around, for forward-facing captures
    /// (their default is the spiral), and in checkpoints from before it
    /// existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_deg: Option<[f32; 2]>,
}

/// A training camera as the rig keeps it (world units).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RigFrame {
    /// The dataset frame index (the image index training rays carry).
    pub image: u32,
    pub centre: [f32; 3],
    /// Unit optical axis (the direction the camera looks).
    pub axis: [f32; 3],
}

/// A closed spiral of cameras in the plane of the mean training camera,
/// looking at a focus: the default path for forward-facing captures, which
/// a full orbit would show from behind.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Spiral {
    /// The mean camera's centre, and its right and up axes (unit).
    pub centre: [f32; 3],
    pub right: [f32; 3],
    pub up: [f32; 3],
    /// 90th percentile of the cameras' offsets from `centre` along `right`
    /// and `up`: the spiral's half-widths.
    pub half_widths: [f32; 2],
}

impl Spiral {
    /// `n + 1` poses (the last equals the first) around the spiral, each
    /// looking at `focus`.
    pub fn poses(&self, focus: [f32; 3], n: usize) -> Vec<[[f32; 4]; 3]> {
        let n = n.max(3);
        let c = Vec3::from_array(self.centre);
        let (r, u) = (Vec3::from_array(self.right), Vec3::from_array(self.up));
        let focus = Vec3::from_array(focus);
        (0..=n)
            .filter_map(|k| {
                let th = std::f32::consts::TAU * (k % n) as f32 / n as f32;
                let eye = c + r * (self.half_widths[0] * th.cos()) + u * (self.half_widths[1] * th.sin());
                super::camera::look_at(eye, focus, u)
            })
            .collect()
    }
}

type V = [f64; 3];
/// A camera's centre, optical axis, up and right vectors.
type Cam = (V, V, V, V);

fn v(p: Vec3) -> V {
    [p.x as f64, p.y as f64, p.z as f64]
}
fn f(p: V) -> [f32; 3] {
    [p[0] as f32, p[1] as f32, p[2] as f32]
}
fn add(a: V, b: V) -> V {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: V, b: V) -> V {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: V, s: f64) -> V {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn dot(a: V, b: V) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V, b: V) -> V {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
fn norm(a: V) -> f64 {
    dot(a, a).sqrt()
}
fn unit(a: V) -> Option<V> {
    let n = norm(a);
    (n.is_finite() && n > 1e-12).then(|| scale(a, 1.0 / n))
}

/// Eigenvalues (ascending) and unit eigenvectors of a symmetric 3x3 matrix.
fn sym_eigen(a: [[f64; 3]; 3]) -> ([f64; 3], [V; 3]) {
    let (vals, q) = jacobi_eigen(a);
    let mut idx = [0, 1, 2];
    idx.sort_by(|&i, &j| vals[i].total_cmp(&vals[j]));
    (idx.map(|i| vals[i]), idx.map(|i| [q[0][i], q[1][i], q[2][i]]))
}

fn solve3(m: [[f64; 3]; 3], b: V) -> Option<V> {
    let det = dot(m[0], cross(m[1], m[2]));
    if !(det.is_finite() && det.abs() > 1e-300) {
        return None;
    }
    // Cramer's rule on the rows' cofactors (m symmetric here, but general).
    let cols = [[m[0][0], m[1][0], m[2][0]], [m[0][1], m[1][1], m[2][1]], [m[0][2], m[1][2], m[2][2]]];
    let x = dot(b, cross(cols[1], cols[2])) / det;
    let y = dot(cols[0], cross(b, cols[2])) / det;
    let z = dot(cols[0], cross(cols[1], b)) / det;
    Some([x, y, z])
}

/// The arc (degrees, `[start, end]`, `start` in (-180, 180], `end - start`
/// < 360) that a set of azimuths spans when the widest gap between
/// neighbours (around the circle) exceeds `min_gap`; `None` otherwise or for
/// fewer than 3 azimuths.
fn covered_arc(mut azimuths: Vec<f64>, min_gap: f64) -> Option<[f64; 2]> {
    azimuths.retain(|a| a.is_finite());
    if azimuths.len() < 3 {
        return None;
    }
    azimuths.sort_by(f64::total_cmp);
    let n = azimuths.len();
    // The gap after azimuth k: to the next one, or around to the first.
    let gap = |k: usize| if k + 1 < n { azimuths[k + 1] - azimuths[k] } else { azimuths[0] + 360.0 - azimuths[k] };
    let widest = (0..n).max_by(|&a, &b| gap(a).total_cmp(&gap(b)))?;
    let g = gap(widest);
    if g <= min_gap {
        return None;
    }
    let mut start = azimuths[(widest + 1) % n];
    if start > 180.0 {
        start -= 360.0;
    }
    Some([start, start + 360.0 - g])
}

fn percentile(mut xs: Vec<f64>, p: f64) -> f64 {
    if xs.is_empty() {
        return 0.0;
    }
    xs.sort_by(f64::total_cmp);
    let k = ((xs.len() - 1) as f64 * p).round() as usize;
    xs[k.min(xs.len() - 1)]
}

/// The cameras of `poses` (centre, optical axis, up, right); `None` for no
/// cameras or a non-finite pose.
fn cams_of(poses: &[[[f32; 4]; 3]]) -> Option<Vec<Cam>> {
    if poses.is_empty() {
        return None;
    }
    let col = |m: &[[f32; 4]; 3], c: usize| [m[0][c] as f64, m[1][c] as f64, m[2][c] as f64];
    let mut cams: Vec<Cam> = Vec::with_capacity(poses.len());
    for m in poses {
        let centre = col(m, 3);
        let axis = unit(scale(col(m, 2), -1.0))?;
        let up = unit(col(m, 1))?;
        let right = unit(col(m, 0))?;
        if !centre.iter().all(|x| x.is_finite()) {
            return None;
        }
        cams.push((centre, axis, up, right));
    }
    Some(cams)
}

/// The least-squares point nearest all optical axes, when it is well
/// defined (the axes are not nearly parallel) and in front of at least 90%
/// of the cameras.
fn axes_focus(cams: &[Cam]) -> Option<V> {
    let mut a = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    for (c, ax, _, _) in cams {
        let p = [
            [1.0 - ax[0] * ax[0], -ax[0] * ax[1], -ax[0] * ax[2]],
            [-ax[1] * ax[0], 1.0 - ax[1] * ax[1], -ax[1] * ax[2]],
            [-ax[2] * ax[0], -ax[2] * ax[1], 1.0 - ax[2] * ax[2]],
        ];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] += p[i][j];
            }
            b[i] += dot(p[i], *c);
        }
    }
    let (vals, _) = sym_eigen(a);
    let n = cams.len() as f64;
    solve3(a, b).filter(|f| {
        let in_front = cams.iter().filter(|(c, ax, _, _)| dot(*ax, sub(*f, *c)) > 0.0).count();
        vals[0] / vals[2].max(1e-300) >= 0.02 && in_front as f64 >= 0.9 * n
    })
}

/// Up: `mean_up` (the cameras' mean up), or the normal of the plane the
/// cameras lie in when they form a ring (four or more, nearly planar, the
/// normal within 30 degrees of `mean_up`).
fn ring_up(cams: &[Cam], c_mean: V, mean_up: V) -> V {
    if cams.len() < 4 {
        return mean_up;
    }
    let mut cov = [[0.0; 3]; 3];
    for c in cams {
        let d = sub(c.0, c_mean);
        for i in 0..3 {
            for j in 0..3 {
                cov[i][j] += d[i] * d[j];
            }
        }
    }
    let (vals, vecs) = sym_eigen(cov);
    let planar = vals[0].max(0.0).sqrt() < 0.2 * vals[1].max(0.0).sqrt();
    let normal = if dot(vecs[0], mean_up) < 0.0 { scale(vecs[0], -1.0) } else { vecs[0] };
    if planar && dot(normal, mean_up) > 30f64.to_radians().cos() { normal } else { mean_up }
}

/// The direction of azimuth 0, perpendicular to `up`: the cameras' mean
/// horizontal direction from the focus (`dirs`) when they agree on one, else
/// the first camera's, else back along the mean axis `a_mean`, else any.
fn front_of(dirs: &[V], up: V, a_mean: V) -> V {
    let horizontal = |d: V| sub(d, scale(up, dot(d, up)));
    let mean_h = dirs.iter().fold([0.0; 3], |s, d| add(s, horizontal(*d)));
    let mean_len = dirs.iter().map(|d| norm(horizontal(*d))).sum::<f64>();
    if norm(mean_h) > 0.25 * mean_len { unit(mean_h) } else { None }
        .or_else(|| dirs.first().and_then(|d| unit(horizontal(*d))))
        .or_else(|| unit(horizontal(scale(a_mean, -1.0))))
        .unwrap_or_else(|| {
            let x = if up[0].abs() > 0.9 { [0.0, 1.0, 0.0] } else { [1.0, 0.0, 0.0] };
            unit(horizontal(x)).unwrap_or([1.0, 0.0, 0.0])
        })
}

/// The frame of the small spiral a forward-facing capture's default video
/// follows: centred on the cameras' mean centre `c_mean`, in the plane
/// across the mean axis `a_mean` (right from the cameras' mean right, up
/// from both; `up` where they fail), its half-widths the 90th percentile
/// of the cameras' distances from the centre along each (at least 1% of
/// `radius`).
fn spiral_of(cams: &[Cam], c_mean: V, a_mean: V, mean_right: V, up: V, radius: f64) -> Spiral {
    let mean_up = unit(cross(scale(a_mean, -1.0), mean_right)).unwrap_or(up);
    let mean_right = cross(mean_up, scale(a_mean, -1.0));
    let along = |axis: V| percentile(cams.iter().map(|c| dot(sub(c.0, c_mean), axis).abs()).collect(), 0.9);
    let floor = 0.01 * radius.max(1e-6);
    Spiral {
        centre: f(c_mean),
        right: f(mean_right),
        up: f(mean_up),
        half_widths: [along(mean_right).max(floor) as f32, along(mean_up).max(floor) as f32],
    }
}

impl CameraRig {
    /// The rig of cameras given as camera-to-world matrices (OpenGL axes:
    /// the camera looks down -z, +y is up). `near`/`far` bound the scene
    /// depth (world units), `box_centre` is the last-resort focus. `None`
    /// for no cameras or non-finite poses.
    pub fn from_poses(poses: &[[[f32; 4]; 3]], near: f32, far: f32, box_centre: Vec3) -> Option<Self> {
        let cams = cams_of(poses)?;
        let n = cams.len() as f64;
        let mean = |sel: &dyn Fn(&Cam) -> V| cams.iter().fold([0.0; 3], |s, c| add(s, sel(c)));
        let c_mean = scale(mean(&|c| c.0), 1.0 / n);
        // Axes that cancel out (a level ring looking inwards) have no mean:
        // they spread all around.
        let a_mean_found = unit(mean(&|c| c.1));
        let a_mean = a_mean_found.unwrap_or([0.0, 0.0, -1.0]);
        let spread = match a_mean_found {
            Some(a_mean) => {
                cams.iter().map(|c| dot(c.1, a_mean).clamp(-1.0, 1.0).acos().to_degrees()).fold(0.0, f64::max)
            }
            None => 180.0,
        };

        let (focus, focus_from) = match axes_focus(&cams) {
            Some(p) => (p, FocusFrom::Axes),
            None => {
                // The NeRF spiral's focus depth: a weighted harmonic mean of
                // the bounds, nearer the far bound.
                let depth = 1.0 / (0.25 / near as f64 + 0.75 / far as f64);
                if a_mean_found.is_some() && near > 0.0 && far > near && depth.is_finite() {
                    (add(c_mean, scale(a_mean, depth)), FocusFrom::FocusDepth)
                } else {
                    (v(box_centre), FocusFrom::Box)
                }
            }
        };
        let offsets: Vec<V> = cams.iter().map(|c| sub(c.0, focus)).collect();
        let radius = percentile(offsets.iter().map(|o| norm(*o)).collect(), 0.5);

        let up = ring_up(&cams, c_mean, unit(mean(&|c| c.2)).unwrap_or([0.0, 0.0, 1.0]));

        let dirs: Vec<V> = offsets.iter().filter_map(|o| unit(*o)).collect();
        let elevation = if dirs.is_empty() {
            0.0
        } else {
            dirs.iter().map(|d| dot(*d, up).clamp(-1.0, 1.0).asin()).sum::<f64>() / dirs.len() as f64
        };
        let horizontal = |d: V| sub(d, scale(up, dot(d, up)));
        let front = front_of(&dirs, up, a_mean);

        // Azimuths as `orbit` counts them: from `front` towards up x front.
        let side = cross(up, front);
        let azimuths = dirs
            .iter()
            .filter_map(|d| unit(horizontal(*d)))
            .map(|h| dot(h, side).atan2(dot(h, front)).to_degrees())
            .collect();
        let forward_facing = (spread as f32) < FORWARD_FACING_SPREAD_DEG;
        let arc = covered_arc(azimuths, ARC_GAP_DEG as f64).filter(|_| !forward_facing);

        let mean_right = unit(mean(&|c| c.3)).unwrap_or([1.0, 0.0, 0.0]);
        Some(Self {
            focus: f(focus),
            focus_from,
            radius: radius as f32,
            up: f(up),
            elevation_deg: elevation.to_degrees() as f32,
            front: f(front),
            spread_deg: spread as f32,
            forward_facing,
            spiral: spiral_of(&cams, c_mean, a_mean, mean_right, up, radius),
            image: [0, 0],
            fov_deg: 0.0,
            frames: cams
                .iter()
                .enumerate()
                .map(|(k, c)| RigFrame { image: k as u32, centre: f(c.0), axis: f(c.1) })
                .collect(),
            arc_deg: arc.map(|[a, b]| [a as f32, b as f32]),
        })
    }

    /// The training frame nearest a camera at `centre` looking along the
    /// unit `axis`, among those `allowed` accepts: the one minimising
    /// `|c - c_i| / radius + (1 - a . a_i)`, the distance between centres
    /// in rig radii plus one minus the cosine of the angle between the axes
    /// (design `real-captures.md` 2.6), the first on ties. `None` when no
    /// frame is allowed.
    pub fn nearest_frame(&self, centre: Vec3, axis: Vec3, allowed: impl Fn(u32) -> bool) -> Option<u32> {
        let r = if self.radius.is_finite() && self.radius > 0.0 { self.radius as f64 } else { 1.0 };
        let (c, a) = (v(centre), v(axis));
        let cost = |fr: &RigFrame| {
            let (ci, ai) = (fr.centre.map(f64::from), fr.axis.map(f64::from));
            norm(sub(c, ci)) / r + (1.0 - dot(a, ai))
        };
        self.frames
            .iter()
            .filter(|fr| allowed(fr.image))
            .map(|fr| (cost(fr), fr.image))
            .filter(|(k, _)| k.is_finite())
            .fold(None, |best: Option<(f64, u32)>, (k, i)| match best {
                Some((b, _)) if b <= k => best,
                _ => Some((k, i)),
            })
            .map(|(_, i)| i)
    }

    /// The orbit around the focus, about the rig's up axis, azimuth 0
    /// towards the cameras.
    pub fn orbit(&self, elevation_deg: f32, radius: f32) -> Orbit {
        Orbit {
            centre: Vec3::from_array(self.focus),
            up: Vec3::from_array(self.up),
            front: Some(Vec3::from_array(self.front)),
            elevation_deg,
            radius,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::look_at;

    fn ring(n: usize, centre: Vec3, r: f32, height: f32, up: Vec3) -> Vec<[[f32; 4]; 3]> {
        let (a, b) = if up.x.abs() > 0.9 {
            (Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.0, 0.0, 1.0))
        } else {
            let a = (Vec3::new(1.0, 0.0, 0.0) - up * up.x).normalized().unwrap();
            (a, up.cross(a))
        };
        (0..n)
            .map(|k| {
                let t = std::f32::consts::TAU * k as f32 / n as f32;
                let eye = centre + a * (r * t.cos()) + b * (r * t.sin()) + up * height;
                look_at(eye, centre, up).unwrap()
            })
            .collect()
    }

    fn close(a: [f32; 3], b: Vec3, tol: f32) -> bool {
        (Vec3::from_array(a) - b).norm() < tol
    }

    #[test]
    fn eigen_decomposes_symmetric_matrices() {
        let m = [[4.0, 1.0, -2.0], [1.0, 2.0, 0.5], [-2.0, 0.5, 3.0]];
        let (vals, vecs) = sym_eigen(m);
        assert!(vals[0] <= vals[1] && vals[1] <= vals[2]);
        for (l, e) in vals.iter().zip(vecs) {
            let me = [dot(m[0], e), dot(m[1], e), dot(m[2], e)];
            assert!(norm(sub(me, scale(e, *l))) < 1e-10, "{l} {e:?}");
            assert!((norm(e) - 1.0).abs() < 1e-12);
        }
        assert!((vals.iter().sum::<f64>() - 9.0).abs() < 1e-10);
    }

    #[test]
    fn a_tilted_ring_turns_about_its_normal_around_its_centre() {
        let up = Vec3::new(0.2, 0.1, 1.0).normalized().unwrap();
        let centre = Vec3::new(3.0, -1.0, 2.0);
        let poses = ring(24, centre, 4.0, 1.5, up);
        let rig = CameraRig::from_poses(&poses, 0.1, 20.0, Vec3::splat(0.0)).unwrap();
        assert_eq!(rig.focus_from, FocusFrom::Axes);
        assert!(close(rig.focus, centre, 1e-3), "{:?}", rig.focus);
        assert!(close(rig.up, up, 1e-3), "{:?}", rig.up);
        let r = (16.0f32 + 1.5 * 1.5).sqrt();
        assert!((rig.radius - r).abs() < 1e-3, "{}", rig.radius);
        assert!((rig.elevation_deg - (1.5f32 / 4.0).atan().to_degrees()).abs() < 0.05, "{}", rig.elevation_deg);
        // Every axis points 20.6 degrees down from the horizon: 69.4 degrees from the mean (straight down).
        assert!(!rig.forward_facing && (rig.spread_deg - 69.44).abs() < 0.1, "{}", rig.spread_deg);
        // A full ring has no mean direction: azimuth 0 is the first camera.
        let first = (Vec3::new(poses[0][0][3], poses[0][1][3], poses[0][2][3]) - centre) * (1.0 / 4.0);
        let first_h = (first - up * first.dot(up)).normalized().unwrap();
        assert!(close(rig.front, first_h, 1e-3), "{:?} vs {first_h:?}", rig.front);
        // A level ring: the axes cancel out, yet meet at the centre.
        let level = CameraRig::from_poses(&ring(12, centre, 4.0, 0.0, up), 0.1, 20.0, Vec3::splat(0.0)).unwrap();
        assert_eq!(level.focus_from, FocusFrom::Axes);
        assert!(close(level.focus, centre, 1e-3) && close(level.up, up, 1e-3) && level.elevation_deg.abs() < 0.01);
    }

    #[test]
    fn a_partial_arc_faces_its_cameras_and_ignores_the_box() {
        // A quarter arc centred on +x, looking at the origin; the box is far off.
        let up = Vec3::new(0.0, 0.0, 1.0);
        let poses: Vec<_> = ring(16, Vec3::splat(0.0), 5.0, 2.0, up).into_iter().take(5).collect();
        let rig = CameraRig::from_poses(&poses, 0.1, 30.0, Vec3::new(10.0, 10.0, 10.0)).unwrap();
        assert!(close(rig.focus, Vec3::splat(0.0), 1e-3), "{:?}", rig.focus);
        // Cameras at 0..90 degrees: their mean direction is at 45.
        let want = Vec3::new(1.0, 1.0, 0.0).normalized().unwrap();
        assert!(close(rig.front, want, 1e-3), "{:?}", rig.front);
        assert!(close(rig.up, up, 1e-3));
    }

    #[test]
    fn parallel_cameras_are_forward_facing_and_focus_at_the_spiral_depth() {
        // A 3x3 grid of cameras looking down -z, slightly converging.
        let mut poses = Vec::new();
        for i in -1..=1 {
            for j in -1..=1 {
                let eye = Vec3::new(i as f32 * 0.3, j as f32 * 0.2, 0.0);
                poses.push(
                    look_at(eye, Vec3::new(i as f32 * 0.29, j as f32 * 0.19, -10.0), Vec3::new(0.0, 1.0, 0.0)).unwrap(),
                );
            }
        }
        let (near, far) = (2.0, 40.0);
        let rig = CameraRig::from_poses(&poses, near, far, Vec3::splat(0.0)).unwrap();
        assert!(rig.forward_facing && rig.spread_deg < 1.0, "{}", rig.spread_deg);
        assert_eq!(rig.focus_from, FocusFrom::FocusDepth);
        let depth = 1.0 / (0.25 / near + 0.75 / far);
        assert!(close(rig.focus, Vec3::new(0.0, 0.0, -depth), 1e-3), "{:?}", rig.focus);
        assert!(
            (rig.spiral.half_widths[0] - 0.3).abs() < 1e-4 && (rig.spiral.half_widths[1] - 0.2).abs() < 1e-4,
            "{:?}",
            rig.spiral.half_widths
        );
        // The spiral stays in the cameras' plane, closes, and looks at the focus.
        let path = rig.spiral.poses(rig.focus, 12);
        assert_eq!(path.len(), 13);
        assert_eq!(path[0], path[12]);
        for m in &path {
            let eye = Vec3::new(m[0][3], m[1][3], m[2][3]);
            assert!(eye.z.abs() < 1e-4 && eye.x.abs() <= 0.3 + 1e-4 && eye.y.abs() <= 0.2 + 1e-4, "{eye:?}");
            let axis = Vec3::new(-m[0][2], -m[1][2], -m[2][2]);
            let to_focus = (Vec3::from_array(rig.focus) - eye).normalized().unwrap();
            assert!(axis.dot(to_focus) > 1.0 - 1e-5);
        }
    }

    #[test]
    fn cameras_looking_away_from_each_other_fall_back() {
        // Outward-looking ring: the axes' nearest point is behind every camera.
        let up = Vec3::new(0.0, 0.0, 1.0);
        let poses: Vec<_> = (0..8)
            .map(|k| {
                let t = std::f32::consts::TAU * k as f32 / 8.0;
                let eye = Vec3::new(t.cos(), t.sin(), 0.0);
                look_at(eye, eye * 3.0, up).unwrap()
            })
            .collect();
        let rig = CameraRig::from_poses(&poses, 0.5, 10.0, Vec3::new(1.0, 2.0, 3.0)).unwrap();
        assert_ne!(rig.focus_from, FocusFrom::Axes);
        assert!(CameraRig::from_poses(&[], 0.5, 10.0, Vec3::splat(0.0)).is_none());
        let mut bad = poses.clone();
        bad[0][0][3] = f32::NAN;
        assert!(CameraRig::from_poses(&bad, 0.5, 10.0, Vec3::splat(0.0)).is_none());
    }

    #[test]
    fn every_training_camera_is_its_own_nearest_frame() {
        let poses = ring(12, Vec3::new(1.0, -2.0, 0.5), 3.0, 1.0, Vec3::new(0.0, 0.0, 1.0));
        let rig = CameraRig::from_poses(&poses, 0.1, 20.0, Vec3::splat(0.0)).unwrap();
        assert_eq!(rig.frames.iter().map(|f| f.image).collect::<Vec<_>>(), (0..12).collect::<Vec<_>>());
        for (k, m) in poses.iter().enumerate() {
            let centre = Vec3::new(m[0][3], m[1][3], m[2][3]);
            let axis = Vec3::new(-m[0][2], -m[1][2], -m[2][2]);
            assert_eq!(rig.nearest_frame(centre, axis, |_| true), Some(k as u32));
            // Without itself, one of its two neighbours on the ring.
            let other = rig.nearest_frame(centre, axis, |i| i != k as u32).unwrap();
            assert!(other == (k as u32 + 1) % 12 || other == (k as u32 + 11) % 12, "{k}: {other}");
        }
    }

    #[test]
    fn the_nearest_frame_weighs_distance_in_radii_against_the_angle() {
        let poses = ring(8, Vec3::splat(0.0), 2.0, 0.0, Vec3::new(0.0, 0.0, 1.0));
        let mut rig = CameraRig::from_poses(&poses, 0.1, 20.0, Vec3::splat(0.0)).unwrap();
        rig.radius = 2.0;
        rig.frames = vec![
            RigFrame { image: 10, centre: [0.0, 0.0, 2.0], axis: [0.0, 0.0, -1.0] },
            RigFrame { image: 11, centre: [0.5, 0.0, 2.0], axis: [0.0, 0.0, -1.0] },
            RigFrame { image: 12, centre: [0.0, 0.0, 2.0], axis: [1.0, 0.0, 0.0] },
        ];
        // Costs by hand: 10: 0.4 / 2 = 0.2; 11: 0.1 / 2 = 0.05; 12: 0.2 + (1 - 0) = 1.2.
        let ahead = Vec3::new(0.0, 0.0, -1.0);
        assert_eq!(rig.nearest_frame(Vec3::new(0.4, 0.0, 2.0), ahead, |_| true), Some(11));
        // Turned towards +x (cos 0.6 with -z, 0.8 with +x): 10: 0 + 0.4; 11: 0.25 + 0.4; 12: 0 + 0.2.
        let turned = Vec3::new(0.8, 0.0, -0.6);
        assert_eq!(rig.nearest_frame(Vec3::new(0.0, 0.0, 2.0), turned, |_| true), Some(12));
        assert_eq!(rig.nearest_frame(Vec3::new(0.0, 0.0, 2.0), turned, |i| i != 12), Some(10));
        assert_eq!(rig.nearest_frame(Vec3::new(0.0, 0.0, 2.0), turned, |_| false), None);
        // The radius sets the trade: from (0.4, 0, 2) looking `turned`, with r = 0.25:
        // 10: 1.6 + 0.4; 11: 0.4 + 0.4; 12: 1.6 + 0.2. With r = 4: 10: 0.1 + 0.4; 11: 0.025 + 0.4; 12: 0.1 + 0.2.
        rig.radius = 0.25;
        assert_eq!(rig.nearest_frame(Vec3::new(0.4, 0.0, 2.0), turned, |_| true), Some(11));
        rig.radius = 4.0;
        assert_eq!(rig.nearest_frame(Vec3::new(0.4, 0.0, 2.0), turned, |_| true), Some(12));
        // A tie keeps the first frame.
        rig.frames[1] = RigFrame { image: 11, ..rig.frames[0] };
        assert_eq!(rig.nearest_frame(Vec3::new(0.0, 0.0, 2.0), ahead, |_| true), Some(10));
    }

    #[test]
    fn arcs_are_found_across_the_widest_gap() {
        // Around 0 (wrapping): 300..360 and 0..60 are covered.
        let arc = covered_arc(vec![10.0, -50.0, 60.0, 300.0 - 360.0, 0.0], 120.0).unwrap();
        assert!((arc[0] + 60.0).abs() < 1e-9 && (arc[1] - 60.0).abs() < 1e-9, "{arc:?}");
        // An arc away from 0, and one whose widest gap wraps.
        assert_eq!(covered_arc(vec![100.0, 170.0, 130.0], 120.0), Some([100.0, 170.0]));
        assert_eq!(covered_arc(vec![-170.0, 170.0, 150.0], 120.0), Some([150.0, 190.0]));
        // All around (largest gap 90), or too few cameras: no arc.
        assert_eq!(covered_arc(vec![0.0, 90.0, 180.0, 270.0], 120.0), None);
        assert_eq!(covered_arc(vec![0.0, 10.0], 120.0), None);
    }

    #[test]
    fn one_sided_captures_get_an_arc_and_rings_do_not() {
        let up = Vec3::new(0.0, 0.0, 1.0);
        // A ring all around: no arc.
        let rig =
            CameraRig::from_poses(&ring(12, Vec3::splat(0.0), 3.0, 1.0, up), 0.1, 10.0, Vec3::splat(0.0)).unwrap();
        assert_eq!(rig.arc_deg, None);
        // The same ring's cameras within 100 degrees of +x: an arc of 90
        // degrees (the cameras at -45..45), centred on azimuth 0 (front).
        let poses: Vec<_> = ring(24, Vec3::splat(0.0), 3.0, 1.0, up)
            .into_iter()
            .filter(|p| p[1][3].atan2(p[0][3]).to_degrees().abs() < 50.0)
            .collect();
        assert_eq!(poses.len(), 7);
        let rig = CameraRig::from_poses(&poses, 0.1, 10.0, Vec3::new(40.0, 0.0, 0.0)).unwrap();
        let [a, b] = rig.arc_deg.expect("a one-sided capture has an arc");
        assert!((a + 45.0).abs() < 0.5 && (b - 45.0).abs() < 0.5, "{a} {b}");
        // Its sweep stays on the cameras' side of the focus.
        let sweep = rig.orbit(rig.elevation_deg, rig.radius).sweep([a, b], 16).unwrap();
        assert!(sweep.iter().all(|p| p[0][3] > 0.0), "{sweep:?}");
    }
}
