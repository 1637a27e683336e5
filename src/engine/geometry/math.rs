//! Small fixed-size vector maths used by cameras, rays and bounding boxes.

use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector of f32.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Vec3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

impl Vec3 {
    pub const fn new(x: f32, y: f32, z: f32) -> Self {
        Self { x, y, z }
    }
    pub const fn splat(v: f32) -> Self {
        Self { x: v, y: v, z: v }
    }
    pub fn dot(self, o: Self) -> f32 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    pub fn cross(self, o: Self) -> Self {
        Self::new(self.y * o.z - self.z * o.y, self.z * o.x - self.x * o.z, self.x * o.y - self.y * o.x)
    }
    pub fn norm(self) -> f32 {
        self.dot(self).sqrt()
    }
    /// Unit vector in the same direction; `None` for zero or non-finite input.
    pub fn normalized(self) -> Option<Self> {
        let n = self.norm();
        if n.is_finite() && n > 0.0 { Some(self * (1.0 / n)) } else { None }
    }
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
    pub fn min(self, o: Self) -> Self {
        Self::new(self.x.min(o.x), self.y.min(o.y), self.z.min(o.z))
    }
    pub fn max(self, o: Self) -> Self {
        Self::new(self.x.max(o.x), self.y.max(o.y), self.z.max(o.z))
    }
    pub fn to_array(self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
    pub fn from_array(a: [f32; 3]) -> Self {
        Self::new(a[0], a[1], a[2])
    }
}

impl Add for Vec3 {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for Vec3 {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f32> for Vec3 {
    type Output = Self;
    fn mul(self, s: f32) -> Self {
        Self::new(self.x * s, self.y * s, self.z * s)
    }
}
impl Neg for Vec3 {
    type Output = Self;
    fn neg(self) -> Self {
        Self::new(-self.x, -self.y, -self.z)
    }
}

/// A ray with origin and unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

impl Ray {
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn centre(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }
    pub fn half_extent(&self) -> Vec3 {
        (self.max - self.min) * 0.5
    }
    /// The parametric interval `[t0, t1]` where the ray is inside the box,
    /// clipped to `[near, far]`; `None` when the ray misses it.
    /// Works for axis-parallel rays (zero direction components).
    pub fn clip(&self, ray: &Ray, near: f32, far: f32) -> Option<(f32, f32)> {
        let mut t0 = near;
        let mut t1 = far;
        for (o, d, lo, hi) in [
            (ray.origin.x, ray.dir.x, self.min.x, self.max.x),
            (ray.origin.y, ray.dir.y, self.min.y, self.max.y),
            (ray.origin.z, ray.dir.z, self.min.z, self.max.z),
        ] {
            if d == 0.0 {
                if o < lo || o > hi {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / d;
            let (a, b) = ((lo - o) * inv, (hi - o) * inv);
            let (a, b) = if a < b { (a, b) } else { (b, a) };
            t0 = t0.max(a);
            t1 = t1.min(b);
        }
        (t0 < t1).then_some((t0, t1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clip_hits_and_misses() {
        let b = Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) };
        let r = Ray { origin: Vec3::new(0.0, 0.0, -5.0), dir: Vec3::new(0.0, 0.0, 1.0) };
        assert_eq!(b.clip(&r, 0.0, 100.0), Some((4.0, 6.0)));
        assert_eq!(b.clip(&r, 4.5, 5.0), Some((4.5, 5.0)));
        let miss = Ray { origin: Vec3::new(2.0, 0.0, -5.0), dir: Vec3::new(0.0, 0.0, 1.0) };
        assert_eq!(b.clip(&miss, 0.0, 100.0), None);
        let inside = Ray { origin: Vec3::ZERO_TEST, dir: Vec3::new(1.0, 0.0, 0.0) };
        assert_eq!(b.clip(&inside, 0.0, 100.0), Some((0.0, 1.0)));
    }

    impl Vec3 {
        const ZERO_TEST: Vec3 = Vec3::splat(0.0);
    }
}
