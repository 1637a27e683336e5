//! What fitting splats to photos needs of them, in one call: a view drawn,
//! its squared error against a photo, and the error's gradient with
//! respect to every parameter (`bake` uses nothing else of the
//! rasteriser).

use super::SplatsModel;
use super::backward::{ScreenGrad, backward};
use super::dssim::ssim_and_gradient;
use super::looks::ColourCorrection;
use super::raster::{RasterCamera, RasterOptions, forward};
use crate::engine::models::Model;

/// One view fitted: its error and where the loss wants each Gaussian.
pub struct ViewFit {
    /// The squared error summed over the target's values that are not NaN.
    pub squared_error: f64,
    /// Each Gaussian's screen-space gradient (its first two entries: how
    /// much the loss wants it to move on the image, in units of the half
    /// image; zero for one the view does not draw).
    pub screen: Vec<ScreenGrad>,
    /// The colour correction the view was fitted through (the identity
    /// without [`FitLoss::look_ridge`]).
    pub correction: ColourCorrection,
}

/// What a view is fitted by.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FitLoss {
    /// The weight of one minus the mean SSIM beside the squared error's
    /// `1 - ssim_weight` (`dssim`; none for a view under 11 pixels either
    /// way).
    pub ssim_weight: f32,
    /// With a ridge: the drawn view is first mapped by the colour
    /// correction that best fits the photo with that ridge
    /// ([`ColourCorrection::fit`]), and the loss is the mapped view's (its
    /// gradient taken with the correction held: the correction is fitted
    /// afresh each view, not learned by gradient).
    pub look_ridge: Option<f64>,
    /// With a correction, the share of the loss that is the view's as
    /// drawn, without it: it keeps the splats' own look at the photos'
    /// common one, which the corrections alone leave free.
    pub own_weight: f32,
}

impl SplatsModel {
    /// Draws `cam` on `background` and adds to `grads` (laid out as the
    /// parameters, of their length) the gradient of `loss` against
    /// `target` (`[h x w x 3]`, NaN where there is no loss): the mean
    /// squared error over `valid` values, weighted `1 - ssim_weight`, plus
    /// `ssim_weight` times one minus the mean SSIM, of the view as drawn or
    /// through its fitted colour correction ([`FitLoss`]).
    pub fn fit_view(
        &self,
        cam: &RasterCamera,
        target: &[f32],
        valid: usize,
        background: [f32; 3],
        loss: FitLoss,
        grads: &mut [f32],
    ) -> ViewFit {
        let (l, opt) = (self.layout(), RasterOptions::for_scene(self.scene()));
        let f = forward(&l, self.params(), cam, &opt, background);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let (squared_error, d_rgb, correction) = match loss.look_ridge {
            None => {
                let (e, d) = loss_gradient(&f.rgb, target, valid, loss.ssim_weight, w, h);
                (e, d, ColourCorrection::IDENTITY)
            }
            Some(ridge) => {
                let correction = ColourCorrection::fit(&f.rgb, target, ridge);
                let mut drawn = f.rgb.clone();
                correction.apply(&mut drawn);
                let (e, mut d) = loss_gradient(&drawn, target, valid, loss.ssim_weight, w, h);
                correction.pull_back(&mut d);
                if loss.own_weight > 0.0 {
                    // The view as drawn is fitted too, a little: it keeps
                    // the splats' own look at the photos' common one.
                    let (_, own) = loss_gradient(&f.rgb, target, valid, loss.ssim_weight, w, h);
                    for (d, o) in d.iter_mut().zip(&own) {
                        *d = (1.0 - loss.own_weight) * *d + loss.own_weight * o;
                    }
                }
                (e, d, correction)
            }
        };
        let screen = backward(&l, self.params(), cam, &opt, &f, &d_rgb, grads);
        ViewFit { squared_error, screen, correction }
    }
}

/// The squared error of `drawn` against `target` over its `valid`
/// values, and the gradient of `1 - ssim_weight` times their mean plus
/// `ssim_weight` times one minus the mean SSIM with respect to `drawn`
/// (`w x h x 3`).
fn loss_gradient(drawn: &[f32], target: &[f32], valid: usize, ssim_weight: f32, w: usize, h: usize) -> (f64, Vec<f32>) {
    let n = valid.max(1) as f32;
    let mut squared_error = 0.0f64;
    let mut d_rgb: Vec<f32> = drawn
        .iter()
        .zip(target)
        .map(|(r, t)| {
            if t.is_nan() {
                return 0.0;
            }
            let e = r - t;
            squared_error += (e * e) as f64;
            2.0 * e / n
        })
        .collect();
    if let Some((_, g)) = (ssim_weight > 0.0).then(|| ssim_and_gradient(drawn, target, w, h)).flatten() {
        for (d, g) in d_rgb.iter_mut().zip(&g) {
            *d = (1.0 - ssim_weight) * *d - ssim_weight * g;
        }
    }
    (squared_error, d_rgb)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::models::splats::SplatsConfig;
    use crate::engine::models::splats::dssim::ssim_f64;
    use crate::engine::models::splats::gaussians::Layout;
    use crate::engine::models::splats::raster_tests::{camera, random_gaussians, unit_scene};
    use crate::engine::rng::Rng;

    /// A small view of four random Gaussians, and a target of random
    /// colours with every fifth value masked out (NaN).
    fn case() -> (SplatsModel, RasterCamera, Vec<f32>) {
        let scene = unit_scene();
        let cam = RasterCamera::new(&camera([0.4, -4.0, 0.6], 24, 18, 35.0), &scene);
        let (_, mut p) = random_gaussians(4, 1, 11, 0.8);
        let l = Layout::new(4, 1);
        for v in &mut p[l.log_scales()] {
            *v += 1.0;
        }
        let config = SplatsConfig { sh_degree: 1, ..SplatsConfig::default() };
        let model = SplatsModel::from_parts(config, scene, p).unwrap();
        let mut rng = Rng::new(5);
        let target = (0..24 * 18 * 3).map(|k| if k % 5 == 0 { f32::NAN } else { rng.f32() }).collect();
        (model, cam, target)
    }

    /// The mean squared error over the valid values, in f64.
    fn mse(model: &SplatsModel, cam: &RasterCamera, target: &[f32], bg: [f32; 3]) -> f64 {
        let f = forward(&model.layout(), model.params(), cam, &RasterOptions::default(), bg);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (r, t) in f.rgb.iter().zip(target).filter(|(_, t)| !t.is_nan()) {
            sum += ((r - t) as f64).powi(2);
            n += 1;
        }
        sum / n as f64
    }

    /// Checks `grads` on every parameter of `ranges` against central
    /// differences (steps of 0.01) of the f64 `loss`, within `rel` of the
    /// larger plus 1e-5; how many of them were away from zero.
    fn checked_by_differences(
        model: &SplatsModel,
        grads: &[f32],
        ranges: &[std::ops::Range<usize>],
        rel: f64,
        loss: impl Fn(&SplatsModel) -> f64,
    ) -> usize {
        let mut checked = 0;
        for i in ranges.iter().cloned().flatten() {
            let step = 1e-2f32;
            let at = |d: f32| {
                let mut p = model.params().to_vec();
                p[i] += d;
                loss(&SplatsModel::from_parts(model.config.clone(), model.scene().clone(), p).unwrap())
            };
            let fd = (at(step) - at(-step)) / (2.0 * step as f64);
            let an = grads[i] as f64;
            assert!((an - fd).abs() <= rel * fd.abs().max(an.abs()) + 1e-5, "[{i}]: analytic {an}, differences {fd}");
            checked += (fd.abs() > 1e-4) as usize;
        }
        checked
    }

    #[test]
    fn a_views_error_and_gradient_are_those_of_its_mean_squared_error() {
        let (model, cam, target) = case();
        let bg = [0.2, 0.5, 0.9];
        let valid = target.iter().filter(|t| !t.is_nan()).count();
        let mut grads = vec![0.0f32; model.params().len()];
        let fit = model.fit_view(&cam, &target, valid, bg, FitLoss::default(), &mut grads);
        let want = mse(&model, &cam, &target, bg);
        assert!((fit.squared_error / valid as f64 - want).abs() <= 1e-6 * want, "{} against {want}", fit.squared_error);
        assert_eq!(fit.screen.len(), 4);
        // Central differences of the f64 error through the f32 forward,
        // on every colour term (the error is quadratic in them) and the
        // opacities; masked values must pull on nothing.
        let l = model.layout();
        let ranges = [l.sh_dc(), l.sh_rest(), l.opacities()];
        let checked = checked_by_differences(&model, &grads, &ranges, 2e-3, |m| mse(m, &cam, &target, bg));
        assert!(checked > 10, "only {checked} gradients were away from zero");
    }

    #[test]
    fn through_a_fitted_correction_the_gradient_is_that_of_the_mapped_views_loss() {
        // A target that is the drawn view's colours mapped and shifted, so
        // the fitted correction is far from the identity; the gradient is
        // the weighted loss's of the view mapped by the correction held,
        // mixed with the view as drawn by `own_weight`.
        let (model, cam, mut target) = case();
        let (bg, weight, ridge) = ([0.2, 0.5, 0.9], 0.3f32, 0.01);
        let drawn = forward(&model.layout(), model.params(), &cam, &RasterOptions::default(), bg).rgb;
        let skew = ColourCorrection([[0.7, 0.2, 0.0, 0.1], [0.0, 1.3, -0.1, -0.05], [0.1, 0.0, 0.8, 0.2]]);
        for (k, t) in target.iter_mut().enumerate() {
            if !t.is_nan() {
                let p = k / 3 * 3;
                *t = 0.8 * skew.map([drawn[p], drawn[p + 1], drawn[p + 2]])[k % 3] + 0.2 * *t;
            }
        }
        let valid = target.iter().filter(|t| !t.is_nan()).count();
        let (w, h) = (cam.width as usize, cam.height as usize);
        // The weighted loss of the view mapped by `m`, in f64.
        let mapped_loss = |model: &SplatsModel, m: ColourCorrection, base: &[f64]| {
            let x = forward(&model.layout(), model.params(), &cam, &RasterOptions::default(), bg).rgb;
            let x: Vec<f64> = x.chunks_exact(3).flat_map(|c| m.map([c[0], c[1], c[2]])).map(f64::from).collect();
            let kept: Vec<f64> =
                target.iter().zip(base).map(|(&t, &d)| if t.is_nan() { d } else { t as f64 }).collect();
            let (sum, n) = x
                .iter()
                .zip(&target)
                .filter(|(_, t)| !t.is_nan())
                .fold((0.0, 0), |(s, n), (a, &t)| (s + (a - t as f64).powi(2), n + 1));
            (1.0 - weight as f64) * sum / n as f64 + weight as f64 * (1.0 - ssim_f64(&x, &kept, w, h))
        };
        for own in [0.0f32, 0.4] {
            let mut grads = vec![0.0f32; model.params().len()];
            let loss = FitLoss { ssim_weight: weight, look_ridge: Some(ridge), own_weight: own };
            let held = model.fit_view(&cam, &target, valid, bg, loss, &mut grads).correction;
            assert_eq!(held, ColourCorrection::fit(&drawn, &target, ridge));
            let off = held.0.iter().flatten().zip(ColourCorrection::IDENTITY.0.iter().flatten());
            let off = off.map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(off > 0.1, "the correction is far from the identity: {held:?}");
            // The drawn values the NaN targets take in the SSIM, held.
            let base = |m: ColourCorrection| -> Vec<f64> {
                drawn.chunks_exact(3).flat_map(|c| m.map([c[0], c[1], c[2]])).map(f64::from).collect()
            };
            let (base_mapped, base_own) = (base(held), base(ColourCorrection::IDENTITY));
            let f64_loss = |m: &SplatsModel| {
                (1.0 - own as f64) * mapped_loss(m, held, &base_mapped)
                    + own as f64 * mapped_loss(m, ColourCorrection::IDENTITY, &base_own)
            };
            let l = model.layout();
            let checked = checked_by_differences(&model, &grads, &[l.sh_dc(), l.opacities()], 1e-2, f64_loss);
            assert!(checked > 6, "own weight {own}: only {checked} gradients were away from zero");
        }
    }

    #[test]
    fn with_ssim_the_gradient_is_that_of_the_weighted_loss() {
        let (model, cam, target) = case();
        let (bg, weight) = ([0.2, 0.5, 0.9], 0.3f32);
        let valid = target.iter().filter(|t| !t.is_nan()).count();
        let mut grads = vec![0.0f32; model.params().len()];
        model.fit_view(&cam, &target, valid, bg, FitLoss { ssim_weight: weight, ..FitLoss::default() }, &mut grads);
        // The photo's NaN values take the drawn view's, held where it is.
        let drawn = forward(&model.layout(), model.params(), &cam, &RasterOptions::default(), bg).rgb;
        let held: Vec<f64> = target.iter().zip(&drawn).map(|(&t, &d)| if t.is_nan() { d } else { t } as f64).collect();
        let (w, h) = (cam.width as usize, cam.height as usize);
        let loss = |m: &SplatsModel| {
            let x = forward(&m.layout(), m.params(), &cam, &RasterOptions::default(), bg).rgb;
            let x: Vec<f64> = x.iter().map(|&v| v as f64).collect();
            (1.0 - weight as f64) * mse(m, &cam, &target, bg) + weight as f64 * (1.0 - ssim_f64(&x, &held, w, h))
        };
        let l = model.layout();
        let checked = checked_by_differences(&model, &grads, &[l.sh_dc(), l.opacities()], 1e-2, loss);
        assert!(checked > 6, "only {checked} gradients were away from zero");
    }
}
