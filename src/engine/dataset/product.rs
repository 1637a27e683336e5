//! The demo scene (`radiance demo`, `POST /v1/demo`): a product shot taken
//! all around. A striped mug with a thin wall, a handle and a straw stands
//! on a round tiled mat; a ring of cameras above looks at it. The scene is
//! a signed distance field, sphere-traced and shaded (a light with soft
//! shadows, a sky term), 2x2 samples a pixel so that thin parts get their
//! partial coverage. Where a ray meets nothing the image is transparent.
//! The mat reaches past what every camera frames, so the automatic crop
//! has a room of sorts to cut away.

use rayon::prelude::*;

use super::synthetic::{RING_TEST_VIEWS, ring_dataset, ring_frame, ring_slot, write_blender};
use crate::engine::dataset::Dataset;
use crate::engine::geometry::camera::{Camera, look_at};
use crate::engine::geometry::math::{Aabb, Vec3};

/// The mat's top: the floor everything stands on.
const FLOOR: f32 = -0.45;
const MAT_RADIUS: f32 = 1.35;
const MUG_RADIUS: f32 = 0.3;
const MUG_HEIGHT: f32 = 0.6;
const WALL: f32 = 0.035;
/// Where the straw starts (inside the mug) and ends (above its rim).
const STRAW: [Vec3; 2] = [Vec3 { x: -0.08, y: 0.05, z: FLOOR + 0.1 }, Vec3 { x: -0.27, y: 0.14, z: FLOOR + 0.98 }];
const STRAW_RADIUS: f32 = 0.02;

/// The demo's size and cameras.
pub struct ProductScene {
    /// Pixels on each side of a view.
    pub size: u32,
    /// Training views (4 held-out views sit between them).
    pub views: usize,
}

impl Default for ProductScene {
    fn default() -> Self {
        Self { size: 96, views: 32 }
    }
}

/// What a point of the scene is made of.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Part {
    Mat,
    Mug,
    Handle,
    Straw,
    Coffee,
}

fn capped_cylinder(p: Vec3, radius: f32, z0: f32, z1: f32) -> f32 {
    let r = (p.x * p.x + p.y * p.y).sqrt() - radius;
    let h = (p.z - 0.5 * (z0 + z1)).abs() - 0.5 * (z1 - z0);
    let outside = Vec3::new(r.max(0.0), h.max(0.0), 0.0).norm();
    outside + r.max(h).min(0.0)
}

fn capsule(p: Vec3, a: Vec3, b: Vec3, radius: f32) -> f32 {
    let (pa, ba) = (p - a, b - a);
    let h = (pa.dot(ba) / ba.dot(ba)).clamp(0.0, 1.0);
    (pa - ba * h).norm() - radius
}

/// The distance to the nearest surface and what it is.
fn sdf(p: Vec3) -> (f32, Part) {
    let mat = capped_cylinder(p, MAT_RADIUS, FLOOR - 0.04, FLOOR);
    let outer = capped_cylinder(p, MUG_RADIUS, FLOOR, FLOOR + MUG_HEIGHT);
    let inner = capped_cylinder(p, MUG_RADIUS - WALL, FLOOR + 0.06, FLOOR + MUG_HEIGHT + 0.1);
    let mug = outer.max(-inner);
    let coffee = capped_cylinder(p, MUG_RADIUS - WALL, FLOOR + 0.06, FLOOR + 0.42);
    // The handle: a torus standing in the xz plane, outside the mug only.
    let q = p - Vec3::new(MUG_RADIUS + 0.1, 0.0, FLOOR + 0.32);
    let ring = ((q.x * q.x + q.z * q.z).sqrt() - 0.15).hypot(q.y) - 0.03;
    let handle = ring.max(-capped_cylinder(p, MUG_RADIUS - 0.01, FLOOR - 1.0, FLOOR + 2.0));
    let straw = capsule(p, STRAW[0], STRAW[1], STRAW_RADIUS);
    [(mug, Part::Mug), (handle, Part::Handle), (straw, Part::Straw), (coffee, Part::Coffee)]
        .into_iter()
        .fold((mat, Part::Mat), |best, c| if c.0 < best.0 { c } else { best })
}

/// The colour a part has at `p` (its texture).
fn albedo(part: Part, p: Vec3) -> Vec3 {
    let teal = Vec3::new(0.08, 0.5, 0.58);
    let cream = Vec3::new(0.95, 0.9, 0.8);
    match part {
        Part::Mat => {
            // Tiles of 0.18 with a darker grout line, warm and cool in turn.
            let (u, v) = (p.x / 0.18, p.y / 0.18);
            let grout = (u - u.round()).abs() < 0.06 || (v - v.round()).abs() < 0.06;
            let odd = (u.floor() + v.floor()).rem_euclid(2.0) > 0.5;
            match (grout, odd) {
                (true, _) => Vec3::new(0.3, 0.28, 0.26),
                (false, true) => Vec3::new(0.78, 0.62, 0.45),
                (false, false) => Vec3::new(0.88, 0.84, 0.76),
            }
        }
        Part::Mug => {
            let r = (p.x * p.x + p.y * p.y).sqrt();
            let band = (p.z - (FLOOR + 0.47)).abs() < 0.03;
            if r < MUG_RADIUS - 0.5 * WALL || p.z > FLOOR + MUG_HEIGHT - 0.005 {
                cream
            } else if band {
                Vec3::new(0.8, 0.12, 0.1)
            } else if ((p.y.atan2(p.x) / std::f32::consts::TAU * 12.0).floor() as i32).rem_euclid(2) == 0 {
                teal
            } else {
                cream
            }
        }
        Part::Handle => teal,
        Part::Straw => {
            let along = (p - STRAW[0]).dot((STRAW[1] - STRAW[0]).normalized().unwrap_or(Vec3::new(0.0, 0.0, 1.0)));
            if (along / 0.06).floor() as i32 % 2 == 0 {
                Vec3::new(0.85, 0.1, 0.15)
            } else {
                Vec3::new(0.97, 0.97, 0.95)
            }
        }
        Part::Coffee => Vec3::new(0.3, 0.17, 0.08),
    }
}

fn normal(p: Vec3) -> Vec3 {
    let e = 1e-4;
    let d = |dx: f32, dy: f32, dz: f32| sdf(p + Vec3::new(dx, dy, dz)).0;
    Vec3::new(d(e, 0.0, 0.0) - d(-e, 0.0, 0.0), d(0.0, e, 0.0) - d(0.0, -e, 0.0), d(0.0, 0.0, e) - d(0.0, 0.0, -e))
        .normalized()
        .unwrap_or(Vec3::new(0.0, 0.0, 1.0))
}

/// How much light reaches `p` from direction `light` (soft shadows).
fn lit(p: Vec3, light: Vec3) -> f32 {
    let mut t = 0.01;
    let mut seen: f32 = 1.0;
    for _ in 0..48 {
        let d = sdf(p + light * t).0;
        if d < 1e-4 {
            return 0.0;
        }
        seen = seen.min(8.0 * d / t);
        t += d.clamp(0.005, 0.2);
        if t > 3.0 {
            break;
        }
    }
    seen.clamp(0.0, 1.0)
}

/// The colour a ray from `o` along unit `d` sees, or `None` for nothing.
fn trace(o: Vec3, d: Vec3, near: f32, far: f32) -> Option<Vec3> {
    let mut t = near;
    for _ in 0..160 {
        let p = o + d * t;
        let (dist, part) = sdf(p);
        if dist < 2e-4 * t {
            let n = normal(p);
            let light = Vec3::new(0.45, -0.35, 0.82).normalized().expect("a direction");
            let sun = n.dot(light).max(0.0) * lit(p + n * 2e-3, light);
            let sky = 0.5 + 0.5 * n.z;
            return Some(albedo(part, p) * (0.25 + 0.2 * sky + 0.65 * sun));
        }
        t += dist;
        if t > far {
            break;
        }
    }
    None
}

impl ProductScene {
    fn camera(&self, k: usize, n: usize) -> Camera {
        let a = k as f32 / n as f32 * std::f32::consts::TAU;
        let height = if (k / 2).is_multiple_of(2) { 1.2 } else { 0.55 };
        let eye = Vec3::new(2.2 * a.cos(), 2.2 * a.sin(), height);
        let pose = look_at(eye, Vec3::new(0.0, 0.0, -0.15), Vec3::new(0.0, 0.0, 1.0)).unwrap_or([[0.0; 4]; 3]);
        Camera::from_fov(self.size, self.size, 0.66, pose)
    }

    /// A view's RGBA pixels, 2x2 samples each.
    fn render(&self, cam: &Camera) -> Vec<u8> {
        let rows: Vec<Vec<u8>> = (0..self.size)
            .into_par_iter()
            .map(|j| {
                let mut row = Vec::with_capacity(self.size as usize * 4);
                for i in 0..self.size {
                    let (mut sum, mut hits) = (Vec3::splat(0.0), 0.0f32);
                    for (sx, sy) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                        let ray = cam.ray(i as f32 + sx, j as f32 + sy);
                        if let Some(c) = trace(ray.origin, ray.dir, 0.5, 8.0) {
                            sum = sum + c;
                            hits += 1.0;
                        }
                    }
                    let alpha = hits / 4.0;
                    let c = if hits > 0.0 { sum * (1.0 / hits) } else { sum };
                    row.extend([c.x, c.y, c.z].map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8));
                    row.push((alpha * 255.0).round() as u8);
                }
                row
            })
            .collect();
        rows.concat()
    }

    /// Renders the dataset: `views` training views and 4 test views between them.
    pub fn dataset(&self) -> Dataset {
        let frames = (0..self.views + RING_TEST_VIEWS)
            .map(|k| {
                let camera = self.camera(ring_slot(k, self.views), 2 * self.views);
                let rgba = self.render(&camera);
                ring_frame(k, camera, self.size, rgba)
            })
            .collect();
        ring_dataset(frames, self.views, [1.0, 6.0], Aabb { min: Vec3::splat(-1.5), max: Vec3::splat(1.5) })
    }

    /// Writes the scene as a Blender-format dataset into `dir`.
    pub fn write_blender(&self, dir: &std::path::Path) -> std::io::Result<()> {
        write_blender(&self.dataset(), dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sdf_is_a_distance_bound_and_finds_each_part() {
        // Points on a grid: the distance never exceeds the true distance
        // to the surface (sphere tracing would overshoot), checked against
        // a dense sampling of where the sign changes nearby.
        for (p, part) in [
            (Vec3::new(1.0, 0.0, FLOOR - 0.02), Part::Mat),
            (Vec3::new(MUG_RADIUS - 0.5 * WALL, 0.0, FLOOR + 0.3), Part::Mug),
            (Vec3::new(MUG_RADIUS + 0.25, 0.0, FLOOR + 0.32), Part::Handle),
            ((STRAW[0] + STRAW[1]) * 0.5, Part::Straw),
            (Vec3::new(0.0, 0.0, FLOOR + 0.3), Part::Coffee),
        ] {
            let (d, found) = sdf(p);
            assert!(d < 0.0, "{p:?} is not inside the {part:?}: {d}");
            assert_eq!(found, part, "{p:?}");
        }
        // Lipschitz: |sdf(a) - sdf(b)| <= |a - b| over random pairs.
        let mut rng = crate::engine::rng::Rng::new(3);
        for _ in 0..20_000 {
            let a = Vec3::new(rng.f32() * 3.0 - 1.5, rng.f32() * 3.0 - 1.5, rng.f32() * 2.0 - 1.0);
            let b = a + Vec3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5) * 0.2;
            let (da, db) = (sdf(a).0, sdf(b).0);
            assert!((da - db).abs() <= (a - b).norm() * 1.001 + 1e-6, "{a:?} {b:?}: {da} {db}");
        }
    }

    #[test]
    fn every_view_shows_the_mug_on_its_mat_with_the_corners_clear() {
        let ds = ProductScene { size: 24, views: 4 }.dataset();
        assert_eq!((ds.train.len(), ds.test.len()), (4, 4));
        for f in &ds.frames {
            let px = |i: u32, j: u32| &f.image.rgba[((j * 24 + i) * 4) as usize..][..4];
            assert_eq!(px(0, 0)[3], 0, "{}: the sky corner is clear", f.name);
            let centre = px(12, 12);
            assert_eq!(centre[3], 255, "{}: the mug is in the middle", f.name);
            let covered = f.image.rgba.chunks(4).filter(|p| p[3] == 255).count();
            assert!(covered > 24 * 24 / 4, "{}: {covered} pixels covered", f.name);
            // Partial coverage somewhere: the silhouettes' samples.
            assert!(f.image.rgba.chunks(4).any(|p| p[3] > 0 && p[3] < 255), "{}", f.name);
        }
    }
}
