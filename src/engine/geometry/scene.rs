//! Scene normalisation: models work in coordinates where the scene box is
//! centred at the origin with its largest half-extent 1, whatever the units
//! of the capture. Distances along rays scale by the same factor.

use crate::engine::geometry::math::{Aabb, Ray, Vec3};
use crate::engine::geometry::rig::CameraRig;

/// `v / |v|` computed in f64, so that tiny (subnormal) and huge components
/// normalise exactly; `None` for zero or non-finite vectors.
fn unit(v: Vec3) -> Option<Vec3> {
    let (x, y, z) = (v.x as f64, v.y as f64, v.z as f64);
    let n = (x * x + y * y + z * z).sqrt();
    (n.is_finite() && n > 0.0).then(|| Vec3::new((x / n) as f32, (y / n) as f32, (z / n) as f32))
}

/// World-to-model mapping and the scene's bounds in model units.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Scene {
    /// World-space centre of the scene box.
    pub centre: [f32; 3],
    /// Model units per world unit.
    pub scale: f32,
    /// The scene box in model units.
    pub aabb_min: [f32; 3],
    pub aabb_max: [f32; 3],
    /// Ray interval in model units.
    pub near: f32,
    pub far: f32,
    /// Whether some training images have transparent pixels (an object on
    /// an empty background, as in the NeRF synthetic scenes).
    #[serde(default)]
    pub transparent: bool,
    /// The training cameras' rig (world units): where they look, from how
    /// far, which way is up. Orbits and default views come from it.
    /// `None` for scenes made from bounds alone, and in checkpoints from
    /// before it existed.
    #[serde(default)]
    pub rig: Option<CameraRig>,
}

impl Scene {
    pub fn from_bounds(aabb: Aabb, near: f32, far: f32) -> Self {
        let c = aabb.centre();
        let h = aabb.half_extent();
        let ext = h.x.max(h.y).max(h.z);
        let scale = if ext.is_finite() && ext > 0.0 { 1.0 / ext } else { 1.0 };
        let lo = (aabb.min - c) * scale;
        let hi = (aabb.max - c) * scale;
        Self {
            centre: c.to_array(),
            scale,
            aabb_min: lo.to_array(),
            aabb_max: hi.to_array(),
            near: near * scale,
            far: far * scale,
            transparent: false,
            rig: None,
        }
    }

    pub fn aabb(&self) -> Aabb {
        Aabb { min: Vec3::from_array(self.aabb_min), max: Vec3::from_array(self.aabb_max) }
    }

    /// A model-space point in world coordinates.
    pub fn point_to_world(&self, p: [f32; 3]) -> [f32; 3] {
        let inv = 1.0 / self.scale;
        [0, 1, 2].map(|c| p[c] * inv + self.centre[c])
    }

    /// A world point in model coordinates.
    pub fn point_to_model(&self, p: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|c| (p[c] - self.centre[c]) * self.scale)
    }

    /// A world ray in model coordinates (same direction, normalised;
    /// distances scale). A zero or non-finite direction is left as it is,
    /// and [`Scene::clip`] rejects it.
    pub fn to_model(&self, ray: &Ray) -> Ray {
        Ray { origin: (ray.origin - Vec3::from_array(self.centre)) * self.scale, dir: unit(ray.dir).unwrap_or(ray.dir) }
    }

    /// The part of a model-space ray inside the box and `[near, far]`;
    /// `None` when it misses, and for rays with a non-finite origin or a
    /// zero or non-finite direction (they see only the background).
    pub fn clip(&self, ray: &Ray) -> Option<(f32, f32)> {
        if !(ray.origin.is_finite() && ray.dir.is_finite()) || ray.dir.dot(ray.dir) == 0.0 {
            return None;
        }
        self.aabb().clip(ray, self.near, self.far)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degenerate_rays_are_normalised_or_rejected() {
        let s = Scene::from_bounds(Aabb { min: Vec3::splat(-2.0), max: Vec3::splat(2.0) }, 0.0, 10.0);
        let inside = Vec3::new(0.5, 0.0, 0.0);
        for (dir, want) in [
            (Vec3::new(0.0, 0.0, 1e-20), Vec3::new(0.0, 0.0, 1.0)),
            (Vec3::new(0.0, -1e-45, 0.0), Vec3::new(0.0, -1.0, 0.0)),
            (Vec3::new(3e38, 0.0, -3e38), Vec3::new(0.70710677, 0.0, -0.70710677)),
        ] {
            let r = s.to_model(&Ray { origin: inside, dir });
            assert!((r.dir - want).norm() < 1e-7, "{dir:?} -> {:?}", r.dir);
            assert!(s.clip(&r).is_some());
        }
        for dir in [Vec3::splat(0.0), Vec3::new(f32::NAN, 0.0, 1.0), Vec3::new(0.0, f32::INFINITY, 0.0)] {
            assert_eq!(s.clip(&s.to_model(&Ray { origin: inside, dir })), None, "{dir:?}");
        }
        let nan_origin = Ray { origin: Vec3::new(f32::NAN, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
        assert_eq!(s.clip(&s.to_model(&nan_origin)), None);
    }
}
