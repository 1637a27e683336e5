//! What a dataset makes of the geometry: the [`Scene`] a model is built
//! for and the [`CameraRig`] of its training cameras. Here, not in
//! `geometry`, so that geometry knows nothing of datasets.

use super::{Dataset, Split};
use crate::engine::geometry::rig::CameraRig;
use crate::engine::geometry::scene::Scene;

impl Dataset {
    /// The scene of this dataset: its box, bounds and training rig, and
    /// whether some training images have transparent pixels.
    pub fn scene(&self) -> Scene {
        let transparent = self.train.iter().any(|&i| self.frames[i].image.has_transparent_pixels());
        Scene { transparent, rig: self.rig(), ..Scene::from_bounds(self.aabb, self.near, self.far) }
    }

    /// The rig of this dataset's training cameras (`None` without any).
    pub fn rig(&self) -> Option<CameraRig> {
        let poses: Vec<_> = self.split_frames(Split::Train).map(|f| f.camera.c2w).collect();
        let cam = &self.split_frames(Split::Train).next()?.camera;
        let mut rig = CameraRig::from_poses(&poses, self.near, self.far, self.centre())?;
        for (fr, &i) in rig.frames.iter_mut().zip(&self.train) {
            fr.image = i as u32;
        }
        let fov_deg = (2.0 * (0.5 * cam.width as f32 / cam.fx).atan()).to_degrees();
        Some(CameraRig { image: [cam.width, cam.height], fov_deg, ..rig })
    }
}
