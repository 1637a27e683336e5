//! Scene normalisation: models work in coordinates where the scene box is
//! centred at the origin with its largest half-extent 1, whatever the units
//! of the capture. Distances along rays scale by the same factor.

use super::dataset::Dataset;
use super::math::{Aabb, Ray, Vec3};

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
}

impl Scene {
    pub fn from_dataset(ds: &Dataset) -> Self {
        Self::from_bounds(ds.aabb, ds.near, ds.far)
    }

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
        }
    }

    pub fn aabb(&self) -> Aabb {
        Aabb { min: Vec3::from_array(self.aabb_min), max: Vec3::from_array(self.aabb_max) }
    }

    /// A world ray in model coordinates (same direction; distances scale).
    pub fn to_model(&self, ray: &Ray) -> Ray {
        Ray { origin: (ray.origin - Vec3::from_array(self.centre)) * self.scale, dir: ray.dir }
    }

    /// The part of a model-space ray inside the box and `[near, far]`.
    pub fn clip(&self, ray: &Ray) -> Option<(f32, f32)> {
        self.aabb().clip(ray, self.near, self.far)
    }
}
