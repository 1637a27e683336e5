//! A textured triangle mesh from a trained model (field or splats), inside
//! a crop box: the model rendered from where its training cameras stood;
//! the surface a level set of the model's density where it exposes one,
//! else the views' depths fused into a truncated signed distance volume;
//! that surface extracted, small pieces dropped, simplified to a triangle
//! budget, laid out in a texture atlas and coloured from the same views
//! (the model's mean appearance). `export` writes it as GLB and USDZ.

pub mod atlas;
pub mod bake;
pub mod clean;
pub mod export;
pub mod fit;
pub mod fuse;
pub mod isosurface;
pub mod level;
pub mod raster;
pub mod usdc;
pub mod views;

use std::sync::atomic::{AtomicBool, Ordering};

use crate::engine::geometry::math::Vec3;
use crate::engine::models::Model;
use crate::engine::models::splats::crop::{CropBox, CropError};

/// A mesh with one texture: world positions, triangles, each triangle's
/// corners' texture coordinates (u right, v down, in [0, 1]) and the
/// texture (RGB in [0, 1], row-major, `texture_size` square).
#[derive(Clone, Debug, PartialEq)]
pub struct TexturedMesh {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    pub uvs: Vec<[[f32; 2]; 3]>,
    pub texture: Vec<[f32; 3]>,
    pub texture_size: u32,
}

impl TexturedMesh {
    /// The texture at `(u, v)`, bilinear, clamped to its edge (no mipmaps).
    pub fn sample(&self, u: f32, v: f32) -> [f32; 3] {
        let (at, w) = bilinear(self.texture_size, u, v);
        [0, 1, 2].map(|k| (0..4).map(|i| w[i] * self.texture[at[i]][k]).sum())
    }
}

/// The four texels a bilinear read of a `size`-texel square texture at
/// `(u, v)` blends, clamped to its edge, and their weights.
pub fn bilinear(size: u32, u: f32, v: f32) -> ([usize; 4], [f32; 4]) {
    let n = size as i64;
    let (x, y) = (u * n as f32 - 0.5, v * n as f32 - 0.5);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let at = |dx: i64, dy: i64| {
        let (px, py) = ((x0 as i64 + dx).clamp(0, n - 1), (y0 as i64 + dy).clamp(0, n - 1));
        (py * n + px) as usize
    };
    ([at(0, 0), at(1, 0), at(0, 1), at(1, 1)], [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy])
}

/// How a mesh is made.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshOptions {
    /// Most triangles.
    pub triangles: usize,
    /// Texture side, texels.
    pub texture: u32,
    /// Grid points along the crop box's longest side.
    pub resolution: usize,
    /// Views rendered (at most; fewer when the model knows fewer cameras).
    pub views: usize,
    /// Their side, pixels.
    pub view_size: u32,
    /// Pieces with less than this share of the surface's area go.
    pub min_piece: f64,
}

impl Default for MeshOptions {
    fn default() -> Self {
        Self { triangles: 200_000, texture: 2048, resolution: 256, views: 40, view_size: 384, min_piece: 0.01 }
    }
}

/// Why a mesh cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// An option out of range: its name and why.
    #[error("{0}: {1}")]
    Option(&'static str, String),
    #[error(transparent)]
    Crop(#[from] CropError),
    #[error("no surface inside the crop box: the model draws nothing solid there")]
    Empty,
    #[error("cancelled")]
    Cancelled,
}

impl MeshOptions {
    /// The options' errors, naming the option.
    pub fn check(&self) -> Result<(), MeshError> {
        let most = atlas::capacity(self.texture);
        let bad = |name, why: String| Err(MeshError::Option(name, why));
        if !(64..=8192).contains(&self.texture) {
            return bad("texture", format!("{}: the texture's side must be 64 to 8192 texels", self.texture));
        }
        if self.triangles == 0 || self.triangles > most {
            return bad(
                "triangles",
                format!("{}: must be 1 to {most} for a {}-texel texture", self.triangles, self.texture),
            );
        }
        if !(16..=512).contains(&self.resolution) {
            return bad("resolution", format!("{}: must be 16 to 512 grid points", self.resolution));
        }
        if !(1..=400).contains(&self.views) {
            return bad("views", format!("{}: must be 1 to 400", self.views));
        }
        if !(32..=2048).contains(&self.view_size) {
            return bad("view_size", format!("{}: must be 32 to 2048 pixels", self.view_size));
        }
        if !(0.0..1.0).contains(&self.min_piece) {
            return bad("min_piece", format!("{}: must be in [0, 1)", self.min_piece));
        }
        Ok(())
    }
}

/// The stages of [`make`], for progress.
pub const STAGES: [&str; 4] =
    ["rendering views", "finding the surface", "extracting the surface", "baking the texture"];

/// A textured mesh of `model` inside `crop`, and what making it took; its
/// texture fitted to the model's views, then to `photos` where given (the
/// training photos, [`views::photos`]: they hold the detail a field
/// smooths; docs/design/mesh.md). `progress(stage, done)`
/// reports the stage (an index into [`STAGES`]) and the share of the
/// whole done; `cancel` stops it between views and stages.
pub fn make(
    model: &dyn Model,
    crop: &CropBox,
    options: &MeshOptions,
    photos: &[views::SurfaceView],
    progress: &mut dyn FnMut(usize, f32),
    cancel: &AtomicBool,
) -> Result<(TexturedMesh, MeshStats), MeshError> {
    options.check()?;
    crop.check()?;
    let stop = || if cancel.load(Ordering::Relaxed) { Err(MeshError::Cancelled) } else { Ok(()) };
    let cameras = views::cameras(model, crop, options.views, options.view_size);
    let mut rendered = Vec::with_capacity(cameras.len());
    for (i, camera) in cameras.iter().enumerate() {
        progress(0, 0.7 * i as f32 / cameras.len() as f32);
        rendered.push(views::render(model, camera, cancel).ok_or(MeshError::Cancelled)?);
    }
    stop()?;
    progress(1, 0.7);
    let volume = fuse::Volume::over(crop, options.resolution);
    // A field's own density where it has one; else the views' depths fused.
    let density = |p: &[[f32; 3]]| model.density(p);
    let level = level::level(&density, &rendered);
    let (grid, on, refine) = match level.and_then(|l| level::grid(&density, &volume, l).map(|g| (g, l))) {
        Some((grid, l)) => (grid, volume.padded(), Some(l)),
        None => {
            let mut fusion = fuse::Fusion::new(volume.clone(), 4.0 * volume.spacing);
            for v in &rendered {
                fusion.add(&v.camera, &v.surface);
            }
            let (grid, on) = fusion.grid();
            (grid, on, None)
        }
    };
    stop()?;
    progress(2, 0.8);
    let (mut raw, edges) = isosurface::extract_on_edges(&grid);
    if let Some(l) = refine {
        level::refine(&density, &volume, l, &grid, &mut raw, &edges, level::REFINE_STEPS);
    }
    let world =
        isosurface::Mesh { positions: raw.positions.iter().map(|p| on.world(*p)).collect(), triangles: raw.triangles };
    let kept = clean::drop_small_pieces(&world, options.min_piece);
    let mesh = clean::simplify(&kept, options.triangles);
    let solid = rendered.iter().map(|v| v.surface.iter().filter(|s| s.is_some()).count()).sum::<usize>();
    let mut stats = MeshStats {
        views: rendered.len(),
        solid: solid as f64 / rendered.iter().map(|v| v.surface.len()).sum::<usize>().max(1) as f64,
        grid: volume.dims,
        level,
        extracted: world.triangles.len(),
        kept: kept.triangles.len(),
        fit: None,
        photos: None,
    };
    if mesh.triangles.is_empty() {
        return Err(MeshError::Empty);
    }
    stop()?;
    progress(3, 0.9);
    let layout = atlas::layout(mesh.triangles.len(), options.texture)
        .map_err(|e| MeshError::Option("triangles", e.to_string()))?;
    let texture = bake::texture(&mesh, &layout, &rendered, 3.0 * volume.spacing);
    stop()?;
    progress(3, 0.95);
    let mut textured = TexturedMesh {
        positions: mesh.positions,
        triangles: mesh.triangles,
        uvs: layout.uvs,
        texture,
        texture_size: options.texture,
    };
    stats.fit = Some(fit::fit(&mut textured, &rendered, 1, fit::PRIOR, fit::ITERATIONS));
    if !photos.is_empty() {
        stop()?;
        stats.photos = Some(fit::fit(&mut textured, photos, fit::PHOTO_SAMPLES, fit::PRIOR, fit::ITERATIONS));
    }
    progress(3, 1.0);
    Ok((textured, stats))
}

/// What [`make`] did, to report.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshStats {
    /// Views rendered, and the share of their pixels that met a surface.
    pub views: usize,
    pub solid: f64,
    /// The volume's grid points along each axis.
    pub grid: [usize; 3],
    /// The density level the surface was taken at (`None`: depths fused).
    pub level: Option<f32>,
    /// Triangles extracted, and left once small pieces went (before simplifying).
    pub extracted: usize,
    pub kept: usize,
    /// The texture's fit to the model's views, then to the photos.
    pub fit: Option<fit::FitStats>,
    pub photos: Option<fit::FitStats>,
}

/// How a mesh is placed in the files written for other tools: upright (the
/// crop box's z, the capture's up, becomes +y), the training cameras'
/// front towards +z (where a viewer's default camera looks from), standing
/// on y = 0 centred over the origin, its longest side `size` metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// Rows: the output x, y and z axes in world coordinates.
    pub axes: [[f32; 3]; 3],
    /// The world point that goes to the origin.
    pub origin: [f32; 3],
    pub scale: f32,
}

impl Placement {
    /// Upright for `crop`, facing `front` (world; any direction not along
    /// the up), `size` metres along its longest side.
    pub fn new(mesh: &TexturedMesh, crop: &CropBox, front: Option<[f32; 3]>, size: f32) -> Self {
        let y = Vec3::from_array(crop.axes[2]);
        let flat = |f: Vec3| (f - y * f.dot(y)).normalized();
        let z = front.map(Vec3::from_array).and_then(flat).unwrap_or(Vec3::from_array(crop.axes[0]));
        let x = y.cross(z);
        let axes = [x, y, z].map(|a| a.to_array());
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for p in &mesh.positions {
            let q = [x, y, z].map(|a| a.dot(Vec3::from_array(*p)));
            (0..3).for_each(|k| (lo[k], hi[k]) = (lo[k].min(q[k]), hi[k].max(q[k])));
        }
        let longest = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f32, f32::max);
        let base = [0.5 * (lo[0] + hi[0]), lo[1], 0.5 * (lo[2] + hi[2])];
        let origin = (x * base[0] + y * base[1] + z * base[2]).to_array();
        Self { axes, origin, scale: if longest > 0.0 { size / longest } else { 1.0 } }
    }

    /// World point `p` where the files put it.
    pub fn apply(&self, p: [f32; 3]) -> [f32; 3] {
        let d = Vec3::from_array(p) - Vec3::from_array(self.origin);
        self.axes.map(|a| self.scale * Vec3::from_array(a).dot(d))
    }
}
