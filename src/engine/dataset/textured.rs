//! A textured procedural scene for tests of pose estimation: a ball and a
//! ground plane covered in solid noise (contour bands of a few octaves of
//! value noise), so a feature detector such as SIFT finds plenty of
//! distinctive blobs and corners, which the smooth [`super::synthetic::BallScene`]
//! lacks. Rendered exactly (ray casting through the engine's cameras) from a
//! ring of cameras above the ground.

use crate::engine::dataset::{Dataset, DatasetFormat, Frame, Image, MaskUse};
use crate::engine::geometry::camera::{Camera, look_at};
use crate::engine::geometry::math::{Aabb, Ray, Vec3};

/// Ball of radius 0.6 at the origin on a ground plane at z = -0.6, which
/// ends at |x|, |y| = 2.2; white beyond. Cameras on a ring of radius 3.
#[derive(Clone, Debug)]
pub struct TexturedScene {
    pub width: u32,
    pub height: u32,
    pub views: usize,
    /// Horizontal field of view, radians.
    pub fov: f32,
}

impl Default for TexturedScene {
    fn default() -> Self {
        Self { width: 320, height: 240, views: 16, fov: 0.9 }
    }
}

const RADIUS: f32 = 0.6;
const GROUND: f32 = -0.6;
const GROUND_HALF: f32 = 2.2;
const RING: f32 = 3.0;

impl TexturedScene {
    /// The camera of view `k`: around the ring, alternately higher and lower.
    pub fn camera(&self, k: usize) -> Camera {
        let a = k as f32 / self.views as f32 * std::f32::consts::TAU;
        let z = if k.is_multiple_of(2) { 1.0 } else { 1.6 };
        let eye = Vec3::new(RING * a.cos(), RING * a.sin(), z);
        let target = Vec3::new(0.0, 0.0, -0.2);
        let pose = look_at(eye, target, Vec3::new(0.0, 0.0, 1.0)).unwrap_or([[0.0; 4]; 3]);
        Camera::from_fov(self.width, self.height, self.fov, pose)
    }

    /// Colour seen along `ray` (white where it meets nothing).
    pub fn shade(&self, ray: &Ray) -> [f32; 3] {
        let mut best: Option<(f32, [f32; 3])> = None;
        let b = ray.origin.dot(ray.dir);
        let c = ray.origin.dot(ray.origin) - RADIUS * RADIUS;
        let disc = b * b - c;
        if disc >= 0.0 {
            let t = -b - disc.sqrt();
            if t > 0.0 {
                let p = ray.at(t);
                let n = fbm(p * 7.0);
                let band = 0.5 + 0.5 * (n * 18.0).sin();
                best = Some((t, [0.15 + 0.8 * band, 0.25 + 0.5 * n, 0.9 - 0.7 * band]));
            }
        }
        if ray.dir.z < -1e-6 {
            let t = (GROUND - ray.origin.z) / ray.dir.z;
            let p = ray.at(t);
            if t > 0.0 && p.x.abs() < GROUND_HALF && p.y.abs() < GROUND_HALF && best.is_none_or(|(tb, _)| t < tb) {
                let n = fbm(Vec3::new(p.x * 4.0 + 31.0, p.y * 4.0 + 17.0, 0.5));
                let band = 0.5 + 0.5 * (n * 14.0).sin();
                let checker = (((p.x * 2.0).floor() + (p.y * 2.0).floor()) as i32).rem_euclid(2) as f32;
                best = Some((t, [0.2 + 0.6 * band, 0.15 + 0.35 * checker + 0.3 * n, 0.1 + 0.3 * band]));
            }
        }
        best.map_or([1.0; 3], |(_, c)| c.map(|v| v.clamp(0.0, 1.0)))
    }

    /// Renders every view; all are training views (pose estimation uses
    /// them all), the last four also make the test split.
    pub fn dataset(&self) -> Dataset {
        self.dataset_of((0..self.views).map(|k| self.frame(k, self.camera(k))).collect())
    }

    /// The camera of view `k` of a forward-facing capture (as LLFF's): the
    /// `views` cameras on a grid of rows of `ceil(sqrt(views))`, 0.8 wide
    /// and 0.5 high, in a plane 3 units out on +x, looking towards the
    /// ball with axes that spread within 2 degrees of their mean (they
    /// would meet about 15 units away).
    pub fn forward_camera(&self, k: usize) -> Camera {
        let cols = (self.views as f32).sqrt().ceil().max(1.0) as usize;
        let rows = self.views.div_ceil(cols).max(1);
        let along = |i: usize, n: usize| if n > 1 { i as f32 / (n - 1) as f32 - 0.5 } else { 0.0 };
        let (dy, dz) = (0.8 * along(k % cols, cols), 0.5 * along(k / cols, rows));
        let eye = Vec3::new(RING, dy, 1.0 + dz);
        let target = Vec3::new(0.0, 0.8 * dy, -0.2 + 0.8 * dz);
        let pose = look_at(eye, target, Vec3::new(0.0, 0.0, 1.0)).unwrap_or([[0.0; 4]; 3]);
        Camera::from_fov(self.width, self.height, self.fov, pose)
    }

    /// The same scene captured forward-facing ([`TexturedScene::forward_camera`]),
    /// in LLFF's manner: the nearest surface is about 2.2 units in front of
    /// the cameras (near bound 1.5), the white beyond the ground is at
    /// infinity. Every fourth view (from the third) is held out.
    pub fn forward_facing(&self) -> Dataset {
        let frames: Vec<Frame> = (0..self.views).map(|k| self.frame(k, self.forward_camera(k))).collect();
        let n = frames.len();
        let held_out: Vec<usize> = (0..n).filter(|k| k % 4 == 2).collect();
        Dataset {
            train: (0..n).filter(|k| k % 4 != 2).collect(),
            val: held_out.clone(),
            test: held_out,
            near: 1.5,
            far: 12.0,
            ..self.dataset_of(frames)
        }
    }

    /// View `k` seen by `camera`, rendered exactly.
    fn frame(&self, k: usize, camera: Camera) -> Frame {
        let mut rgba = Vec::with_capacity((self.width * self.height * 4) as usize);
        for j in 0..self.height {
            for i in 0..self.width {
                // 3x3 samples a pixel: edges without aliasing, which
                // would move features by fractions of a pixel.
                let mut c = [0.0f32; 3];
                for (sx, sy) in (0..9).map(|s| ((s % 3) as f32, (s / 3) as f32)) {
                    let ray = camera.ray(i as f32 + (sx + 0.5) / 3.0, j as f32 + (sy + 0.5) / 3.0);
                    let v = self.shade(&ray);
                    (0..3).for_each(|k| c[k] += v[k] / 9.0);
                }
                rgba.extend(c.iter().map(|v| (v * 255.0).round() as u8).chain([255]));
            }
        }
        let image = Image { width: self.width, height: self.height, rgba, has_alpha: false };
        Frame { name: format!("view_{k:03}"), path: format!("view_{k:03}.png").into(), camera, image, mask: None }
    }

    /// A dataset of `frames`, all trained on, the last four also held out.
    fn dataset_of(&self, frames: Vec<Frame>) -> Dataset {
        let n = frames.len();
        Dataset {
            format: DatasetFormat::Blender,
            root: ".".into(),
            frames,
            train: (0..n).collect(),
            val: (n.saturating_sub(4)..n).collect(),
            test: (n.saturating_sub(4)..n).collect(),
            near: 0.5,
            far: 8.0,
            aabb: Aabb { min: Vec3::new(-GROUND_HALF, -GROUND_HALF, GROUND - 0.1), max: Vec3::splat(GROUND_HALF) },
            background: [1.0; 3],
            warnings: Vec::new(),
            masks: MaskUse::Off,
            mask_folder: None,
        }
    }

    /// Writes the views as plain RGB PNG photos, `view_000.png`, ... into
    /// `dir` (no poses: what a user with a camera has).
    pub fn write_photos(&self, dir: &std::path::Path) -> std::io::Result<Vec<Camera>> {
        std::fs::create_dir_all(dir)?;
        let ds = self.dataset();
        for f in &ds.frames {
            let rgb: Vec<u8> = f.image.rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
            let img = image::RgbImage::from_raw(f.image.width, f.image.height, rgb)
                .ok_or_else(|| std::io::Error::other("image size"))?;
            img.save(dir.join(format!("{}.png", f.name))).map_err(std::io::Error::other)?;
        }
        Ok(ds.frames.into_iter().map(|f| f.camera).collect())
    }
}

/// Three octaves of value noise, in [0, 1).
fn fbm(p: Vec3) -> f32 {
    (value_noise(p) * 0.55 + value_noise(p * 2.03) * 0.3 + value_noise(p * 4.1) * 0.15).clamp(0.0, 0.999)
}

/// Trilinearly interpolated hash values on the integer lattice, smoothstepped.
fn value_noise(p: Vec3) -> f32 {
    let (fx, fy, fz) = (p.x.floor(), p.y.floor(), p.z.floor());
    let (ix, iy, iz) = (fx as i32, fy as i32, fz as i32);
    let s = |t: f32| t * t * (3.0 - 2.0 * t);
    let (tx, ty, tz) = (s(p.x - fx), s(p.y - fy), s(p.z - fz));
    let h = |x: i32, y: i32, z: i32| {
        let mut v = (x as u32).wrapping_mul(0x8da6_b343)
            ^ (y as u32).wrapping_mul(0xd816_3841)
            ^ (z as u32).wrapping_mul(0xcb1a_b31f);
        v ^= v >> 15;
        v = v.wrapping_mul(0x2c1b_3c6d);
        v ^= v >> 12;
        (v & 0xffff) as f32 / 65536.0
    };
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(h(ix, iy, iz), h(ix + 1, iy, iz), tx);
    let x10 = lerp(h(ix, iy + 1, iz), h(ix + 1, iy + 1, iz), tx);
    let x01 = lerp(h(ix, iy, iz + 1), h(ix + 1, iy, iz + 1), tx);
    let x11 = lerp(h(ix, iy + 1, iz + 1), h(ix + 1, iy + 1, iz + 1), tx);
    lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_view_sees_the_ball_and_the_ground_with_texture() {
        let scene = TexturedScene { width: 48, height: 36, views: 6, fov: 0.9 };
        let ds = scene.dataset();
        assert_eq!(ds.frames.len(), 6);
        for f in &ds.frames {
            // The centre pixel looks at the ball (not white), the image has
            // many distinct colours (texture), and the corners see something.
            let px = |i: u32, j: u32| &f.image.rgba[((j * 48 + i) * 4) as usize..][..3];
            assert_ne!(px(24, 18), [255, 255, 255], "{}", f.name);
            let distinct: std::collections::HashSet<_> = f.image.rgba.chunks_exact(4).collect();
            assert!(distinct.len() > 300, "{}: {} colours", f.name, distinct.len());
        }
    }

    #[test]
    fn noise_is_bounded_and_continuous() {
        for k in 0..500 {
            let p = Vec3::new(k as f32 * 0.37 - 50.0, k as f32 * 0.11, -(k as f32) * 0.23);
            let v = fbm(p);
            assert!((0.0..1.0).contains(&v));
            let d = (fbm(p + Vec3::splat(1e-3)) - v).abs();
            assert!(d < 0.02, "jump of {d} at {p:?}");
        }
    }
}
