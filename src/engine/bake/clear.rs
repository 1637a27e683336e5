//! The space around the training cameras is kept clear of what no photo
//! checks.
//!
//! A capture's near bound says nothing lies that close to a camera along
//! its rays: the field is rendered from there on, and the splats are drawn
//! from there on too (`RasterOptions::for_scene`), so a training photo
//! does not see a Gaussian nearer its camera than that. Beside and behind
//! a camera no photo looks either. A Gaussian within that distance of a
//! training camera (a far wall that the field set on the other side of the
//! walk, or one placed past the photos' edges) is kept only where another
//! training photo has it in its frame beyond the near bound, where the fit
//! checks it (the rim of what an object stands on can pass that close to a
//! camera of a walk around it); otherwise a new view between two photos
//! would look straight into it.

use crate::engine::dataset::Dataset;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::splats::raster::RasterCamera;

/// The training cameras, and the balls of their near bound around their
/// centres (model units).
pub(super) struct CameraBalls {
    cams: Vec<RasterCamera>,
    radius: f32,
}

impl CameraBalls {
    /// Balls of `radius` around the centres of `cams`, which see from
    /// `radius` on.
    pub fn new(cams: &[RasterCamera], radius: f32) -> Self {
        Self { cams: cams.to_vec(), radius }
    }

    /// Balls of `scene`'s near bound around the cameras of `ds`'s `frames`
    /// (in `scene`'s model units).
    pub fn around(ds: &Dataset, frames: &[usize], scene: &Scene) -> Self {
        let cams: Vec<RasterCamera> = frames.iter().map(|&f| RasterCamera::new(&ds.frames[f].camera, scene)).collect();
        Self::new(&cams, scene.near)
    }

    /// Whether `at` may be kept: outside every ball, or inside a camera's
    /// frame beyond the near bound.
    pub fn clear(&self, at: [f32; 3]) -> bool {
        let r2 = self.radius * self.radius;
        let inside = |c: &RasterCamera| {
            let d = [at[0] - c.origin[0], at[1] - c.origin[1], at[2] - c.origin[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < r2
        };
        !self.cams.iter().any(inside) || self.cams.iter().any(|c| self.sees(c, at))
    }

    /// Whether `c` has `at` in its frame, at least the near bound in front
    /// of it.
    fn sees(&self, c: &RasterCamera, at: [f32; 3]) -> bool {
        let t = c.to_camera(at);
        if !(t[2] >= self.radius && t[2] > 0.0) {
            return false;
        }
        let [u, v] = c.pixel(t);
        super::in_frame(u, v, c.width as f32, c.height as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::bake::testutil::facing_camera;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::math::Vec3;

    #[test]
    fn a_point_within_the_radius_of_a_camera_is_clear_only_where_another_sees_it_beyond_it() {
        let (scene, cam) = facing_camera();
        let o = cam.origin;
        // Alone, the camera keeps nothing within its radius, in front of it
        // or behind: it does not draw that near.
        let balls = CameraBalls::new(&[cam], 1.0);
        assert!(!balls.clear(o));
        assert!(!balls.clear([o[0] + 0.99, o[1], o[2]]));
        assert!(balls.clear([o[0], o[1], o[2] - 1.01]));
        assert!(balls.clear([0.0; 3]));
        assert!(CameraBalls::new(&[], 1.0).clear(o));
        // A second camera 3 units further back on the same axis sees what
        // lies before and just behind the first from more than a unit
        // away, but not what lies within a unit of itself.
        let eye = Vec3::new(0.0, -7.0, 0.0);
        let c2w = look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
        let far = RasterCamera::new(&Camera::from_fov(cam.width, cam.height, 1.0, c2w), &scene);
        let f = far.origin;
        let gap = ((o[0] - f[0]).powi(2) + (o[1] - f[1]).powi(2) + (o[2] - f[2]).powi(2)).sqrt();
        let ahead = |d: f32| [0, 1, 2].map(|k| o[k] + d * (o[k] - f[k]) / gap);
        let radius = gap / 3.0;
        let (one, both) = (CameraBalls::new(&[cam], radius), CameraBalls::new(&[cam, far], radius));
        for d in [0.5, -0.5] {
            let p = ahead(d * radius);
            assert!(!one.clear(p), "{d}: the first camera alone does not see it");
            assert!(both.clear(p), "{d}: the far camera sees it {} away", gap + d * radius);
        }
        assert!(!both.clear(ahead(-gap + 0.5 * radius)), "half the radius in front of the far camera");
    }
}
