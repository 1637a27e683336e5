//! The space around the training cameras is kept clear of Gaussians.
//!
//! A capture's near bound says nothing lies that close to a camera along
//! its rays, and the field is rendered from there on, so it draws nothing
//! nearer. Beside and behind a camera no photo looks, so a Gaussian there
//! (a far wall that the field set on the other side of the walk, or one
//! placed past the photos' edges) is never checked by the fit, and a new
//! view between two photos looks straight into it.

use crate::engine::dataset::Dataset;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::splats::raster::RasterCamera;

/// Balls around the training cameras' centres (model units).
pub(super) struct CameraBalls {
    origins: Vec<[f32; 3]>,
    radius2: f32,
}

impl CameraBalls {
    /// Balls of `radius` around the centres of `cams`.
    pub fn new(cams: &[RasterCamera], radius: f32) -> Self {
        Self { origins: cams.iter().map(|c| c.origin).collect(), radius2: radius * radius }
    }

    /// Balls of `scene`'s near bound around the cameras of `ds`'s `frames`
    /// (in `scene`'s model units).
    pub fn around(ds: &Dataset, frames: &[usize], scene: &Scene) -> Self {
        let cams: Vec<RasterCamera> = frames.iter().map(|&f| RasterCamera::new(&ds.frames[f].camera, scene)).collect();
        Self::new(&cams, scene.near)
    }

    /// Whether `at` is outside every ball.
    pub fn clear(&self, at: [f32; 3]) -> bool {
        self.origins.iter().all(|o| {
            let d = [at[0] - o[0], at[1] - o[1], at[2] - o[2]];
            d[0] * d[0] + d[1] * d[1] + d[2] * d[2] >= self.radius2
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::bake::testutil::facing_camera;

    #[test]
    fn a_point_within_the_radius_of_a_camera_is_not_clear() {
        let (_, cam) = facing_camera();
        let balls = CameraBalls::new(&[cam], 1.0);
        let o = cam.origin;
        assert!(!balls.clear(o));
        assert!(!balls.clear([o[0] + 0.99, o[1], o[2]]));
        assert!(balls.clear([o[0], o[1], o[2] - 1.01]));
        assert!(balls.clear([0.0; 3]));
        assert!(CameraBalls::new(&[], 1.0).clear(o));
    }
}
