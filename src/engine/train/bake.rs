//! Baking: a trained radiance field becomes Gaussian splats
//! (`models::splats`) in two stages.
//!
//! 1. **Placing.** Rays through a jittered grid of every training photo's
//!    pixels are rendered by the field; where a ray's opacity says it hit
//!    something, a Gaussian goes at its expected depth, a fifth as wide as
//!    the spacing of its neighbours (of all photos), with the field's
//!    colour (as the SH DC term) and half opacity. Then every photo's rays
//!    carve: a Gaussian well in front of what another photo saw along it
//!    is a floater in that photo's free space, and goes (a ray through an
//!    object's edge has an expected depth between the object and what is
//!    behind it). The unbounded background of a capture is carried over
//!    the same way, but within three times the cameras' distance from the
//!    centre (the field puts much of it at the far plane, where the photos
//!    disagree about it), each Gaussian as wide as half its grid cell
//!    there. The grid reaches a tenth of the photo past each of its edges
//!    ([`MARGIN`]): what a view near the photos sees past their frames is
//!    what the field filled in there, kept where no photo saw it within
//!    its frame. (Fitting the splats also to the field's renders at
//!    virtual views between neighbouring photos, each with the appearance
//!    a held-out view there takes, was tried. At half size with 15% of a
//!    60 s bake: gold_cape, from a 120 s source, 19.13 dB held out with
//!    them against 18.83 without, but fox 28.37 against 28.76 (a 120 s
//!    source) and 28.51 against 29.19 (a 60 s one). At full size, lego
//!    from a 120 s source: 31.82 dB over its 200 test views with 15%,
//!    31.54 with 30%, 32.38 without. The splats learn more from the
//!    photos than from the field's views, which are blurrier.) The field
//!    is rendered with the mean appearance of its
//!    training photos (`RenderOptions::default()`), the appearance a
//!    held-out view takes by default; splats have one appearance, which
//!    optimising against the photos keeps near their mean. (A colour
//!    transform per training photo, fitted with the Gaussians and taken
//!    from the nearest photo by a held-out view, as the capture model's
//!    embeddings are, was tried: fox, a 60 s source baked 400 steps, 27.90
//!    dB held out without, 28.25-28.40 with; but in `bench --budgets 120
//!    --bake 60` fox 28.00 dB with against 27.98 without, fern 25.92
//!    against 25.91, gold_cape 18.42 against 18.22, within the spread
//!    between runs, for a second appearance rule and a tensor in the
//!    checkpoint. Nor did per-Gaussian appearance: each Gaussian's colour
//!    plus a 3xK response to a per-photo code, the source's embeddings
//!    along their K principal directions, whitened, a held-out view taking
//!    its nearest photo's code. From a 120 s fox source (29.68 dB nearest,
//!    28.32 mean), `bake --steps 475` then `eval --fit-steps 0`, 2-core
//!    Xeon VM: responses learnt from zero 28.52 dB (K 4), 28.82 (2), 28.56
//!    (1) against 28.93 without; the field's own response (the placement
//!    rays rendered again with the embedding one spread along each
//!    direction), kept fixed, 28.98; gold_cape from a 120 s source, 300
//!    steps, 19.81 against 19.73, for 10 s more placing. One appearance
//!    fitted to every photo already scores better on held-out photos than
//!    the source's mean embedding does (fox 28.93 against 28.32), and what
//!    fox's splats lose against the source is mostly in three views
//!    (0012, 0042, 0110), two of which lose most at their edges, which
//!    see past the photos: the squared error of their 10-pixel border is
//!    2.3 and 2.5 times the source's.)
//! 2. **Optimising** against the training photos with the differentiable
//!    rasteriser (`splats::raster`, `splats::backward`): one whole photo a
//!    step (at half size for the first [`COARSE_SHARE`] of the budget,
//!    when the photos are large enough to gain by it), mean squared error,
//!    Adam with the 3DGS paper's per-block rates (scaled for a budget of
//!    hundreds of steps, [`BASE_LR`]), and, every `DENSIFY_EVERY` steps
//!    of the first half, the paper's densification (Gaussians the loss
//!    wants to move on the image are cloned when small and split when
//!    large) and pruning (nearly transparent ones go), within
//!    `max_gaussians`. (From the fox source
//!    above, also tried and dropped: every rate decayed by a cosine to a
//!    tenth over the second half, `bake --steps 380`, 28.20 dB against
//!    28.45; half the tiles drawn and fitted each step, at random, `bake
//!    --seconds 50`, 527 steps and 28.19 dB against 442 and 28.70; the
//!    margins' Gaussians starting at opacity 0.9, or all at 0.7, 28.49 and
//!    28.45 against 28.45. Steps are what a bake is short of: 475 steps
//!    against 380 is 28.93 dB against 28.45.) What the splats lose is on
//!    new views, not on the photos: baked 60 s from a 120 s fox source
//!    (`ca07950`), they score 32.31 dB on its first 12 training photos
//!    (`eval --split train --limit 12 --fit-steps 0`) against the source's
//!    32.41 with each photo's own embedding, and 29.40 held out against
//!    30.11. Of the held-out views, 0042 loses most in its top-left
//!    corner, a dark band that the field draws and the splats smear.
//!    Neither their one appearance nor their geometry explains it (the
//!    same bake, scored again in Python): a 3x4 colour transform fitted to
//!    each held-out photo itself, an oracle no appearance rule can beat,
//!    lifts them only from 29.39 to 29.58 dB (the source's mean appearance
//!    from 28.60 to 29.43); their depth (`render --depth`) is within a few
//!    percent of the field's (the median per cell of a 4x4 grid; 4% in that
//!    corner); and the positions' rate times 0.3 or 3 gives 29.11 and 29.24,
//!    or 28.42 and 28.19 dB (seeds 1-2), against 29.40 and 29.29. The band
//!    is a thin structure that few photos see: the splats draw it as sharply
//!    as the field in the photo that sees it best (0035), and do not carry
//!    it to a new view beside it. Nor would steps close the gap: baked 90 s
//!    (809 and 818 steps, seeds 1-2) they score 29.53 and 29.47 dB, 120 s
//!    (1054 steps) 29.68, against 29.40 and 29.29 in 60 s (about 500).

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::engine::batch::RayOutput;
use crate::engine::dataset::{Dataset, Split};
use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::models::splats::backward::backward;
use crate::engine::models::splats::gaussians::{Layout, SH_C0};
use crate::engine::models::splats::lens;
use crate::engine::models::splats::raster::{RasterCamera, RasterOptions, forward};
use crate::engine::models::splats::{SplatsConfig, SplatsModel};
use crate::engine::models::{Model, RenderOptions};
use crate::engine::nn::adam::{Adam, AdamConfig, LrGroup};
use crate::engine::rng::Rng;
use crate::engine::view::render_rays_with;

/// How to bake.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BakeSettings {
    /// Wall-clock budget of both stages (seconds).
    pub seconds: Option<f64>,
    /// Optimisation steps (one photo each); the first of the two budgets
    /// reached ends baking.
    pub steps: Option<u64>,
    /// Gaussians placed from the field within the photos' frames before
    /// optimising (the margins past their edges add those no photo saw);
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
            seconds: Some(60.0),
            steps: None,
            initial: None,
            splats: SplatsConfig::default(),
            seed: 0,
            coarse_min_pixels: COARSE_MIN_PIXELS,
        }
    }
}

/// The share of a bake's budget (of its steps or seconds) whose steps fit
/// a photo at half its size (each pixel the mean of two by two), when it
/// has at least [`COARSE_MIN_PIXELS`]. A coarse step draws a quarter of
/// the pixels, and the Gaussians' own work (projecting, their backward,
/// Adam) stays: on the 2-core Xeon VM, one costs about 0.55 of a full one
/// on fox and 0.5 on gold_cape. Fitted against the photos at half size
/// first, the splats take their broad shape in more steps, and the second
/// half sharpens them. Baked from one 120 s source each, then `eval
/// --fit-steps 0`, with the steps either way fits in about 60 s (`bake
/// --steps N --seed S`): fox 29.56, 29.53 and 29.60 dB held out (seeds
/// 1-3, 620 steps) against 28.92, 28.73 and 28.73 (480 steps); gold_cape
/// 19.06 and 20.02 dB, masks 20.53 and 21.41 (seeds 1-2, 385 steps)
/// against 18.81 and 19.53, masks 20.19 and 20.91 (300 steps). With
/// `--seconds 60`: fern 25.96 dB against 25.57 (764 steps against 536);
/// fox with a share of 0.3, 0.5 (twice), 0.7 and 1: 29.26, 29.36, 28.93,
/// 29.13 and 25.76 dB, against 29.14 and 28.84 without.
pub const COARSE_SHARE: f64 = 0.5;

/// The fewest pixels of a photo that a bake fits at half size first
/// ([`COARSE_SHARE`]). lego's 200x200 photos lose by it: baked 60 s from a
/// 120 s source, 32.06 dB over its 200 test views against 32.62 without
/// (1222 steps against 1080: with few pixels, a step's cost is mostly the
/// Gaussians', and a coarse one saves little). fox's 270x480 photos, the
/// smallest above, gain.
pub const COARSE_MIN_PIXELS: usize = 100_000;

/// Gaussians each training photo places by default. A forward-facing
/// capture's photos all see one wall: a fixed total there is many samples
/// of the same surface, more Gaussians than the bake's minute can fit (each
/// step draws them all), so the default follows the photos. Baked 60 s
/// from one source each (`bake --seconds 60 --initial N`, then `eval
/// --fit-steps 0`, on the 2-core Xeon VM): fern (20 photos) 20.27 dB from
/// 30k against 19.20 from 200k; fox (50) 27.56 from 50k against 25.96 from
/// 200k; lego (100) 31.54 from 30k against 31.88 from 200k; gold_cape
/// (119) 16.99 from 80k against 17.22 from 200k.
pub const PER_PHOTO: usize = 1_500;

/// The most Gaussians placed by default.
pub const MOST_INITIAL: usize = 200_000;

impl BakeSettings {
    /// How many Gaussians `photos` training photos place.
    pub fn initial_for(&self, photos: usize) -> usize {
        self.initial.unwrap_or((PER_PHOTO * photos).min(MOST_INITIAL))
    }
}

/// The field's rays that placing `initial` Gaussians within the photos'
/// frames renders, with those of the margins past the frames ([`MARGIN`]).
pub fn placing_rays(initial: usize) -> u64 {
    (initial as f64 * (1.0 + 2.0 * MARGIN as f64).powi(2)).ceil() as u64
}

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
}

/// Progress of a bake, reported after each step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BakeProgress {
    pub step: u64,
    pub elapsed: f64,
    /// Fraction of the budget used.
    pub progress: f64,
    pub gaussians: usize,
    /// PSNR of the last step's photo, smoothed.
    pub psnr: f64,
}

/// The opacity a field's ray must reach for a Gaussian to be placed where
/// it ends: a ray through an object's edge, or through a thin haze, has an
/// expected depth between surfaces, where a Gaussian would float.
const MIN_HIT_OPACITY: f32 = 0.9;
/// The opacity below which a field's ray saw nothing (free space all
/// along it, for [`carve`]); between the two, it is not trusted either way.
const MISS_OPACITY: f32 = 0.1;
/// Carving's margin: a Gaussian nearer than this fraction of the distance
/// a photo's ray saw is in its free space. (gold_cape, a 120 s
/// `capture-360` model, 130 steps: carving lifts the held-out PSNR inside
/// the object's masks from 18.33 to 18.87 dB.)
const CARVE_MARGIN: f32 = 0.8;
/// Gaussians are placed within this many times the farthest camera's
/// distance from the centre: a capture's field puts much of its background
/// at the far plane, where no two photos agree on it (gold_cape as above:
/// 19.06 dB inside the masks at 3, 18.81 at 2, 18.87 with no limit).
const FAR_RADIUS: f32 = 3.0;
/// A placed Gaussian with no neighbours' spacing (the background, seen by
/// few photos) gets this fraction of its grid cell's width (gold_cape as
/// above, no carving: 16.74 dB held out at 0.5, 15.58 at 0.2).
const ISOLATED_SCALE: f32 = 0.5;
/// How far past each edge of a photo (as a fraction of its width and
/// height) the field's rays place Gaussians, at the photo's grid spacing:
/// a view near the photos sees past their frames, where the field has
/// filled in what it learnt nearby, and the splats had nothing (`bake
/// --seconds 60`, then `eval --fit-steps 0`, on the 2-core Xeon VM: fox
/// from a 60 s source 28.40 dB held out without the margin, 28.91 with it,
/// 29.19 keeping only what no photo saw within its frame; gold_cape from a
/// 120 s source 18.20 without, 18.83 with). Tried and dropped on the same
/// VM at `ca07950`, from a 120 s fox source (30.11 dB held out), `bake
/// --seconds 60 --seed S`: a margin of 0.2, 29.24 and 29.30 dB (seeds 1-2)
/// against 29.40 and 29.29; the margins' Gaussians, which no photo sees and
/// so never move, covering their grid cell (as wide as it, opacity 0.9,
/// where the others start at a fifth of their neighbours' spacing and half
/// opacity): fox 29.56, 29.46 and 29.33 (seeds 1-3) against 29.40, 29.29
/// and 29.08, but fern from a 120 s source 25.57 and 25.66 against 25.81
/// and 25.93, and gold_cape 20.02 and 20.07 (masks 20.61 and 20.74) against
/// 18.95 and 19.90 (masks 20.43 and 21.56), its held-out view IMG_5953 at
/// 14-15 dB with both seeds: big opaque Gaussians that no photo checks
/// stand in front of some new views.
const MARGIN: f32 = 0.1;
/// A placed Gaussian's scale, as a fraction of the spacing of its
/// neighbours (lego, 30 s instant model, placement alone: 15.8 dB at 1,
/// 18.3 at 0.5, 19.5 at 0.3, 20.0 at 0.2).
const INITIAL_SCALE: f32 = 0.2;
/// Steps between densifications. (From the fox source of [`MARGIN`],
/// seeds 1-2: every 50 steps, 29.10 and 29.15 dB held out against 29.40
/// and 29.29; densifying for three quarters of the budget instead of
/// half, 29.39 and 29.36.)
const DENSIFY_EVERY: u64 = 100;
/// Screen-space gradient (per view, in units of the half image) above
/// which a Gaussian is densified: the 3DGS paper's 0.0002 is for an L1
/// loss; a squared error's gradients are about ten times smaller (lego,
/// 800 steps: 79k Gaussians and 32.1 dB at 2e-5, 57k and 32.0 dB at 2e-4).
const DENSIFY_GRAD: f32 = 2e-5;
/// Opacity below which a Gaussian is pruned (the paper's 0.005).
const PRUNE_OPACITY: f32 = 0.005;

/// The learning rate the blocks' scales multiply: four times the 3DGS
/// paper's rates, since a bake has hundreds of steps where the paper has
/// 30k (lego, a 30 s instant model baked 200 steps: 27.0 dB at the
/// paper's rates, 29.0 at twice, 29.9 at four times, 28.4 at eight).
const BASE_LR: f32 = 4e-3;

/// The per-block learning rates as multiples of [`BASE_LR`]: the 3DGS
/// paper's relative rates (positions in model units, whose scene box has
/// half-extent 1: the paper's rate times its typical scene radius of 3).
fn groups(l: &Layout, progress: f64) -> Vec<LrGroup> {
    // Positions decay a hundredfold over the bake.
    let pos = 0.48 * (0.01f64).powf(progress) as f32;
    let mut g = vec![
        LrGroup { range: l.means(), scale: pos },
        LrGroup { range: l.log_scales(), scale: 5.0 },
        LrGroup { range: l.rotations(), scale: 1.0 },
        LrGroup { range: l.opacities(), scale: 25.0 },
    ];
    // The SH terms, all at the paper's DC rate (the paper's twentieth for
    // the others is for 30k steps: lego, 200 steps: 27.0 dB at the DC
    // rate, 25.0 dB at a twentieth).
    g.push(LrGroup { range: l.sh_dc(), scale: 2.5 });
    g.push(LrGroup { range: l.sh_rest(), scale: 2.5 });
    g
}

/// Bakes `source` (trained on `ds`) into splats.
pub fn bake(
    source: &dyn Model,
    ds: &Dataset,
    settings: &BakeSettings,
    cancel: &AtomicBool,
    mut on_progress: impl FnMut(&BakeProgress),
) -> Result<(SplatsModel, Adam, u64), BakeError> {
    if source.rasteriser().is_some() {
        return Err(BakeError::Kind(source.kind()));
    }
    if settings.seconds.is_none() && settings.steps.is_none() {
        return Err(BakeError::NoBudget);
    }
    let started = Instant::now();
    let frames = ds.split(Split::Train).to_vec();
    if frames.is_empty() {
        return Err(BakeError::NoPhotos);
    }
    let params = place(source, ds, &frames, settings, cancel)?;
    let mut b = Baker::new(source, ds, frames, settings, params)?;
    let budget = |step: u64, t: f64| -> f64 {
        let a = settings.steps.map_or(0.0, |s| step as f64 / s.max(1) as f64);
        let b = settings.seconds.map_or(0.0, |s| t / s.max(1e-9));
        a.max(b)
    };
    loop {
        let elapsed = started.elapsed().as_secs_f64();
        let progress = budget(b.step, elapsed);
        if progress >= 1.0 {
            break;
        }
        if cancel.load(Ordering::Relaxed) {
            return Err(BakeError::Cancelled);
        }
        b.step(progress);
        if b.step.is_multiple_of(DENSIFY_EVERY) && progress < 0.5 {
            b.densify(settings.splats.max_gaussians);
        }
        on_progress(&BakeProgress {
            step: b.step,
            elapsed,
            progress,
            gaussians: b.model.layout().n,
            psnr: b.smoothed_psnr,
        });
    }
    // A last pruning: nothing nearly transparent is written.
    b.grad_accum.iter_mut().for_each(|a| *a = (0.0, 0));
    b.densify(0);
    Ok((b.model, b.adam, b.step))
}

/// The optimisation stage's state.
struct Baker<'a> {
    ds: &'a Dataset,
    frames: Vec<usize>,
    settings: &'a BakeSettings,
    model: SplatsModel,
    adam: Adam,
    /// Each training photo's colours on the dataset's background.
    targets: Vec<Vec<f32>>,
    /// How many values of each target are not NaN (the loss's divisor).
    valid: Vec<usize>,
    /// The photos left in this epoch (shuffled).
    order: Vec<usize>,
    /// Per Gaussian: the sum of its screen-space gradient norms and the
    /// number of views that saw it, since the last densification.
    grad_accum: Vec<(f32, u32)>,
    /// Each photo at half size (and its valid values), made when a coarse
    /// step first takes it.
    halves: Vec<Option<(Vec<f32>, usize)>>,
    rng: Rng,
    step: u64,
    smoothed_psnr: f64,
    grads: Vec<f32>,
}

impl<'a> Baker<'a> {
    fn new(
        source: &dyn Model,
        ds: &'a Dataset,
        frames: Vec<usize>,
        settings: &'a BakeSettings,
        params: Vec<f32>,
    ) -> Result<Self, BakeError> {
        let scene = source.scene().clone();
        let model = SplatsModel::from_parts(settings.splats.clone(), scene, params).map_err(|_| BakeError::Empty)?;
        if model.layout().n == 0 {
            return Err(BakeError::Empty);
        }
        let adam_config = AdamConfig { lr: BASE_LR, lr_end: BASE_LR, beta1: 0.9, beta2: 0.999, eps: 1e-15 };
        let adam = Adam::new(adam_config, model.params().len());
        let bg = ds.background;
        let targets: Vec<Vec<f32>> = frames
            .iter()
            .map(|&f| {
                let im = &ds.frames[f].image;
                let rgb: Vec<f32> =
                    (0..im.height).flat_map(|j| (0..im.width).flat_map(move |i| im.rgb_on(i, j, bg))).collect();
                // The rasteriser draws the pinhole part of a camera: a
                // distorted photo is fitted as that camera would have
                // taken it (NaN where it does not reach: no loss there).
                let camera = &ds.frames[f].camera;
                if camera.distortion.is_identity() { rgb } else { lens::undistort_photo(camera, &rgb) }
            })
            .collect();
        let n = model.layout().n;
        Ok(Self {
            ds,
            frames,
            settings,
            model,
            adam,
            valid: targets.iter().map(|t| valid_values(t)).collect(),
            halves: vec![None; targets.len()],
            targets,
            order: Vec::new(),
            grad_accum: vec![(0.0, 0); n],
            rng: Rng::new(settings.seed ^ 0xBA4E),
            step: 0,
            smoothed_psnr: 0.0,
            grads: Vec::new(),
        })
    }

    /// One step on the next photo of the epoch.
    fn step(&mut self, progress: f64) {
        if self.order.is_empty() {
            self.order = (0..self.frames.len()).collect();
            for i in (1..self.order.len()).rev() {
                self.order.swap(i, self.rng.below(i as u64 + 1) as usize);
            }
        }
        let which = self.order.pop().expect("refilled");
        let frame = &self.ds.frames[self.frames[which]];
        let full = RasterCamera::new(&frame.camera, self.model.scene());
        let pixels = full.width as usize * full.height as usize;
        let coarse = progress < COARSE_SHARE && pixels >= self.settings.coarse_min_pixels;
        let cam = if coarse { half_camera(&full) } else { full };
        let l = self.model.layout();
        let opt = RasterOptions::default();
        let f = forward(&l, self.model.params(), &cam, &opt, self.ds.background);
        let (target, valid) = if coarse {
            let targets = &self.targets;
            let (w, h) = (full.width as usize, full.height as usize);
            let (half, valid) = self.halves[which].get_or_insert_with(|| {
                let half = halve(&targets[which], w, h);
                let valid = valid_values(&half);
                (half, valid)
            });
            (&half[..], *valid)
        } else {
            (&self.targets[which][..], self.valid[which])
        };
        let n = valid.max(1) as f32;
        let mut sq = 0.0f64;
        let d_rgb: Vec<f32> = f
            .rgb
            .iter()
            .zip(target)
            .map(|(r, t)| {
                if t.is_nan() {
                    return 0.0;
                }
                let e = r - t;
                sq += (e * e) as f64;
                2.0 * e / n
            })
            .collect();
        let psnr = -10.0 * (sq / n as f64).max(1e-10).log10();
        self.smoothed_psnr = if self.step == 0 { psnr } else { 0.9 * self.smoothed_psnr + 0.1 * psnr };
        // The gradient buffer is kept between steps (zeroing it is cheaper
        // than the page faults of a fresh one of the parameters' size).
        let mut grads = std::mem::take(&mut self.grads);
        grads.clear();
        grads.resize(l.len(), 0.0);
        let screen = backward(&l, self.model.params(), &cam, &opt, &f, &d_rgb, &mut grads);
        let (hw, hh) = (0.5 * cam.width as f32, 0.5 * cam.height as f32);
        for (acc, s) in self.grad_accum.iter_mut().zip(&screen) {
            if s[0] != 0.0 || s[1] != 0.0 {
                acc.0 += ((s[0] * hw).powi(2) + (s[1] * hh).powi(2)).sqrt();
                acc.1 += 1;
            }
        }
        let groups = groups(&l, progress);
        self.adam.step_groups(self.model.params_mut(), &mut grads, BASE_LR, &groups);
        self.grads = grads;
        self.step += 1;
    }

    /// Densifies and prunes within `max` Gaussians (0: prunes only).
    fn densify(&mut self, max: usize) {
        let (params, m, v) = densify(&self.model, &self.adam, &self.grad_accum, max, &mut self.rng);
        self.adam.m = m;
        self.adam.v = v;
        let scene = self.model.scene().clone();
        self.model = SplatsModel::from_parts(self.settings.splats.clone(), scene, params).expect("same layout");
        self.grad_accum = vec![(0.0, 0); self.model.layout().n];
    }
}

/// A Gaussian placed from the field: position (model units), scale, colour.
type Placed = ([f32; 3], f32, [f32; 3]);

/// Places Gaussians where the field's rays end (module docs, stage 1).
fn place(
    source: &dyn Model,
    ds: &Dataset,
    frames: &[usize],
    settings: &BakeSettings,
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
        let (grid, points, out) = sample_photo(source, ds, f, per_frame, far, &mut rng);
        owners.extend(std::iter::repeat_n(k as u32, points.len()));
        outside.extend(out);
        placed.extend(points);
        grids.push(grid);
    }
    let mut placed = carve(placed, &owners, &outside, &grids, &cams);
    if placed.is_empty() {
        return Err(BakeError::Empty);
    }
    if placed.len() > settings.splats.max_gaussians {
        placed.truncate(settings.splats.max_gaussians);
    }
    let near = neighbour_spacing(&placed);
    for (p, s) in placed.iter_mut().zip(near) {
        // Samples of many photos land on one surface: their own spacing
        // is finer than one photo's grid. One with no neighbours (the
        // background, which few photos see) covers its grid cell.
        p.1 = match s {
            Some(d) => INITIAL_SCALE * d.min(p.1),
            None => ISOLATED_SCALE * p.1,
        };
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
    count: usize,
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
    let hit = |o: &RayOutput| o.opacity >= MIN_HIT_OPACITY && o.depth.is_finite();
    let depth = out
        .iter()
        .map(|o| match (hit(o), o.opacity < MISS_OPACITY) {
            (true, _) => o.depth / o.opacity,
            (false, true) => f32::INFINITY,
            (false, false) => f32::NAN,
        })
        .collect();
    let (mut placed, mut outside) = (Vec::new(), Vec::new());
    for (k, (ray, o)) in rays.iter().zip(&out).enumerate().filter(|(_, (_, o))| hit(o)) {
        let r = scene.to_model(ray);
        let t = (o.depth / o.opacity).min(exit_distance(&r, far));
        let p = r.at(t).to_array();
        if !p.iter().all(|v| v.is_finite()) {
            continue;
        }
        let colour = [0, 1, 2].map(|c| ((o.rgb[c] - (1.0 - o.opacity) * bg[c]) / o.opacity).clamp(0.0, 1.0));
        // A pixel's width at that distance, times the grid's spacing.
        placed.push((p, t * spacing / cam.fx.max(1e-6), colour));
        outside.push(past[k]);
    }
    (DepthGrid { nx, ny, origin, spacing, depth }, placed, outside)
}

/// Whether image point `(u, v)` (pixels) is within a `w x h` frame.
fn in_frame(u: f32, v: f32, w: f32, h: f32) -> bool {
    u >= 0.0 && v >= 0.0 && u < w && v < h
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
fn parameters(placed: &[Placed], sh_degree: u32) -> Vec<f32> {
    let l = Layout::new(placed.len(), sh_degree);
    let n = l.n;
    let mut params = vec![0.0f32; l.len()];
    for (i, (p, size, colour)) in placed.iter().enumerate() {
        params[3 * i..3 * i + 3].copy_from_slice(p);
        params[3 * n + 3 * i..3 * n + 3 * i + 3].fill(size.max(1e-6).ln());
        params[6 * n + 4 * i] = 1.0;
        params[10 * n + i] = 0.0; // opacity 0.5
        for c in 0..3 {
            params[11 * n + 3 * i + c] = (colour[c] - 0.5) / SH_C0;
        }
    }
    params
}

/// What a photo's placement rays saw: the distance along each ray of a
/// jittered grid (`spacing` pixels a cell) to what it hit (infinite where
/// it hit nothing, NaN where it is unsure).
struct DepthGrid {
    nx: usize,
    ny: usize,
    /// The grid's top-left corner on the image (pixels; negative: the
    /// grid starts past the photo's edge).
    origin: [f32; 2],
    spacing: f32,
    depth: Vec<f32>,
}

/// Drops the placed Gaussians that another photo sees through (free-space
/// carving): one that lies well in front (nearer than [`CARVE_MARGIN`]
/// times) of what photo `b` saw in each grid cell around its pixel there
/// is a floater in `b`'s free space. `owners`: the photo each was placed
/// from, whose own rays are not asked. One placed `outside` its photo's
/// frame also goes when another photo saw it within its frame (that photo
/// placed its own there): the margins fill only what no photo saw.
fn carve(
    placed: Vec<Placed>,
    owners: &[u32],
    outside: &[bool],
    grids: &[DepthGrid],
    cams: &[RasterCamera],
) -> Vec<Placed> {
    use rayon::prelude::*;
    let keep: Vec<bool> = placed
        .par_iter()
        .zip(owners)
        .zip(outside)
        .map(|((p, &owner), &outside)| {
            let mut seen = false;
            for (b, (cam, g)) in cams.iter().zip(grids).enumerate() {
                if b == owner as usize {
                    continue;
                }
                let t = cam.to_camera(p.0);
                if t[2] <= 0.0 {
                    continue;
                }
                let (u, v) = (cam.fx * t[0] / t[2] + cam.cx, cam.fy * t[1] / t[2] + cam.cy);
                let (gx, gy) = ((u - g.origin[0]) / g.spacing, (v - g.origin[1]) / g.spacing);
                if !(gx >= 0.0 && gy >= 0.0 && gx < g.nx as f32 && gy < g.ny as f32) {
                    continue;
                }
                let (gx, gy) = (gx as usize, gy as usize);
                let mut nearest = f32::INFINITY;
                let mut known = true;
                for y in gy.saturating_sub(1)..(gy + 2).min(g.ny) {
                    for x in gx.saturating_sub(1)..(gx + 2).min(g.nx) {
                        let d = g.depth[y * g.nx + x];
                        known &= !d.is_nan();
                        nearest = nearest.min(d);
                    }
                }
                let dist = Vec3::from_array(t).norm();
                if known && dist < CARVE_MARGIN * nearest {
                    return false;
                }
                seen |= outside
                    && in_frame(u, v, cam.width as f32, cam.height as f32)
                    && dist < g.depth[gy * g.nx + gx] / CARVE_MARGIN;
            }
            !seen
        })
        .collect();
    placed.into_iter().zip(keep).filter_map(|(p, k)| k.then_some(p)).collect()
}

/// Each point's root-mean-square distance to its three nearest neighbours
/// (the 3DGS paper's initial scale), found in a hash of cells as wide as
/// the median of the points' own sizes; `None` for a point with fewer than
/// three neighbours in its cell and the 26 around it.
fn neighbour_spacing(points: &[Placed]) -> Vec<Option<f32>> {
    let mut sizes: Vec<f32> = points.iter().map(|p| p.1).collect();
    let mid = sizes.len() / 2;
    let cell = *sizes.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1;
    if !(cell > 0.0 && cell.is_finite()) {
        return vec![None; points.len()];
    }
    let key = |p: &[f32; 3]| p.map(|v| (v / cell).floor() as i64);
    let mut cells: std::collections::HashMap<[i64; 3], Vec<u32>> = std::collections::HashMap::new();
    for (i, p) in points.iter().enumerate() {
        cells.entry(key(&p.0)).or_default().push(i as u32);
    }
    use rayon::prelude::*;
    points
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let k = key(&p.0);
            let mut best = [f32::INFINITY; 3];
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let Some(list) = cells.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) else { continue };
                        for &j in list {
                            if j as usize == i {
                                continue;
                            }
                            let q = &points[j as usize].0;
                            let d2 = (0..3).map(|c| (q[c] - p.0[c]).powi(2)).sum::<f32>();
                            if d2 < best[2] {
                                best[2] = d2;
                                best.sort_by(|a, b| a.total_cmp(b));
                            }
                        }
                    }
                }
            }
            best[2].is_finite().then(|| ((best[0] + best[1] + best[2]) / 3.0).sqrt().max(1e-7))
        })
        .collect()
}

/// Densifies and prunes (module docs): the new parameters and Adam moments
/// (new Gaussians start with zero moments).
fn densify(
    model: &SplatsModel,
    adam: &Adam,
    grad_accum: &[(f32, u32)],
    max: usize,
    rng: &mut Rng,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let l = model.layout();
    let p = model.params();
    let n = l.n;
    let sig = |x: f32| 1.0 / (1.0 + (-x).exp());
    let keep: Vec<usize> = (0..n).filter(|&i| sig(p[10 * n + i]) >= PRUNE_OPACITY).collect();
    let mut grow: Vec<usize> = keep
        .iter()
        .copied()
        .filter(|&i| grad_accum[i].1 > 0 && grad_accum[i].0 / grad_accum[i].1 as f32 > DENSIFY_GRAD)
        .collect();
    let room = max.saturating_sub(keep.len());
    if grow.len() > room {
        // The largest gradients first.
        let avg = |i: usize| grad_accum[i].0 / grad_accum[i].1 as f32;
        grow.sort_by(|&a, &b| avg(b).total_cmp(&avg(a)));
        grow.truncate(room);
    }
    let mut all = keep.clone();
    all.extend_from_slice(&grow);
    let mut params = l.select(p, &all);
    let mut m = l.select(&adam.m, &all);
    let mut v = l.select(&adam.v, &all);
    let to = Layout { n: all.len(), k: l.k };
    let tn = to.n;
    // Zero moments for the new ones; a large one is split: both halves
    // move to a sample of it and shrink by 1.6 (the paper's).
    for j in keep.len()..tn {
        for r in [to.means(), to.log_scales(), to.rotations(), to.opacities(), to.sh_dc(), to.sh_rest()] {
            let width = r.len() / tn;
            for c in 0..width {
                m[r.start + width * j + c] = 0.0;
                v[r.start + width * j + c] = 0.0;
            }
        }
        let src = all[j];
        let g = l.get(p, src);
        let big = g.log_scale.iter().cloned().fold(f32::MIN, f32::max).exp() > 0.01;
        if big {
            let s = g.log_scale.map(f32::exp);
            let r = crate::engine::models::splats::gaussians::rotation_matrix(
                crate::engine::models::splats::gaussians::unit_quat(g.rotation),
            );
            let z = [rng.normal() * s[0], rng.normal() * s[1], rng.normal() * s[2]];
            for c in 0..3 {
                let off = r[c][0] * z[0] + r[c][1] * z[1] + r[c][2] * z[2];
                params[3 * j + c] = g.mean[c] + off;
                params[3 * tn + 3 * j + c] = g.log_scale[c] - 1.6f32.ln();
            }
            // The original (kept at its index in `keep`, which is in
            // ascending order) shrinks too.
            let i = keep.binary_search(&src).expect("grown from kept");
            for c in 0..3 {
                params[3 * tn + 3 * i + c] = g.log_scale[c] - 1.6f32.ln();
                params[3 * i + c] = g.mean[c] - (params[3 * j + c] - g.mean[c]);
            }
        }
    }
    (params, m, v)
}

/// `cam` at half its size: every pixel of it covers two by two of `cam`'s.
fn half_camera(cam: &RasterCamera) -> RasterCamera {
    RasterCamera {
        width: cam.width / 2,
        height: cam.height / 2,
        fx: 0.5 * cam.fx,
        fy: 0.5 * cam.fy,
        cx: 0.5 * cam.cx,
        cy: 0.5 * cam.cy,
        ..*cam
    }
}

/// How many of a target's values are valid (not masked out: NaN).
fn valid_values(rgb: &[f32]) -> usize {
    rgb.iter().filter(|v| !v.is_nan()).count()
}

/// A photo (`[h x w x 3]`, NaN where masked out) at half size, each pixel
/// the mean of its two by two (NaN if any of them is).
fn halve(rgb: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (hw, hh) = (w / 2, h / 2);
    let mut out = Vec::with_capacity(hw * hh * 3);
    for j in 0..hh {
        for i in 0..hw {
            for c in 0..3 {
                let at = |x: usize, y: usize| rgb[3 * (y * w + x) + c];
                out.push(
                    0.25 * (at(2 * i, 2 * j) + at(2 * i + 1, 2 * j) + at(2 * i, 2 * j + 1) + at(2 * i + 1, 2 * j + 1)),
                );
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::scene::Scene;

    /// The unit box's scene, and a camera 4 units from its centre along
    /// -y, looking at it (z up).
    fn facing_origin() -> (Scene, [[f32; 4]; 3]) {
        let scene = Scene::from_bounds(
            crate::engine::geometry::math::Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) },
            0.0,
            10.0,
        );
        (scene, look_at(Vec3::new(0.0, -4.0, 0.0), Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap())
    }

    #[test]
    fn a_ray_leaves_a_sphere_where_the_analytic_root_says() {
        let r = Ray { origin: Vec3::new(0.5, 0.0, 0.0), dir: Vec3::new(0.6, 0.8, 0.0) };
        // |o + t d| = 2: t² + 0.6 t + 0.25 - 4 = 0.
        let want = (-0.6 + (0.36f32 + 4.0 * 3.75).sqrt()) / 2.0;
        assert!((exit_distance(&r, 2.0) - want).abs() < 1e-6);
        assert!(exit_distance(&Ray { origin: Vec3::new(3.0, 0.0, 0.0), ..r }, 2.0).is_infinite());
    }

    #[test]
    fn carving_drops_what_another_photo_sees_through_and_keeps_what_it_sees() {
        let (scene, c2w) = facing_origin();
        // Both photos look at the origin from 4 units away along -y; photo
        // 1 saw a wall 4 units away everywhere (3x3 cells of 10 px), photo
        // 0 is unsure of all its depths.
        let cams = vec![RasterCamera::new(&Camera::from_fov(30, 30, 1.0, c2w), &scene); 2];
        let grid = |d: f32| DepthGrid { nx: 3, ny: 3, origin: [0.0; 2], spacing: 10.0, depth: vec![d; 9] };
        let grids = [grid(f32::NAN), grid(4.0)];
        let placed: Vec<Placed> = vec![
            ([0.0, -2.0, 0.0], 0.1, [1.0; 3]), // halfway: photo 1's free space
            ([0.0, 0.0, 0.0], 0.1, [1.0; 3]),  // on the wall
            ([0.0, 1.0, 0.0], 0.1, [1.0; 3]),  // behind it
            ([0.0, -2.0, 0.0], 0.1, [1.0; 3]), // halfway, but photo 1's own
        ];
        let kept = carve(placed.clone(), &[0, 0, 0, 1], &[false; 4], &grids, &cams);
        assert_eq!(kept, vec![placed[1], placed[2], placed[3]]);
        // One that saw nothing (infinitely far) carves all it sees.
        let empty = [grid(f32::INFINITY), grid(f32::INFINITY)];
        assert_eq!(carve(placed.clone(), &[1, 1, 1, 1], &[false; 4], &empty, &cams), vec![]);
        // Placed past photo 0's frame: the one on the wall, which photo 1
        // saw within its frame, goes; one beside the wall, past photo 1's
        // frame too (its half-width there is 4 tan 0.5 = 2.2), stays.
        let beside: Placed = ([3.0, 0.0, 0.0], 0.1, [1.0; 3]);
        let margin = vec![placed[1], beside];
        assert_eq!(carve(margin.clone(), &[0, 0], &[true, true], &grids, &cams), vec![beside]);
        assert_eq!(carve(margin.clone(), &[0, 0], &[false, false], &grids, &cams), margin);
    }

    #[test]
    fn a_halved_photo_is_the_mean_of_each_two_by_two_and_nan_where_any_is() {
        // 5x3 pixels, value 10 y + x in every channel; the last column and
        // row fall outside the half-size photo's 2x1.
        let mut rgb: Vec<f32> = (0..3).flat_map(|y| (0..5).flat_map(move |x| [(10 * y + x) as f32; 3])).collect();
        let half = halve(&rgb, 5, 3);
        assert_eq!(half, [[5.5f32; 3], [7.5; 3]].concat());
        assert_eq!(valid_values(&half), 6);
        rgb[3 * (5 + 3) + 1] = f32::NAN; // pixel (3, 1), green
        let half = halve(&rgb, 5, 3);
        assert_eq!(&half[..4], &[5.5, 5.5, 5.5, 7.5]);
        assert!(half[4].is_nan() && half[5] == 7.5);
        assert_eq!(valid_values(&half), 5);
    }

    #[test]
    fn a_view_at_half_size_is_the_full_view_averaged_two_by_two() {
        // One Gaussian off the axis, its standard deviation about 5 px at
        // full size, drawn at 64x48 and at 32x24 by the half camera: the
        // half view is the full one's two-by-two means, up to the box
        // filter's blur and the dilation (a fixed 0.3 px² at either size).
        // A half camera off by half of its pixel differs from them many
        // times as much.
        let (scene, c2w) = facing_origin();
        let full = RasterCamera::new(&Camera::from_fov(64, 48, 0.8, c2w), &scene);
        let params = parameters(&[([0.3, 0.0, 0.2], 0.3, [0.9, 0.6, 0.3])], 0);
        let l = Layout::new(1, 0);
        let opt = RasterOptions::default();
        let draw = |cam: &RasterCamera| forward(&l, &params, cam, &opt, [0.0; 3]).rgb;
        let want = halve(&draw(&full), 64, 48);
        let worst = |cam: &RasterCamera| draw(cam).iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        let half = half_camera(&full);
        assert_eq!((half.width, half.height), (32, 24));
        let peak = want.iter().fold(0.0f32, |m, &v| m.max(v));
        let (right, shifted) = (worst(&half), worst(&RasterCamera { cx: half.cx + 0.5, ..half }));
        assert!(peak > 0.3, "the Gaussian is in view: peak {peak}");
        // Measured: 0.0048 against a peak of 0.44, and 0.050 shifted.
        assert!(right < 0.02 * peak, "{right} against a peak of {peak}");
        assert!(shifted > 5.0 * right, "shifted {shifted}, right {right}");
    }
}
