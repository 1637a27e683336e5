//! Rendering whole views: one ray per pixel centre, in parallel over tiles.
//!
//! The parts: `composite` (volume rendering of one ray, forward and
//! backward), `loss` (the photometric loss), `regularize` (losses on a ray's
//! weights: distortion and interlevel), `rounds` (the one render loop),
//! `appearance` (which training image's appearance a new view takes).

pub mod appearance;
pub mod composite;
pub mod loss;
pub mod regularize;
pub mod rounds;

use std::sync::atomic::{AtomicBool, Ordering};

use rayon::prelude::*;

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Ray;
use crate::engine::models::{BatchStats, Model, RayOutput, RenderOptions};

/// Why a per-ray function of `composite` or `regularize` refused its
/// inputs: the slices of one ray must fit each other, and interval edges
/// must be sorted. Checked once per ray, so a caller's mistake is an error
/// that names the slice rather than an out-of-bounds panic.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InputError {
    #[error("{what} has {got} values, expected {expected}")]
    Length { what: &'static str, expected: usize, got: usize },
    #[error("{what}: value {index} ({value}) is not finite or is below the one before it")]
    Unsorted { what: &'static str, index: usize, value: f32 },
}

impl InputError {
    /// `Ok` when slice `what` has `expected` values.
    pub fn check_len(what: &'static str, expected: usize, got: usize) -> Result<(), Self> {
        if expected == got { Ok(()) } else { Err(Self::Length { what, expected, got }) }
    }

    /// `Ok` when `v` is finite and non-decreasing.
    pub fn check_sorted(what: &'static str, v: &[f32]) -> Result<(), Self> {
        let mut prev = f32::NEG_INFINITY;
        for (index, &value) in v.iter().enumerate() {
            if !(value.is_finite() && value >= prev) {
                return Err(Self::Unsorted { what, index, value });
            }
            prev = value;
        }
        Ok(())
    }
}

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
/// ([`Model::heldout_pose`]: a model that refined its training cameras
/// applies their common drift; the camera itself for the others), with
/// render `options` (`appearance::held_out_options` for the held-out rule).
pub fn render_heldout_view(model: &dyn Model, camera: &Camera, background: [f32; 3], options: &RenderOptions) -> View {
    let moved = Camera { c2w: model.heldout_pose(camera.c2w), ..camera.clone() };
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
    let rays: Vec<Ray> =
        (0..h).flat_map(|j| (0..w).map(move |i| (i, j))).map(|(i, j)| camera.pixel_ray(i as u32, j as u32)).collect();
    let (out, stats) = render_rays_until(model, &rays, background, options, cancel)?;
    let inv = 1.0 / scene.scale;
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
fn render_rays_until(
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
                model.render_rays_with(r, background, options, o)
            }
        })
        .reduce(BatchStats::default, |mut a, b| {
            a.add(&b);
            a
        });
    (!cancel.load(Ordering::Relaxed)).then_some((out, stats))
}
