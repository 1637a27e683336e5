//! Baking: a trained radiance field becomes Gaussian splats
//! (`models::splats`) in two stages.
//!
//! 1. **Placing** ([`place`], [`carve`]): rays through a jittered grid of
//!    every training photo's pixels, and a margin past its edges, are
//!    rendered by the field; where a ray's opacity says it hit something, a
//!    Gaussian goes where that opacity reached one half (its median depth),
//!    with the field's colour. Then
//!    every photo's rays carve: a Gaussian well in front of what another
//!    photo saw along it is a floater in that photo's free space, and goes.
//!    None is kept within the capture's near bound of a training camera
//!    ([`clear`]), then or at any later pruning: no photo looks there.
//! 2. **Fitting** ([`fit`], [`densify`]) against the training photos with
//!    the differentiable rasteriser: one whole photo a step (at half size
//!    first, for large photos, at a rate rising from half), mean squared
//!    error and D-SSIM, Adam with per-block rates, and the 3DGS paper's
//!    densification and pruning in the first half, all on one [`Budget`]
//!    of steps or seconds as training's. From a source with a per-photo appearance, each photo is
//!    fitted through its own colour correction (`splats::looks`), kept
//!    with the splats for views that take a photo's look. The
//!    background of a capture taken all around keeps a colour of degree 0
//!    ([`background`]).
//!
//! What was tried, kept and dropped, with its figures:
//! `docs/design/splats.md`.

mod background;
mod carve;
mod clear;
mod densify;
mod fit;
mod place;

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::engine::dataset::{Dataset, Split};
use crate::engine::models::Model;
use crate::engine::models::splats::{SplatsConfig, SplatsModel};
use crate::engine::models::training::Budget;
use crate::engine::nn::adam::Adam;
use crate::engine::transient::TransientMaps;

pub use place::{MOST_INITIAL, PER_PHOTO, placing_rays};

/// How to bake.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BakeSettings {
    /// When to stop, placing included: the first of its steps (one photo
    /// each) or seconds reached ends baking.
    #[serde(flatten)]
    pub budget: Budget,
    /// Gaussians placed from the field within the photos' frames before
    /// fitting (the margins past their edges add those no photo saw);
    /// `None`: [`PER_PHOTO`] for each training photo, at most
    /// [`MOST_INITIAL`].
    pub initial: Option<usize>,
    pub splats: SplatsConfig,
    pub seed: u64,
    /// Photos of at least this many pixels are fitted at half their size
    /// for the first [`COARSE_SHARE`] of the budget.
    #[serde(default = "coarse_min_pixels")]
    pub coarse_min_pixels: usize,
}

fn coarse_min_pixels() -> usize {
    COARSE_MIN_PIXELS
}

impl Default for BakeSettings {
    fn default() -> Self {
        Self {
            budget: Budget { steps: None, seconds: Some(60.0) },
            initial: None,
            splats: SplatsConfig::default(),
            seed: 0,
            coarse_min_pixels: COARSE_MIN_PIXELS,
        }
    }
}

impl BakeSettings {
    /// How many Gaussians `photos` training photos place.
    pub fn initial_for(&self, photos: usize) -> usize {
        self.initial.unwrap_or((PER_PHOTO * photos).min(MOST_INITIAL))
    }
}

/// The share of a bake's budget whose steps fit a photo at half its size
/// (each pixel the mean of two by two), when it has at least
/// [`COARSE_MIN_PIXELS`]: a coarse step draws a quarter of the pixels, so
/// the splats take their broad shape in more steps, and the second half
/// sharpens them.
pub const COARSE_SHARE: f64 = 0.5;

/// The fewest pixels of a photo that a bake fits at half size first
/// ([`COARSE_SHARE`]): with few pixels, a step's cost is mostly the
/// Gaussians', and a coarse one saves little (lego's 200x200 photos lose by
/// it; fox's 270x480, the smallest above, gain).
pub const COARSE_MIN_PIXELS: usize = 100_000;

/// What went wrong.
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    #[error("the dataset has no training photos")]
    NoPhotos,
    #[error("the field is empty: no training ray hit anything, so there is nothing to place Gaussians on")]
    Empty,
    #[error("baking was cancelled")]
    Cancelled,
    #[error("a {0} model cannot be baked: bake an instant, nerf or capture model")]
    Kind(&'static str),
    #[error("a bake needs a budget: seconds, steps or both")]
    NoBudget,
    #[error("the source's transient masks are of other photos than the dataset's training photos")]
    OtherPhotos,
}

/// Progress of a bake, reported after each step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BakeProgress {
    pub step: u64,
    pub elapsed: f64,
    /// Fraction of the budget used.
    pub progress: f64,
    pub gaussians: usize,
    /// PSNR of the last step's photo (through its colour correction, if
    /// the bake fits them), smoothed.
    pub psnr: f64,
}

/// A Gaussian placed from the field.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Placed {
    /// Position (model units).
    at: [f32; 3],
    /// Scale (model units).
    size: f32,
    colour: [f32; 3],
}

impl Placed {
    #[cfg(test)]
    fn ball(at: [f32; 3], size: f32, colour: [f32; 3]) -> Self {
        Self { at, size, colour }
    }
}

/// Whether image point `(u, v)` (pixels) is within a `w x h` frame.
fn in_frame(u: f32, v: f32, w: f32, h: f32) -> bool {
    u >= 0.0 && v >= 0.0 && u < w && v < h
}

/// Steps between densifications (in the first half of the budget).
const DENSIFY_EVERY: u64 = 100;

/// Bakes `source` (trained on `ds`) into splats: the splats, their
/// optimiser and the steps made. `dropped`, the transient maps of a source
/// trained with them, keeps the pixels training dropped out of the fit, so
/// that what training left out does not come back in the splats.
pub fn bake(
    source: &dyn Model,
    ds: &Dataset,
    settings: &BakeSettings,
    dropped: Option<&TransientMaps>,
    cancel: &AtomicBool,
    mut on_progress: impl FnMut(&BakeProgress),
) -> Result<(SplatsModel, Adam, u64), BakeError> {
    if source.rasteriser().is_some() {
        return Err(BakeError::Kind(source.kind()));
    }
    let budget = settings.budget;
    if budget.seconds.is_none() && budget.steps.is_none() {
        return Err(BakeError::NoBudget);
    }
    let started = Instant::now();
    let frames = ds.split(Split::Train).to_vec();
    if frames.is_empty() {
        return Err(BakeError::NoPhotos);
    }
    if dropped.is_some_and(|m| !m.fits(ds)) {
        return Err(BakeError::OtherPhotos);
    }
    let balls = clear::CameraBalls::around(ds, &frames, source.scene());
    let params = place::place(source, ds, &frames, settings, &balls, cancel)?;
    let model = SplatsModel::from_parts(settings.splats.clone(), source.scene().clone(), params)
        .map_err(|_| BakeError::Empty)?;
    if model.layout().n == 0 {
        return Err(BakeError::Empty);
    }
    let mut fit = fit::Fit::new(ds, frames, settings, model, dropped, balls);
    // The splats get what the source has: a photo's own look where the
    // source learned one per photo.
    if crate::engine::models::learns_appearance(source) {
        fit.fit_looks();
    }
    loop {
        let elapsed = started.elapsed().as_secs_f64();
        if budget.done(fit.step, elapsed) {
            break;
        }
        if cancel.load(Ordering::Relaxed) {
            return Err(BakeError::Cancelled);
        }
        let progress = budget.progress(fit.step, elapsed);
        fit.step(progress);
        if fit.step.is_multiple_of(DENSIFY_EVERY) && progress < 0.5 {
            fit.densify(settings.splats.max_gaussians);
        }
        on_progress(&BakeProgress {
            step: fit.step,
            elapsed,
            progress,
            gaussians: fit.model.layout().n,
            psnr: fit.smoothed_psnr,
        });
    }
    // A last pruning: nothing nearly transparent is written.
    fit.prune();
    let looks = fit.looks();
    fit.model.set_looks(looks);
    Ok((fit.model, fit.adam, fit.step))
}

#[cfg(test)]
pub(crate) mod testutil {
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::math::{Aabb, Vec3};
    use crate::engine::geometry::scene::Scene;
    use crate::engine::models::splats::raster::RasterCamera;

    /// The unit box's scene, and a camera 4 units from its centre along
    /// -y, looking at it (z up).
    pub fn facing_origin() -> (Scene, [[f32; 4]; 3]) {
        let scene = Scene::from_bounds(Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }, 0.0, 10.0);
        (scene, look_at(Vec3::new(0.0, -4.0, 0.0), Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap())
    }

    /// [`facing_origin`]'s scene and its camera, 30x30 pixels at a field of
    /// view of 1 radian, as the rasteriser takes it.
    pub fn facing_camera() -> (Scene, RasterCamera) {
        let (scene, c2w) = facing_origin();
        let cam = RasterCamera::new(&Camera::from_fov(30, 30, 1.0, c2w), &scene);
        (scene, cam)
    }
}
