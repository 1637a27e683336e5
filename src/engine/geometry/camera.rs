//! Pinhole cameras with optional OpenCV radial-tangential distortion, and the
//! rays through their pixels.
//!
//! Conventions: `c2w` is a 3x4 camera-to-world matrix in the OpenGL/Blender
//! convention (camera x right, y up, looking down -z). Pixel coordinates are
//! continuous with the image spanning `[0, width] x [0, height]`, so the
//! centre of pixel `(i, j)` is `(i + 0.5, j + 0.5)` and `cx, cy` are given in
//! the same frame (the COLMAP / instant-ngp / nerfstudio convention).

use crate::engine::geometry::math::{Ray, Vec3};

/// OpenCV distortion coefficients (`k1 k2 p1 p2`), acting on normalised
/// image coordinates.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    pub k1: f32,
    pub k2: f32,
    pub p1: f32,
    pub p2: f32,
}

impl Distortion {
    pub fn is_identity(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0
    }

    /// Maps undistorted normalised coordinates to distorted ones.
    pub fn distort(&self, x: f32, y: f32) -> (f32, f32) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * self.k2);
        (
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Inverts [`Distortion::distort`] by Newton's method (the distortion of
    /// real lenses is mild, so a few iterations from the distorted point
    /// converge to f32 precision).
    pub fn undistort(&self, xd: f32, yd: f32) -> (f32, f32) {
        if self.is_identity() {
            return (xd, yd);
        }
        let (mut x, mut y) = (xd as f64, yd as f64);
        let (k1, k2, p1, p2) = (self.k1 as f64, self.k2 as f64, self.p1 as f64, self.p2 as f64);
        for _ in 0..10 {
            let r2 = x * x + y * y;
            let radial = 1.0 + r2 * (k1 + r2 * k2);
            let fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd as f64;
            let fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd as f64;
            // d(radial)/dx = (2 k1 + 4 k2 r2) x
            let dr = 2.0 * k1 + 4.0 * k2 * r2;
            let j00 = radial + x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x;
            let j01 = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
            let j10 = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y;
            let j11 = radial + y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x;
            let det = j00 * j11 - j01 * j10;
            if !det.is_finite() || det.abs() < 1e-12 {
                break;
            }
            let dx = (fx * j11 - fy * j01) / det;
            let dy = (fy * j00 - fx * j10) / det;
            x -= dx;
            y -= dy;
            if dx.abs() < 1e-10 && dy.abs() < 1e-10 {
                break;
            }
        }
        (x as f32, y as f32)
    }
}

/// A calibrated camera: intrinsics, distortion and pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub distortion: Distortion,
    /// Camera-to-world, rows of a 3x4 matrix (rotation | translation).
    pub c2w: [[f32; 4]; 3],
}

impl Camera {
    /// A camera with the principal point at the image centre and the given
    /// horizontal field of view (radians).
    pub fn from_fov(width: u32, height: u32, fov_x: f32, c2w: [[f32; 4]; 3]) -> Self {
        let f = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Self {
            width,
            height,
            fx: f,
            fy: f,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
            distortion: Distortion::default(),
            c2w,
        }
    }

    /// The same camera with a frame of `width x height` pixels and its
    /// focal lengths and principal point scaled by `s` (the frame `s`
    /// times as large, or a whole image averaged down by `1 / s`).
    pub fn resized(&self, width: u32, height: u32, s: f32) -> Self {
        Self { width, height, fx: self.fx * s, fy: self.fy * s, cx: self.cx * s, cy: self.cy * s, ..self.clone() }
    }

    pub fn origin(&self) -> Vec3 {
        Vec3::new(self.c2w[0][3], self.c2w[1][3], self.c2w[2][3])
    }

    /// Rotates a camera-space direction into world space.
    pub fn rotate(&self, d: Vec3) -> Vec3 {
        let m = &self.c2w;
        Vec3::new(
            m[0][0] * d.x + m[0][1] * d.y + m[0][2] * d.z,
            m[1][0] * d.x + m[1][1] * d.y + m[1][2] * d.z,
            m[2][0] * d.x + m[2][1] * d.y + m[2][2] * d.z,
        )
    }

    /// The world-space ray through continuous pixel coordinates `(u, v)`
    /// (pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`), with a unit
    /// direction.
    pub fn ray(&self, u: f32, v: f32) -> Ray {
        let xd = (u - self.cx) / self.fx;
        let yd = (v - self.cy) / self.fy;
        let (x, y) = self.distortion.undistort(xd, yd);
        // Image y grows downwards, camera y upwards; the camera looks down -z.
        let d = self.rotate(Vec3::new(x, -y, -1.0));
        let dir = d.normalized().unwrap_or(Vec3::new(0.0, 0.0, -1.0));
        Ray { origin: self.origin(), dir }
    }

    /// Where world point `p` falls in the frame (pixels), if in front of
    /// the camera and inside it (lens distortion ignored: for finding
    /// places, not for sub-pixel truth).
    pub fn project(&self, p: [f32; 3]) -> Option<(f32, f32)> {
        let m = &self.c2w;
        let d = Vec3::from_array(p) - self.origin();
        // Camera coordinates: the rotation's columns are the camera's axes.
        let c = [0, 1, 2].map(|k| Vec3::new(m[0][k], m[1][k], m[2][k]).dot(d));
        let depth = -c[2];
        if depth <= 1e-6 {
            return None;
        }
        let u = self.fx * c[0] / depth + self.cx;
        let v = -self.fy * c[1] / depth + self.cy;
        (u >= 0.0 && v >= 0.0 && u < self.width as f32 && v < self.height as f32).then_some((u, v))
    }

    /// The ray through the centre of pixel `(i, j)`.
    pub fn pixel_ray(&self, i: u32, j: u32) -> Ray {
        self.ray(i as f32 + 0.5, j as f32 + 0.5)
    }
}

/// A camera-to-world pose looking from `eye` at `target` with `up` as the
/// approximate up vector (OpenGL convention). `None` when degenerate.
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Option<[[f32; 4]; 3]> {
    let back = (eye - target).normalized()?; // camera +z points away from target
    let right = up.cross(back).normalized()?;
    let up = back.cross(right);
    Some([[right.x, up.x, back.x, eye.x], [right.y, up.y, back.y, eye.y], [right.z, up.z, back.z, eye.z]])
}

/// An orbit around `centre`, looking at it: the one place where orbit
/// renders and orbit videos get their cameras. Azimuth 0 is world +x
/// projected on the horizon (or +y when `up` is close to x).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    pub centre: Vec3,
    /// The scene's up axis (need not be unit length).
    pub up: Vec3,
    /// The direction of azimuth 0 (projected perpendicular to `up`); `None`:
    /// world x (world y when `up` is near x).
    pub front: Option<Vec3>,
    /// Degrees above the horizon.
    pub elevation_deg: f32,
    /// Distance from the centre, world units.
    pub radius: f32,
}

impl Orbit {
    /// The pose at `azimuth_deg` around `up`. `None` when degenerate (zero
    /// `up`, or looking straight along it).
    pub fn pose(&self, azimuth_deg: f32) -> Option<[[f32; 4]; 3]> {
        let up = self.up.normalized()?;
        let x = Vec3::new(1.0, 0.0, 0.0);
        let fallback = if up.dot(x).abs() > 0.9 { Vec3::new(0.0, 1.0, 0.0) } else { x };
        let horizontal = |r: Vec3| (r - up * up.dot(r)).normalized();
        let a = self.front.and_then(horizontal).or_else(|| horizontal(fallback))?;
        let b = up.cross(a);
        let (az, el) = (azimuth_deg.to_radians(), self.elevation_deg.to_radians());
        let dir = (a * az.cos() + b * az.sin()) * el.cos() + up * el.sin();
        look_at(self.centre + dir * self.radius, self.centre, up)
    }

    /// `n` poses sweeping across the azimuths `arc_deg` (`[start, end]`,
    /// degrees) and back: from the middle to `end`, back through the middle
    /// to `start` and back again, slowing at the ends (azimuth = middle +
    /// half-width * sin(2 pi k / n)), so the video loops without a jump.
    /// `None` when a pose is degenerate (as for [`Orbit::pose`]).
    pub fn sweep(&self, arc_deg: [f32; 2], n: usize) -> Option<Vec<[[f32; 4]; 3]>> {
        let (mid, half) = (0.5 * (arc_deg[0] + arc_deg[1]), 0.5 * (arc_deg[1] - arc_deg[0]));
        (0..n).map(|k| self.pose(mid + half * (std::f32::consts::TAU * k as f32 / n.max(1) as f32).sin())).collect()
    }

    /// The camera at `azimuth_deg` with a `width x height` image and a
    /// horizontal field of view of `fov_deg` degrees (`None` as for
    /// [`Orbit::pose`]).
    pub fn camera(&self, azimuth_deg: f32, width: u32, height: u32, fov_deg: f32) -> Option<Camera> {
        Some(Camera::from_fov(width, height, fov_deg.to_radians(), self.pose(azimuth_deg)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let d = Distortion { k1: 0.0578, k2: -0.0805, p1: -0.00098, p2: 0.000156 };
        for &(x, y) in &[(0.0f32, 0.0f32), (0.3, -0.2), (-0.5, 0.6), (0.7, 0.7)] {
            let (xd, yd) = d.distort(x, y);
            let (xu, yu) = d.undistort(xd, yd);
            assert!((xu - x).abs() < 1e-5 && (yu - y).abs() < 1e-5, "{x},{y} -> {xu},{yu}");
        }
    }

    #[test]
    fn centre_ray_looks_down_minus_z() {
        let c2w = [[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0]];
        let cam = Camera::from_fov(100, 80, 1.0, c2w);
        let r = cam.ray(50.0, 40.0);
        assert_eq!(r.origin, Vec3::new(1.0, 2.0, 3.0));
        assert!((r.dir.z + 1.0).abs() < 1e-6 && r.dir.x.abs() < 1e-6);
        // A pixel right of and above the centre points to +x and +y.
        let r = cam.ray(90.0, 10.0);
        assert!(r.dir.x > 0.0 && r.dir.y > 0.0);
        // The image edge is at half the field of view.
        let r = cam.ray(100.0, 40.0);
        assert!((r.dir.x.atan2(-r.dir.z) - 0.5).abs() < 1e-5);
    }

    #[test]
    fn look_at_points_at_target() {
        let eye = Vec3::new(0.0, -4.0, 1.0);
        let m = look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
        let cam = Camera::from_fov(10, 10, 0.8, m);
        let r = cam.ray(5.0, 5.0);
        let to_target = (Vec3::splat(0.0) - eye).normalized().unwrap();
        assert!((r.dir.dot(to_target) - 1.0).abs() < 1e-6);
        assert!(look_at(eye, eye, Vec3::new(0.0, 0.0, 1.0)).is_none());
    }

    #[test]
    fn orbit_looks_at_its_centre_from_its_radius() {
        let centre = Vec3::new(1.0, 2.0, 3.0);
        let orbit = Orbit { centre, up: Vec3::new(0.0, 0.0, 2.0), front: None, elevation_deg: 30.0, radius: 4.0 };
        let cam = orbit.camera(90.0, 8, 8, 50.0).unwrap();
        assert_eq!((cam.width, cam.height), (8, 8));
        // 50 degrees across 8 pixels: fx = 4 / tan(25 degrees).
        assert!((cam.fx - 4.0 / 25f32.to_radians().tan()).abs() < 1e-4);
        let to_centre = (centre - cam.origin()).normalized().unwrap();
        assert!((cam.ray(4.0, 4.0).dir.dot(to_centre) - 1.0).abs() < 1e-5);
        assert!(((cam.origin() - centre).norm() - 4.0).abs() < 1e-4);
        // Azimuth 90 turns from +x towards +y; 30 degrees up: z = 3 + 4 sin 30.
        assert!(cam.origin().y > 2.0 && (cam.origin().z - 5.0).abs() < 1e-4);
        assert_eq!(orbit.pose(90.0), Some(cam.c2w));
        // A zero up axis has no camera.
        assert!(Orbit { up: Vec3::splat(0.0), ..orbit }.camera(0.0, 8, 8, 50.0).is_none());
    }

    #[test]
    fn a_sweep_spans_its_arc_and_loops() {
        let orbit = Orbit {
            centre: Vec3::splat(0.0),
            up: Vec3::new(0.0, 0.0, 1.0),
            front: Some(Vec3::new(1.0, 0.0, 0.0)),
            elevation_deg: 0.0,
            radius: 2.0,
        };
        let poses = orbit.sweep([-30.0, 90.0], 40).unwrap();
        assert_eq!(poses.len(), 40);
        let azimuth = |p: &[[f32; 4]; 3]| p[1][3].atan2(p[0][3]).to_degrees();
        let az: Vec<f32> = poses.iter().map(azimuth).collect();
        // Starts in the middle, reaches both ends (a quarter and three
        // quarters of the way), never leaves the arc.
        assert!((az[0] - 30.0).abs() < 1e-3 && (az[10] - 90.0).abs() < 1e-3 && (az[30] + 30.0).abs() < 1e-3, "{az:?}");
        assert!(az.iter().all(|a| (-30.001..=90.001).contains(a)), "{az:?}");
        // The step from the last frame back to the first is no larger than
        // the largest step inside: the loop has no jump.
        let step = |a: f32, b: f32| (a - b).abs();
        let largest = az.windows(2).map(|w| step(w[0], w[1])).fold(0.0, f32::max);
        assert!(step(az[39], az[0]) <= largest + 1e-3, "{} vs {largest}", step(az[39], az[0]));
    }
}
