//! A cheap estimate of the held-out error while training goes on: a fixed
//! random sample of pixels from the held-out views (test split, else
//! validation), rendered and scored together. Rendering whole views would
//! cost seconds to minutes per check with the classic model; a few thousand
//! pixels cost a fraction of a training step's rays many times over less,
//! and their mean squared error is an unbiased estimate of the views'.
//!
//! Each view's pixels render with the appearance its whole view is scored
//! with (`view::appearance::held_out_options`: the nearest training
//! camera's, for a model with per-image appearance), so the chart agrees
//! with `eval` and the training job's final number.

use std::ops::Range;

use rayon::prelude::*;

use crate::engine::dataset::{Dataset, Split};
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Ray;
use crate::engine::metrics::mse_to_psnr;
use crate::engine::models::Model;
use crate::engine::rng::Rng;
use crate::engine::view::appearance::held_out_options;
use crate::engine::view::render_rays_with;

/// A fixed sample of held-out pixels: their rays and true colours, grouped
/// by view.
pub struct HeldOutPixels {
    rays: Vec<Ray>,
    target: Vec<[f32; 3]>,
    /// Each view with pixels in the sample, and the range of its pixels.
    views: Vec<(Camera, Range<usize>)>,
    background: [f32; 3],
    /// The split the pixels come from.
    pub split: Split,
}

impl HeldOutPixels {
    /// Up to `n` pixels drawn uniformly (with `seed`) from every held-out
    /// view; `None` when the dataset has no test or validation views.
    pub fn new(ds: &Dataset, n: usize, seed: u64) -> Option<Self> {
        let split = [Split::Test, Split::Val].into_iter().find(|&s| !ds.split(s).is_empty())?;
        let frames: Vec<_> = ds.split_frames(split).collect();
        let mut rng = Rng::stream(seed, 0x6865_6c64, 0);
        let mut drawn: Vec<(usize, u32, u32)> = (0..n)
            .map(|_| {
                let k = rng.below(frames.len() as u64) as usize;
                let (w, h) = (frames[k].camera.width, frames[k].camera.height);
                (k, rng.below(w as u64) as u32, rng.below(h as u64) as u32)
            })
            .collect();
        drawn.sort_by_key(|d| d.0);
        let (mut rays, mut target, mut views) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::new());
        for (p, &(k, i, j)) in drawn.iter().enumerate() {
            let f = frames[k];
            if p == 0 || drawn[p - 1].0 != k {
                views.push((f.camera.clone(), p..p));
            }
            if let Some(v) = views.last_mut() {
                v.1.end = p + 1;
            }
            rays.push(f.camera.pixel_ray(i, j));
            target.push(f.image.rgb_on(i, j, ds.background));
        }
        Some(Self { rays, target, views, background: ds.background, split })
    }

    /// Mean squared error of `model` on the pixels (in f64). The views
    /// render in parallel (each holds a few hundred pixels, one tile), and
    /// their sums add up in view order, so the estimate does not depend on
    /// the threads.
    pub fn mse(&self, model: &dyn Model) -> f64 {
        let per_view: Vec<f64> = self
            .views
            .par_iter()
            .map(|(camera, range)| {
                let options = held_out_options(model, camera);
                let (out, _) = render_rays_with(model, &self.rays[range.clone()], self.background, &options);
                out.iter()
                    .zip(&self.target[range.clone()])
                    .flat_map(|(o, t)| (0..3).map(move |c| (o.rgb[c] as f64 - t[c] as f64).powi(2)))
                    .sum::<f64>()
            })
            .collect();
        per_view.iter().sum::<f64>() / (3 * self.rays.len().max(1)) as f64
    }

    /// PSNR of `model` on the pixels.
    pub fn psnr(&self, model: &dyn Model) -> f64 {
        mse_to_psnr(self.mse(model))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    use crate::engine::models::config::ModelConfig;
    use crate::engine::view::render_view_with;

    /// With every pixel of the held-out views sampled many times, the
    /// estimate agrees with the exact per-view mean squared error, each
    /// view rendered with the appearance it is scored with (for the capture
    /// model, with embeddings moved apart, the nearest training camera's).
    #[test]
    fn estimate_matches_the_full_views() {
        let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
        for preset in ["instant-tiny", "capture-tiny"] {
            let mut model = ModelConfig::preset(preset).unwrap().build(ds.scene(), 3).unwrap();
            if model.appearance().map(|a| a.images()).is_some() {
                let mut seen = vec![0.0; 2000];
                ds.train.iter().for_each(|&i| seen[i] = 1.0);
                model.restore_state(&mut |_| Some(seen.clone()), 1).unwrap();
                let mut rng = Rng::new(5);
                model.params_mut().iter_mut().for_each(|p| *p += 0.3 * rng.normal());
            }
            let mut exact = 0.0;
            let mut n = 0usize;
            for f in ds.split_frames(Split::Test) {
                let v = render_view_with(&*model, &f.camera, ds.background, &held_out_options(&*model, &f.camera));
                for j in 0..f.camera.height {
                    for i in 0..f.camera.width {
                        let t = f.image.rgb_on(i, j, ds.background);
                        let k = 3 * (j * f.camera.width + i) as usize;
                        exact += (0..3).map(|c| (v.rgb[k + c] as f64 - t[c] as f64).powi(2)).sum::<f64>();
                        n += 3;
                    }
                }
            }
            exact /= n as f64;
            let h = HeldOutPixels::new(&ds, 20_000, 1).unwrap();
            assert_eq!(h.split, Split::Test);
            let est = h.mse(&*model);
            assert!(exact > 1e-3, "{preset}: the untrained model should be visibly wrong: {exact}");
            assert!((est - exact).abs() < 0.05 * exact, "{preset}: estimate {est} vs exact {exact}");
            assert!((h.psnr(&*model) - mse_to_psnr(exact)).abs() < 0.25);
        }
    }

    #[test]
    fn no_held_out_views_gives_none() {
        let mut ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
        ds.test.clear();
        ds.val.clear();
        assert!(HeldOutPixels::new(&ds, 100, 0).is_none());
    }
}
