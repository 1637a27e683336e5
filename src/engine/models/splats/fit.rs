//! What fitting splats to photos needs of them, in one call: a view drawn,
//! its squared error against a photo, and the error's gradient with
//! respect to every parameter (`bake` uses nothing else of the
//! rasteriser).

use super::SplatsModel;
use super::backward::{ScreenGrad, backward};
use super::dssim::ssim_and_gradient;
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
}

impl SplatsModel {
    /// Draws `cam` on `background` and adds to `grads` (laid out as the
    /// parameters, of their length) the gradient of the loss against
    /// `target` (`[h x w x 3]`, NaN where there is no loss): the mean
    /// squared error over `valid` values, weighted `1 - ssim_weight`, plus
    /// `ssim_weight` times one minus the mean SSIM (`dssim`; none for a
    /// view under 11 pixels either way).
    pub fn fit_view(
        &self,
        cam: &RasterCamera,
        target: &[f32],
        valid: usize,
        background: [f32; 3],
        ssim_weight: f32,
        grads: &mut [f32],
    ) -> ViewFit {
        let (l, opt) = (self.layout(), RasterOptions::for_scene(self.scene()));
        let f = forward(&l, self.params(), cam, &opt, background);
        let n = valid.max(1) as f32;
        let mut squared_error = 0.0f64;
        let mut d_rgb: Vec<f32> = f
            .rgb
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
        let (w, h) = (cam.width as usize, cam.height as usize);
        if let Some((_, g)) = (ssim_weight > 0.0).then(|| ssim_and_gradient(&f.rgb, target, w, h)).flatten() {
            for (d, g) in d_rgb.iter_mut().zip(&g) {
                *d = (1.0 - ssim_weight) * *d - ssim_weight * g;
            }
        }
        let screen = backward(&l, self.params(), cam, &opt, &f, &d_rgb, grads);
        ViewFit { squared_error, screen }
    }
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
        let fit = model.fit_view(&cam, &target, valid, bg, 0.0, &mut grads);
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
    fn with_ssim_the_gradient_is_that_of_the_weighted_loss() {
        let (model, cam, target) = case();
        let (bg, weight) = ([0.2, 0.5, 0.9], 0.3f32);
        let valid = target.iter().filter(|t| !t.is_nan()).count();
        let mut grads = vec![0.0f32; model.params().len()];
        model.fit_view(&cam, &target, valid, bg, weight, &mut grads);
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
