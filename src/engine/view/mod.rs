//! Rendering whole views of a model: one ray per pixel centre, in parallel
//! over tiles, and `appearance` (which training image's appearance a new
//! view takes).

pub mod appearance;

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use crate::engine::batch::{BatchStats, RayOutput};
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Ray;
use crate::engine::models::{Model, RenderOptions};

/// A rendered view.
#[derive(Clone, Debug)]
pub struct View {
    pub width: u32,
    pub height: u32,
    /// `[h x w x 3]`, composited on the requested background.
    pub rgb: Vec<f32>,
    /// Expected depth along the ray in world units (0 where nothing was hit).
    pub depth: Vec<f32>,
    /// Accumulated opacity in [0, 1].
    pub opacity: Vec<f32>,
    pub stats: BatchStats,
}

/// Rays rendered together by one task: small enough to balance two threads
/// on a 200x200 view, large enough to keep the GEMMs efficient.
const TILE: usize = 256;

/// Side of the square blocks of pixels a view's rays are ordered in (one
/// block a task, `BLOCK^2 = TILE`): neighbouring pixels' samples read the
/// same entries of the hash tables, which then stay in cache (row order
/// renders the benchmark scenes 3-6% slower).
const BLOCK: usize = 16;

/// The pixels `(x, y)` of a `w x h` view in blocks of `BLOCK x BLOCK`,
/// row-major inside a block and from block to block (partial blocks at the
/// right and bottom edges).
fn block_order(w: usize, h: usize) -> Vec<(usize, usize)> {
    let mut order = Vec::with_capacity(w * h);
    for by in (0..h).step_by(BLOCK) {
        for bx in (0..w).step_by(BLOCK) {
            for y in by..(by + BLOCK).min(h) {
                order.extend((bx..(bx + BLOCK).min(w)).map(|x| (x, y)));
            }
        }
    }
    order
}

/// Renders every pixel of `camera`.
pub fn render_view(model: &dyn Model, camera: &Camera, background: [f32; 3]) -> View {
    render_view_with(model, camera, background, &RenderOptions::default())
}

/// [`render_view`] with render options (a chosen appearance:
/// `appearance::Appearance::resolve` gives them for a camera).
pub fn render_view_with(model: &dyn Model, camera: &Camera, background: [f32; 3], options: &RenderOptions) -> View {
    render_view_until(model, camera, background, options, &AtomicBool::new(false)).expect("never cancelled")
}

/// Renders a held-out view of the dataset the model was trained on: from
/// `camera` moved as the model says held-out cameras move
/// ([`models::heldout_pose`](crate::engine::models::heldout_pose): a model that refined its training cameras
/// applies their common drift; the camera itself for the others), with
/// render `options` (`appearance::held_out_options` for the held-out rule).
pub fn render_heldout_view(model: &dyn Model, camera: &Camera, background: [f32; 3], options: &RenderOptions) -> View {
    let moved = Camera { c2w: crate::engine::models::heldout_pose(model, camera.c2w), ..camera.clone() };
    render_view_with(model, &moved, background, options)
}

/// [`render_view_with`], stopping early (`None`) once `cancel` is set: tiles not
/// yet started are skipped. A client that goes away mid-render (the web
/// viewer, moving on to a newer view) frees the workers at once.
pub fn render_view_until(
    model: &dyn Model,
    camera: &Camera,
    background: [f32; 3],
    options: &RenderOptions,
    cancel: &AtomicBool,
) -> Option<View> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let scene = model.scene();
    let inv = 1.0 / scene.scale;
    if let Some(r) = model.rasteriser() {
        // Drawn whole, in a fraction of a ray-marched view's time: nothing
        // to cancel part-way.
        let (rgb, depth, opacity) = r.render_view(camera, background, options);
        let stats = BatchStats { rays: (w * h) as u64, ..Default::default() };
        let depth = depth.iter().map(|d| d * inv).collect();
        return (!cancel.load(Ordering::Relaxed)).then_some(View {
            width: camera.width,
            height: camera.height,
            rgb,
            depth,
            opacity,
            stats,
        });
    }
    let order = block_order(w, h);
    let rays: Vec<Ray> = order.iter().map(|&(x, y)| camera.pixel_ray(x as u32, y as u32)).collect();
    let (blocked, stats) = render_rays_until(model, &rays, background, options, cancel)?;
    let mut out = vec![RayOutput::default(); w * h];
    for (&(x, y), o) in order.iter().zip(blocked) {
        out[y * w + x] = o;
    }
    Some(View {
        width: camera.width,
        height: camera.height,
        rgb: out.iter().flat_map(|o| o.rgb).collect(),
        depth: out.iter().map(|o| o.depth * inv).collect(),
        opacity: out.iter().map(|o| o.opacity).collect(),
        stats,
    })
}

/// Renders world-space rays in parallel tiles; depths stay in model units.
pub fn render_rays(model: &dyn Model, rays: &[Ray], background: [f32; 3]) -> (Vec<RayOutput>, BatchStats) {
    render_rays_with(model, rays, background, &RenderOptions::default())
}

/// [`render_rays`] with render options.
pub fn render_rays_with(
    model: &dyn Model,
    rays: &[Ray],
    background: [f32; 3],
    options: &RenderOptions,
) -> (Vec<RayOutput>, BatchStats) {
    render_rays_until(model, rays, background, options, &AtomicBool::new(false)).expect("never cancelled")
}

/// [`render_rays_with`], or `None` once `cancel` is set.
pub(crate) fn render_rays_until(
    model: &dyn Model,
    rays: &[Ray],
    background: [f32; 3],
    options: &RenderOptions,
    cancel: &AtomicBool,
) -> Option<(Vec<RayOutput>, BatchStats)> {
    let scene = model.scene();
    let rays: Vec<Ray> = rays.iter().map(|r| scene.to_model(r)).collect();
    let mut out = vec![RayOutput::default(); rays.len()];
    let stats = rays
        .par_chunks(TILE)
        .zip(out.par_chunks_mut(TILE))
        .map(|(r, o)| {
            if cancel.load(Ordering::Relaxed) {
                BatchStats::default()
            } else {
                model.render_rays(r, background, options, o)
            }
        })
        .reduce(BatchStats::default, |mut a, b| {
            a.add(&b);
            a
        });
    (!cancel.load(Ordering::Relaxed)).then_some((out, stats))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pixel once, and every task's `TILE` rays inside one
    /// `BLOCK x BLOCK` square.
    #[test]
    fn block_order_visits_every_pixel_once_in_blocks() {
        for (w, h) in [(1, 1), (17, 5), (48, 33), (200, 200), (16, 64)] {
            let order = block_order(w, h);
            let mut seen = vec![false; w * h];
            for &(x, y) in &order {
                assert!(x < w && y < h && !seen[y * w + x], "{w}x{h}: ({x}, {y})");
                seen[y * w + x] = true;
            }
            assert!(seen.iter().all(|&s| s), "{w}x{h}: a pixel missing");
            // Whole blocks come first in each band of rows, so a chunk of
            // TILE rays stays in one block when the width is a multiple.
            if w % BLOCK == 0 && h % BLOCK == 0 {
                for chunk in order.chunks(TILE) {
                    let (x0, y0) = (chunk[0].0 / BLOCK, chunk[0].1 / BLOCK);
                    assert!(chunk.iter().all(|&(x, y)| x / BLOCK == x0 && y / BLOCK == y0), "{w}x{h}");
                }
            }
        }
    }
}
