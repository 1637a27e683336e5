//! Unit quaternions for rotations: from and to rotation matrices, and the
//! spherical interpolation camera paths use. `f64` inside: a path evaluates
//! long chains of them.

/// `w + xi + yj + zk`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quat {
    pub w: f64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Quat {
    pub const IDENTITY: Quat = Quat { w: 1.0, x: 0.0, y: 0.0, z: 0.0 };

    /// The rotation of `angle` radians about the unit `axis`.
    pub fn from_axis_angle(axis: [f64; 3], angle: f64) -> Quat {
        let (s, c) = (0.5 * angle).sin_cos();
        Quat { w: c, x: axis[0] * s, y: axis[1] * s, z: axis[2] * s }
    }

    /// A rotation matrix (orthonormal, determinant 1) as a unit quaternion
    /// with `w >= 0` (Shepperd's method: the largest of the four
    /// candidates, so no division by a small number).
    pub fn from_matrix(m: [[f64; 3]; 3]) -> Quat {
        let trace = m[0][0] + m[1][1] + m[2][2];
        let q = if trace >= m[0][0].max(m[1][1]).max(m[2][2]) {
            let s = 2.0 * (1.0 + trace).max(0.0).sqrt();
            Quat { w: 0.25 * s, x: (m[2][1] - m[1][2]) / s, y: (m[0][2] - m[2][0]) / s, z: (m[1][0] - m[0][1]) / s }
        } else if m[0][0] >= m[1][1] && m[0][0] >= m[2][2] {
            let s = 2.0 * (1.0 + m[0][0] - m[1][1] - m[2][2]).max(0.0).sqrt();
            Quat { w: (m[2][1] - m[1][2]) / s, x: 0.25 * s, y: (m[0][1] + m[1][0]) / s, z: (m[0][2] + m[2][0]) / s }
        } else if m[1][1] >= m[2][2] {
            let s = 2.0 * (1.0 + m[1][1] - m[0][0] - m[2][2]).max(0.0).sqrt();
            Quat { w: (m[0][2] - m[2][0]) / s, x: (m[0][1] + m[1][0]) / s, y: 0.25 * s, z: (m[1][2] + m[2][1]) / s }
        } else {
            let s = 2.0 * (1.0 + m[2][2] - m[0][0] - m[1][1]).max(0.0).sqrt();
            Quat { w: (m[1][0] - m[0][1]) / s, x: (m[0][2] + m[2][0]) / s, y: (m[1][2] + m[2][1]) / s, z: 0.25 * s }
        };
        let q = q.normalized();
        if q.w < 0.0 { q.negated() } else { q }
    }

    /// The rotation matrix of a unit quaternion.
    pub fn to_matrix(self) -> [[f64; 3]; 3] {
        let Quat { w, x, y, z } = self;
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ]
    }

    pub fn dot(self, o: Quat) -> f64 {
        self.w * o.w + self.x * o.x + self.y * o.y + self.z * o.z
    }
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }
    pub fn negated(self) -> Quat {
        Quat { w: -self.w, x: -self.x, y: -self.y, z: -self.z }
    }
    pub fn conj(self) -> Quat {
        Quat { w: self.w, x: -self.x, y: -self.y, z: -self.z }
    }
    pub fn normalized(self) -> Quat {
        let n = self.norm();
        if n > 0.0 { Quat { w: self.w / n, x: self.x / n, y: self.y / n, z: self.z / n } } else { Quat::IDENTITY }
    }

    /// The Hamilton product `self * o` (apply `o`, then `self`).
    pub fn times(self, o: Quat) -> Quat {
        Quat {
            w: self.w * o.w - self.x * o.x - self.y * o.y - self.z * o.z,
            x: self.w * o.x + self.x * o.w + self.y * o.z - self.z * o.y,
            y: self.w * o.y - self.x * o.z + self.y * o.w + self.z * o.x,
            z: self.w * o.z + self.x * o.y - self.y * o.x + self.z * o.w,
        }
    }

    /// `self^u` for a unit quaternion: the rotation about the same axis by
    /// `u` times the angle (any real `u`, so slerp can also extrapolate).
    pub fn pow(self, u: f64) -> Quat {
        let v = (self.x * self.x + self.y * self.y + self.z * self.z).sqrt();
        let half = v.atan2(self.w);
        if v < 1e-12 {
            return Quat::IDENTITY;
        }
        let (s, c) = (u * half).sin_cos();
        let k = s / v;
        Quat { w: c, x: self.x * k, y: self.y * k, z: self.z * k }
    }

    /// Spherical linear interpolation from `self` (u = 0) to `o` (u = 1)
    /// along the shorter arc, at constant angular speed; `u` outside [0, 1]
    /// extrapolates along the same great circle.
    pub fn slerp(self, o: Quat, u: f64) -> Quat {
        self.slerp_as_given(if self.dot(o) < 0.0 { o.negated() } else { o }, u)
    }

    /// Slerp from `self` to `o` as the two are signed (the longer arc when
    /// their dot product is negative): continuous in both, which the
    /// choice of the shorter arc is not. For quaternions already in one
    /// hemisphere.
    pub fn slerp_as_given(self, o: Quat, u: f64) -> Quat {
        self.times(self.conj().times(o).normalized().pow(u)).normalized()
    }

    /// The angle in radians of the rotation between `self` and `o`.
    pub fn angle_to(self, o: Quat) -> f64 {
        2.0 * self.dot(o).abs().min(1.0).acos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: Quat, b: Quat, tol: f64) -> bool {
        a.angle_to(b) < tol
    }

    #[test]
    fn matrix_round_trip_on_every_branch() {
        // Angles near 0, 90, 180 degrees about each axis and a skew axis
        // reach all four branches of Shepperd's method.
        let s = 1.0 / 3f64.sqrt();
        for axis in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [s, s, s], [s, -s, s]] {
            for angle in [0.0, 0.3, std::f64::consts::FRAC_PI_2, 3.0, std::f64::consts::PI - 1e-5, -2.0] {
                let q = Quat::from_axis_angle(axis, angle);
                let back = Quat::from_matrix(q.to_matrix());
                assert!(close(q, back, 1e-7), "{axis:?} {angle}: {q:?} {back:?}");
                assert!((back.norm() - 1.0).abs() < 1e-12 && back.w >= 0.0);
            }
        }
    }

    #[test]
    fn slerp_turns_at_constant_speed_about_the_axis() {
        let axis = [0.0, 0.0, 1.0];
        let (a, b) = (Quat::from_axis_angle(axis, 0.2), Quat::from_axis_angle(axis, 1.4));
        for u in [-0.5, 0.0, 0.25, 0.5, 1.0, 1.5] {
            let want = Quat::from_axis_angle(axis, 0.2 + 1.2 * u);
            assert!(close(a.slerp(b, u), want, 1e-10), "u {u}");
        }
        // The shorter arc, whichever sign the second quaternion has.
        assert!(close(a.slerp(b.negated(), 0.5), Quat::from_axis_angle(axis, 0.8), 1e-10));
        assert!(close(a.slerp(a, 0.7), a, 1e-12));
    }
}
