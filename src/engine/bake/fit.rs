//! Fitting the placed splats to the training photos (the module docs of
//! `bake`, stage 2): the state between steps, one step, and Adam's rates
//! per block.

use super::background::{Background, zero_rest};
use super::clear::CameraBalls;
use super::{BakeSettings, COARSE_SHARE, densify};
use crate::engine::dataset::Dataset;
use crate::engine::models::Model;
use crate::engine::models::splats::SplatsModel;
use crate::engine::models::splats::fit::FitLoss;
use crate::engine::models::splats::gaussians::Layout;
use crate::engine::models::splats::lens;
use crate::engine::models::splats::looks::{ColourCorrection, Looks};
use crate::engine::models::splats::raster::RasterCamera;
use crate::engine::nn::adam::{Adam, AdamConfig, LrGroup};
use crate::engine::rng::Rng;
use crate::engine::transient::TransientMaps;

/// The learning rate the blocks' scales multiply: four times the 3DGS
/// paper's rates, since a bake has hundreds of steps where the paper has
/// 30k.
const BASE_LR: f32 = 4e-3;

/// The first coarse step's rate as a share of [`BASE_LR`], rising to all
/// of it by the last ([`coarse_rate`]).
const COARSE_RATE: f32 = 0.5;

/// A coarse step's rate as a share of [`BASE_LR`], `progress` into the
/// budget: the placed splats start near the field, and a photo at half
/// size, taken once or twice in the coarse steps, pulls them about more
/// than it tells them; the rate rises to the whole by the full-size steps
/// (docs/design/splats.md).
fn coarse_rate(progress: f64) -> f32 {
    COARSE_RATE + (1.0 - COARSE_RATE) * (progress / COARSE_SHARE).clamp(0.0, 1.0) as f32
}

/// The weight of one minus the SSIM in the loss, beside the squared error
/// (`SplatsModel::fit_view`): it keeps edges and texture the squared error
/// alone blurs (docs/design/splats.md).
const SSIM_WEIGHT: f32 = 0.05;

/// The ridge that draws each photo's colour correction towards the
/// identity (`splats::looks`), per pixel of the photo.
const LOOK_RIDGE: f64 = 0.1;

/// With corrections, the share of the loss that is the view's as drawn
/// (`FitLoss::own_weight`): it keeps the splats' own look, which the
/// browser and the exports show, at the photos' common one.
const OWN_WEIGHT: f32 = 0.4;

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
    // The SH terms, all at the paper's DC rate (its twentieth for the
    // others is for 30k steps, and loses in a few hundred).
    g.push(LrGroup { range: l.sh_dc(), scale: 2.5 });
    g.push(LrGroup { range: l.sh_rest(), scale: 2.5 });
    g
}

/// The fitting stage's state.
pub(super) struct Fit<'a> {
    ds: &'a Dataset,
    frames: Vec<usize>,
    settings: &'a BakeSettings,
    pub model: SplatsModel,
    pub adam: Adam,
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
    pub step: u64,
    pub smoothed_psnr: f64,
    grads: Vec<f32>,
    /// No Gaussian stays this near a training camera (`clear`).
    balls: CameraBalls,
    /// Where Gaussians keep a colour of degree 0 (`background`).
    background: Option<Background>,
    /// Each photo's colour correction, as last fitted (`None` for a photo
    /// not yet taken); `None` when the bake fits none.
    corrections: Option<Vec<Option<ColourCorrection>>>,
}

impl<'a> Fit<'a> {
    /// `dropped`: the pixels training dropped as transient, which are not
    /// fitted (their maps are of `frames`, in order); `balls`: where no
    /// Gaussian is kept at a densification or pruning.
    pub fn new(
        ds: &'a Dataset,
        frames: Vec<usize>,
        settings: &'a BakeSettings,
        model: SplatsModel,
        dropped: Option<&TransientMaps>,
        balls: CameraBalls,
    ) -> Self {
        let adam_config = AdamConfig { lr: BASE_LR, lr_end: BASE_LR, beta1: 0.9, beta2: 0.999, eps: 1e-15 };
        let adam = Adam::new(adam_config, model.params().len());
        let bg = ds.background;
        let targets: Vec<Vec<f32>> = frames
            .iter()
            .enumerate()
            .map(|(k, &f)| {
                let im = &ds.frames[f].image;
                let kept = |i: u32, j: u32| dropped.is_none_or(|m| m.weight(k, i, j) > 0.0);
                let rgb: Vec<f32> = (0..im.height)
                    .flat_map(|j| {
                        (0..im.width).flat_map(move |i| if kept(i, j) { im.rgb_on(i, j, bg) } else { [f32::NAN; 3] })
                    })
                    .collect();
                // The rasteriser draws the pinhole part of a camera: a
                // distorted photo is fitted as that camera would have
                // taken it (NaN where it does not reach: no loss there).
                let camera = &ds.frames[f].camera;
                if camera.distortion.is_identity() { rgb } else { lens::undistort_photo(camera, &rgb) }
            })
            .collect();
        let n = model.layout().n;
        Self {
            background: Background::of(ds, model.scene()),
            balls,
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
            corrections: None,
        }
    }

    /// From now on, each photo is fitted through its own colour correction.
    pub fn fit_looks(&mut self) {
        self.corrections = Some(vec![None; self.frames.len()]);
    }

    /// The corrections of the photos taken, as last fitted, by frame index
    /// (`None` when the bake fits none): a photo never taken has no look of
    /// its own to give a view.
    pub fn looks(&self) -> Option<Looks> {
        let corrections = self.corrections.as_ref()?;
        let mut pairs: Vec<(u32, ColourCorrection)> =
            self.frames.iter().zip(corrections).filter_map(|(&f, c)| c.map(|c| (f as u32, c))).collect();
        pairs.sort_by_key(|p| p.0);
        let (images, corrections) = pairs.into_iter().unzip();
        Some(Looks { images, corrections, background: self.ds.background })
    }

    /// One step on the next photo of the epoch, `progress` into the budget.
    pub fn step(&mut self, progress: f64) {
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
        // The gradient buffer is kept between steps (zeroing it is cheaper
        // than the page faults of a fresh one of the parameters' size).
        let l = self.model.layout();
        let mut grads = std::mem::take(&mut self.grads);
        grads.clear();
        grads.resize(l.len(), 0.0);
        let look_ridge = self.corrections.is_some().then_some(LOOK_RIDGE);
        let loss = FitLoss { ssim_weight: SSIM_WEIGHT, look_ridge, own_weight: OWN_WEIGHT };
        let fit = self.model.fit_view(&cam, target, valid, self.ds.background, loss, &mut grads);
        if let Some(c) = &mut self.corrections {
            c[which] = Some(fit.correction);
        }
        let psnr = -10.0 * (fit.squared_error / valid.max(1) as f64).max(1e-10).log10();
        self.smoothed_psnr = if self.step == 0 { psnr } else { 0.9 * self.smoothed_psnr + 0.1 * psnr };
        let (hw, hh) = (0.5 * cam.width as f32, 0.5 * cam.height as f32);
        for (acc, s) in self.grad_accum.iter_mut().zip(&fit.screen) {
            if s[0] != 0.0 || s[1] != 0.0 {
                acc.0 += ((s[0] * hw).powi(2) + (s[1] * hh).powi(2)).sqrt();
                acc.1 += 1;
            }
        }
        let groups = groups(&l, progress);
        let far = self.background.as_ref().map(|b| b.members(&l, self.model.params())).unwrap_or_default();
        zero_rest(&l, &mut grads, &far);
        let lr = if coarse { coarse_rate(progress) * BASE_LR } else { BASE_LR };
        self.adam.step_groups(self.model.params_mut(), &mut grads, lr, &groups);
        // Adam's momentum would move them still.
        zero_rest(&l, self.model.params_mut(), &far);
        self.grads = grads;
        self.step += 1;
    }

    /// Densifies and prunes within `max` Gaussians (0: prunes only).
    pub fn densify(&mut self, max: usize) {
        let (params, m, v) =
            densify::densify(&self.model, &self.adam, &self.grad_accum, max, &self.balls, &mut self.rng);
        self.adam.m = m;
        self.adam.v = v;
        let scene = self.model.scene().clone();
        self.model = SplatsModel::from_parts(self.settings.splats.clone(), scene, params).expect("same layout");
        self.grad_accum = vec![(0.0, 0); self.model.layout().n];
    }

    /// Prunes the nearly transparent Gaussians, growing none.
    pub fn prune(&mut self) {
        self.grad_accum.iter_mut().for_each(|a| *a = (0.0, 0));
        self.densify(0);
    }
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
    use crate::engine::bake::Placed;
    use crate::engine::bake::place::parameters;
    use crate::engine::bake::testutil::facing_origin;
    use crate::engine::geometry::camera::Camera;
    use crate::engine::models::splats::raster::{RasterOptions, forward};

    #[test]
    fn a_coarse_steps_rate_rises_from_half_to_the_whole() {
        assert_eq!(coarse_rate(0.0), 0.5);
        assert_eq!(coarse_rate(0.5 * COARSE_SHARE), 0.75);
        assert_eq!(coarse_rate(COARSE_SHARE), 1.0);
        assert_eq!(coarse_rate(0.9), 1.0);
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
        let params = parameters(&[Placed::ball([0.3, 0.0, 0.2], 0.3, [0.9, 0.6, 0.3])], 0);
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
