//! Depth maps fused into a truncated signed distance volume over the crop
//! box (Curless and Levoy 1996, as KinectFusion and nerfstudio's `tsdf`
//! exporter do): each grid point takes the running mean, over the views
//! that see it, of its distance in front of the surface the view draws,
//! clipped to one truncation band. A point every view sees only from
//! behind a surface is inside; a point no view sees is outside.

use rayon::prelude::*;

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Vec3;
use crate::engine::mesh::isosurface::Grid;
use crate::engine::models::splats::crop::CropBox;

/// A grid of points over an oriented box, the same spacing on each axis.
#[derive(Clone, Debug, PartialEq)]
pub struct Volume {
    /// World position of grid point (0, 0, 0).
    pub origin: [f32; 3],
    /// The box's unit axes (rows), the grid's x, y and z.
    pub axes: [[f32; 3]; 3],
    pub dims: [usize; 3],
    /// World units between neighbouring grid points.
    pub spacing: f32,
}

impl Volume {
    /// The grid over `crop` with `resolution` points along its longest side.
    pub fn over(crop: &CropBox, resolution: usize) -> Self {
        let longest = crop.half.iter().cloned().fold(0.0f32, f32::max);
        let spacing = 2.0 * longest / (resolution.max(2) - 1) as f32;
        let dims = crop.half.map(|h| ((2.0 * h / spacing).ceil() as usize + 1).clamp(2, resolution.max(2)));
        let mut origin = Vec3::from_array(crop.centre);
        for a in 0..3 {
            origin = origin - Vec3::from_array(crop.axes[a]) * (0.5 * (dims[a] - 1) as f32 * spacing);
        }
        Self { origin: origin.to_array(), axes: crop.axes, dims, spacing }
    }

    pub fn len(&self) -> usize {
        self.dims.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// World position of grid coordinates `g` (fractional ones too).
    pub fn world(&self, g: [f32; 3]) -> [f32; 3] {
        let mut p = self.origin;
        for a in 0..3 {
            for (k, pk) in p.iter_mut().enumerate() {
                *pk += g[a] * self.spacing * self.axes[a][k];
            }
        }
        p
    }

    /// The same grid with one more point on every side (where a border
    /// of outside goes).
    pub fn padded(&self) -> Volume {
        Volume { origin: self.world([-1.0; 3]), dims: self.dims.map(|d| d + 2), ..self.clone() }
    }
}

/// What the views said about one grid point.
#[derive(Clone, Copy, Debug, Default)]
struct Cell {
    /// Sum of the clipped signed distances, in truncation bands.
    sum: f32,
    /// Views that saw the point in front of, or within a band of, a surface.
    seen: u16,
    /// Views that saw it only from behind a surface.
    behind: u16,
}

/// A truncated signed distance volume being filled.
pub struct Fusion {
    pub volume: Volume,
    cells: Vec<Cell>,
    /// The truncation band, world units.
    pub band: f32,
}

impl Fusion {
    pub fn new(volume: Volume, band: f32) -> Self {
        Self { cells: vec![Cell::default(); volume.len()], volume, band }
    }

    /// Adds a view: `surface[y * width + x]` is how far along pixel (x, y)'s
    /// ray the surface lies (world units), or `None` where the ray meets
    /// nothing. Lens distortion is ignored: the views are made undistorted.
    pub fn add(&mut self, camera: &Camera, surface: &[Option<f32>]) {
        let v = &self.volume;
        let m = &camera.c2w;
        let o = camera.origin();
        // Camera coordinates are linear in the grid coordinates.
        let to_cam = |d: Vec3| [0, 1, 2].map(|k| Vec3::new(m[0][k], m[1][k], m[2][k]).dot(d));
        let c0 = to_cam(Vec3::from_array(v.origin) - o);
        let step = v.axes.map(|a| to_cam(Vec3::from_array(a) * v.spacing));
        let (w, h) = (camera.width as usize, camera.height as usize);
        let [nx, ny, _] = v.dims;
        let band = self.band;
        self.cells.par_chunks_mut(nx * ny).enumerate().for_each(|(z, slab)| {
            for y in 0..ny {
                for x in 0..nx {
                    let c = [0, 1, 2]
                        .map(|k| c0[k] + x as f32 * step[0][k] + y as f32 * step[1][k] + z as f32 * step[2][k]);
                    let depth = -c[2];
                    if depth <= 1e-6 {
                        continue;
                    }
                    let u = camera.fx * c[0] / depth + camera.cx;
                    let t = -camera.fy * c[1] / depth + camera.cy;
                    if !(u >= 0.0 && t >= 0.0 && u < w as f32 && t < h as f32) {
                        continue;
                    }
                    let dist = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                    let cell = &mut slab[y * nx + x];
                    let sdf = match surface[t as usize * w + u as usize] {
                        None => band,
                        Some(s) => s - dist,
                    };
                    if sdf >= -band {
                        cell.sum += (sdf / band).min(1.0);
                        cell.seen = cell.seen.saturating_add(1);
                    } else {
                        cell.behind = cell.behind.saturating_add(1);
                    }
                }
            }
        });
    }

    /// The fused values with a border of outside around them (so that the
    /// surface closes where the object meets the box), and the volume that
    /// grid is on.
    pub fn grid(&self) -> (Grid, Volume) {
        let [nx, ny, nz] = self.volume.dims;
        let mut grid = Grid::bordered(self.volume.dims);
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let c = self.cells[(z * ny + y) * nx + x];
                    let v = if c.seen > 0 {
                        c.sum / c.seen as f32
                    } else if c.behind > 0 {
                        -1.0
                    } else {
                        1.0
                    };
                    grid.set_inner(x, y, z, v);
                }
            }
        }
        (grid, self.volume.padded())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::look_at;
    use crate::engine::mesh::isosurface::extract;

    /// Where each pixel's ray meets a sphere at the origin.
    fn sphere_depths(camera: &Camera, r: f32) -> Vec<Option<f32>> {
        let mut out = Vec::new();
        for y in 0..camera.height {
            for x in 0..camera.width {
                let ray = camera.pixel_ray(x, y);
                let b = ray.origin.dot(ray.dir);
                let c = ray.origin.dot(ray.origin) - r * r;
                let disc = b * b - c;
                out.push((disc >= 0.0).then(|| -b - disc.sqrt()));
            }
        }
        out
    }

    #[test]
    fn a_volume_covers_its_box_with_even_spacing() {
        let crop = CropBox {
            centre: [1.0, 2.0, 3.0],
            axes: [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            half: [1.0, 0.5, 0.25],
        };
        let v = Volume::over(&crop, 41);
        assert_eq!(v.dims, [41, 21, 11]);
        assert!((v.spacing - 0.05).abs() < 1e-6);
        let far = v.world([40.0, 20.0, 10.0]);
        let near = v.world([0.0; 3]);
        for k in 0..3 {
            assert!((0.5 * (far[k] + near[k]) - crop.centre[k]).abs() < 1e-5, "{near:?} {far:?}");
        }
        assert!((far[1] - near[1] - 2.0).abs() < 1e-5 && (near[0] - far[0] - 1.0).abs() < 1e-5);
    }

    #[test]
    fn views_of_a_sphere_fuse_into_that_sphere() {
        let r = 0.5;
        let crop =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [0.8; 3] };
        let mut fusion = Fusion::new(Volume::over(&crop, 48), 0.1);
        for i in 0..24 {
            let (az, el) = (i as f32 * 0.9, ((i % 5) as f32 - 2.0) * 0.5);
            let eye = Vec3::new(az.cos() * el.cos(), el.sin(), az.sin() * el.cos()) * 2.5;
            let cam = Camera::from_fov(64, 64, 0.8, look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap());
            fusion.add(&cam, &sphere_depths(&cam, r));
        }
        let (grid, volume) = fusion.grid();
        let mesh = extract(&grid);
        assert!(mesh.is_closed());
        let s = volume.spacing as f64;
        let (area, want) = (mesh.area() * s * s, 4.0 * std::f64::consts::PI * (r as f64).powi(2));
        assert!((area / want - 1.0).abs() < 0.05, "area {area} against {want}");
        for p in &mesh.positions {
            let w = volume.world(*p);
            let d = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
            assert!((d - r).abs() < 1.5 * volume.spacing, "a vertex {d} from the centre");
        }
    }
}
