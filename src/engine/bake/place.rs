//! Placing: Gaussians where the field's rays through the training photos
//! end, with the field's colour, before any fitting (the module docs of
//! `bake`, stage 1).

use std::sync::atomic::{AtomicBool, Ordering};

use super::carve::{self, DepthGrid};
use super::clear::CameraBalls;
use super::{BakeError, BakeSettings};
use super::{Placed, in_frame};
use crate::engine::batch::RayOutput;
use crate::engine::dataset::Dataset;
use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::models::splats::gaussians::{Layout, SH_C0};
use crate::engine::models::splats::raster::RasterCamera;
use crate::engine::models::{Model, RenderOptions};
use crate::engine::rng::Rng;
use crate::engine::view::render_rays_with;

/// Gaussians each training photo places by default. A forward-facing
/// capture's photos all see one wall: a fixed total there is many samples
/// of the same surface, more Gaussians than the bake's minute can fit (each
/// step draws them all), so the default follows the photos.
pub const PER_PHOTO: usize = 1_500;

/// The most Gaussians placed by default.
pub const MOST_INITIAL: usize = 200_000;

/// The field's rays that placing `initial` Gaussians within the photos'
/// frames renders, with those of the margins past the frames ([`MARGIN`]).
pub fn placing_rays(initial: usize) -> u64 {
    (initial as f64 * (1.0 + 2.0 * MARGIN as f64).powi(2)).ceil() as u64
}

/// The opacity a field's ray must reach for a Gaussian to be placed where
/// it ends: a ray through an object's edge, or through a thin haze, has an
/// expected depth between surfaces, where a Gaussian would float.
const MIN_HIT_OPACITY: f32 = 0.9;
/// The opacity a ray must reach when no ray of any photo reaches
/// [`MIN_HIT_OPACITY`]: a young field (a few seconds of training on a slow
/// machine) is still translucent everywhere, and its splats start from
/// where its rays end all the same rather than not at all.
const YOUNG_HIT_OPACITY: f32 = 0.5;
/// The opacity below which a field's ray saw nothing (free space all
/// along it, for carving); between the two, it is not trusted either way.
const MISS_OPACITY: f32 = 0.1;
/// Gaussians are placed within this many times the farthest camera's
/// distance from the centre: a capture's field puts much of its background
/// at the far plane, where no two photos agree on it.
const FAR_RADIUS: f32 = 3.0;
/// A placed Gaussian with no neighbours (the background, seen by few
/// photos) gets this fraction of its grid cell's width.
const ISOLATED_SCALE: f32 = 0.5;
/// How far past each edge of a photo (as a fraction of its width and
/// height) the field's rays place Gaussians, at the photo's grid spacing:
/// a view near the photos sees past their frames, where the field has
/// filled in what it learnt nearby, and the splats would have nothing.
/// Those placed there are kept only where no photo saw them within its
/// frame (`carve`).
const MARGIN: f32 = 0.1;
/// A placed Gaussian's scale, as a fraction of its grid cell's width
/// (`docs/design/splats.md`, the median termination depth).
const INITIAL_SCALE: f32 = 0.25;

/// Places Gaussians where the field's rays end (module docs, stage 1):
/// where they reach [`MIN_HIT_OPACITY`], or [`YOUNG_HIT_OPACITY`] when none
/// does.
pub(super) fn place(
    source: &dyn Model,
    ds: &Dataset,
    frames: &[usize],
    settings: &BakeSettings,
    balls: &CameraBalls,
    cancel: &AtomicBool,
) -> Result<Vec<f32>, BakeError> {
    for hit_opacity in [MIN_HIT_OPACITY, YOUNG_HIT_OPACITY] {
        match place_at(source, ds, frames, settings, balls, hit_opacity, cancel) {
            Err(BakeError::Empty) => continue,
            placed => return placed,
        }
    }
    Err(BakeError::Empty)
}

/// [`place`] with rays that reach `hit_opacity` taken as hits.
fn place_at(
    source: &dyn Model,
    ds: &Dataset,
    frames: &[usize],
    settings: &BakeSettings,
    balls: &CameraBalls,
    hit_opacity: f32,
    cancel: &AtomicBool,
) -> Result<Vec<f32>, BakeError> {
    let per_frame = settings.initial_for(frames.len()).div_ceil(frames.len()).max(1);
    let mut rng = Rng::new(settings.seed);
    let scene = source.scene();
    let cams: Vec<RasterCamera> = frames.iter().map(|&f| RasterCamera::new(&ds.frames[f].camera, scene)).collect();
    let far = FAR_RADIUS * cams.iter().map(|c| Vec3::from_array(c.origin).norm()).fold(0.0f32, f32::max);
    let (mut placed, mut owners, mut outside, mut grids) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (k, &f) in frames.iter().enumerate() {
        if cancel.load(Ordering::Relaxed) {
            return Err(BakeError::Cancelled);
        }
        let (grid, points, out) = sample_photo(source, ds, f, (per_frame, hit_opacity), far, &mut rng);
        owners.extend(std::iter::repeat_n(k as u32, points.len()));
        outside.extend(out);
        placed.extend(points);
        grids.push(grid);
    }
    let mut placed = carve::carve(placed, &owners, &outside, &grids, &cams);
    placed.retain(|p| balls.clear(p.at));
    if placed.is_empty() {
        return Err(BakeError::Empty);
    }
    if placed.len() > settings.splats.max_gaussians {
        placed.truncate(settings.splats.max_gaussians);
    }
    let near = has_neighbours(&placed);
    for (p, near) in placed.iter_mut().zip(near) {
        // A photo's samples land on the surfaces the others' do (median
        // depths), so their spacing there is finer than a grid cell and a
        // Gaussian that wide only at it would leave holes: a part of the
        // cell covers them. One with no neighbours (the background, which
        // few photos see) covers more.
        p.size *= if near { INITIAL_SCALE } else { ISOLATED_SCALE };
    }
    Ok(parameters(&placed, settings.splats.sh_degree))
}

/// Renders the field's rays through a jittered grid of photo `f`'s pixels
/// (about `count` of them): what they saw, and a Gaussian where each that
/// hit something ends (its scale: the grid cell's width there), brought
/// within `far` of the centre, and whether each of those is outside the
/// photo's frame (in its [`MARGIN`]).
fn sample_photo(
    source: &dyn Model,
    ds: &Dataset,
    f: usize,
    (count, hit_opacity): (usize, f32),
    far: f32,
    rng: &mut Rng,
) -> (DepthGrid, Vec<Placed>, Vec<bool>) {
    let (scene, bg) = (source.scene(), ds.background);
    let cam = &ds.frames[f].camera;
    let (w, h) = (cam.width as f32, cam.height as f32);
    let spacing = (w * h / count as f32).sqrt().max(1.0);
    // The grid reaches past the photo's edges by the margin.
    let origin = [-MARGIN * w, -MARGIN * h];
    let (gw, gh) = ((1.0 + 2.0 * MARGIN) * w, (1.0 + 2.0 * MARGIN) * h);
    let (nx, ny) = ((gw / spacing).ceil() as usize, (gh / spacing).ceil() as usize);
    let (mut rays, mut past): (Vec<Ray>, Vec<bool>) = (Vec::with_capacity(nx * ny), Vec::with_capacity(nx * ny));
    for y in 0..ny {
        for x in 0..nx {
            let u = origin[0] + ((x as f32 + rng.f32()) * spacing).min(gw - 1e-3);
            let v = origin[1] + ((y as f32 + rng.f32()) * spacing).min(gh - 1e-3);
            rays.push(cam.ray(u, v));
            past.push(!in_frame(u, v, w, h));
        }
    }
    let (out, _) = render_rays_with(source, &rays, bg, &RenderOptions::default());
    // Where a ray's opacity reaches one half: on a surface, where its
    // expected depth through fur or across an edge lies between two.
    let hit = |o: &RayOutput| o.opacity >= hit_opacity && o.median > 0.0 && o.median.is_finite();
    let depth = out
        .iter()
        .map(|o| match (hit(o), o.opacity < MISS_OPACITY) {
            (true, _) => o.median,
            (false, true) => f32::INFINITY,
            (false, false) => f32::NAN,
        })
        .collect();
    let (mut placed, mut outside) = (Vec::new(), Vec::new());
    for (k, (ray, o)) in rays.iter().zip(&out).enumerate().filter(|(_, (_, o))| hit(o)) {
        let r = scene.to_model(ray);
        let t = o.median.min(exit_distance(&r, far));
        let at = r.at(t).to_array();
        if !at.iter().all(|v| v.is_finite()) {
            continue;
        }
        let colour = [0, 1, 2].map(|c| ((o.rgb[c] - (1.0 - o.opacity) * bg[c]) / o.opacity).clamp(0.0, 1.0));
        // A pixel's width at that distance, times the grid's spacing.
        placed.push(Placed { at, size: t * spacing / cam.fx.max(1e-6), colour });
        outside.push(past[k]);
    }
    (DepthGrid { nx, ny, origin, spacing, depth }, placed, outside)
}

/// Where model-space ray `r` leaves the sphere of radius `radius` around
/// the centre (infinite for a ray starting outside it).
fn exit_distance(r: &Ray, radius: f32) -> f32 {
    let (b, dd) = (r.origin.dot(r.dir), r.dir.dot(r.dir));
    let c = r.origin.dot(r.origin) - radius * radius;
    if c >= 0.0 || dd == 0.0 {
        return f32::INFINITY;
    }
    (-b + (b * b - dd * c).sqrt()) / dd
}

/// The parameters of the placed Gaussians: round, half opaque, coloured
/// by their SH DC term.
pub(super) fn parameters(placed: &[Placed], sh_degree: u32) -> Vec<f32> {
    let l = Layout::new(placed.len(), sh_degree);
    let n = l.n;
    let mut params = vec![0.0f32; l.len()];
    for (i, g) in placed.iter().enumerate() {
        params[3 * i..3 * i + 3].copy_from_slice(&g.at);
        params[3 * n + 3 * i..3 * n + 3 * i + 3].fill(g.size.max(1e-6).ln());
        params[6 * n + 4 * i] = 1.0;
        params[10 * n + i] = 0.0; // opacity 0.5
        for c in 0..3 {
            params[11 * n + 3 * i + c] = (g.colour[c] - 0.5) / SH_C0;
        }
    }
    params
}

/// Whether each point has at least three others in its cell and the 26
/// around it, in a hash of cells as wide as the median of the points' own
/// sizes.
fn has_neighbours(points: &[Placed]) -> Vec<bool> {
    let mut sizes: Vec<f32> = points.iter().map(|p| p.size).collect();
    let mid = sizes.len() / 2;
    let cell = *sizes.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    if !(cell > 0.0 && cell.is_finite()) {
        return vec![false; points.len()];
    }
    let key = |p: &[f32; 3]| p.map(|v| (v / cell).floor() as i64);
    let mut cells: std::collections::HashMap<[i64; 3], u32> = std::collections::HashMap::new();
    for p in points {
        *cells.entry(key(&p.at)).or_default() += 1;
    }
    points
        .iter()
        .map(|p| {
            let k = key(&p.at);
            let mut around = 0;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        around += cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]).copied().unwrap_or(0);
                    }
                }
            }
            // The point itself is one of them.
            around > 3
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ray_leaves_a_sphere_where_the_analytic_root_says() {
        let r = Ray { origin: Vec3::new(0.5, 0.0, 0.0), dir: Vec3::new(0.6, 0.8, 0.0) };
        // |o + t d| = 2: t² + 0.6 t + 0.25 - 4 = 0.
        let want = (-0.6 + (0.36f32 + 4.0 * 3.75).sqrt()) / 2.0;
        assert!((exit_distance(&r, 2.0) - want).abs() < 1e-6);
        assert!(exit_distance(&Ray { origin: Vec3::new(3.0, 0.0, 0.0), ..r }, 2.0).is_infinite());
    }

    #[test]
    fn a_point_needs_three_others_within_a_cell_to_have_neighbours() {
        let at = |x: f32| Placed::ball([x, 0.0, 0.0], 1.0, [0.5; 3]);
        // Cells of width 1 (the median size): four within reach of each
        // other, and one alone three cells away.
        let points = [at(0.1), at(0.5), at(0.9), at(1.5), at(5.0)];
        assert_eq!(has_neighbours(&points), [true, true, true, true, false]);
        assert_eq!(has_neighbours(&points[1..]), [false; 4]);
    }
}
