//! 3D Gaussian splats: a model that is a few hundred thousand anisotropic
//! Gaussians with opacities and view-dependent colours (`gaussians`),
//! drawn by a tile rasteriser (`raster`, with its derivative in
//! `backward`). It is made from a trained radiance field by `bake`,
//! renders views by rasterising them whole (`Model::rasteriser`), and is
//! written in the formats splat viewers read by `export`.

pub mod backward;
pub mod cleanup;
pub mod config;
pub mod crop;
pub mod dssim;
pub mod export;
pub mod fit;
pub mod frame;
pub mod gaussians;
pub mod lens;
pub mod looks;
pub mod raster;
pub mod tile;

pub use config::SplatsConfig;

use std::sync::OnceLock;

use super::{Appearance, Model, ModelError, RenderOptions, StateSource};
use crate::engine::batch::{BatchStats, RayOutput, StepCtx, TrainRay};
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::render::composite::mark_median;
use gaussians::{Layout, covariance, sh_colour, sigmoid};
use looks::{ColourCorrection, Looks};
use raster::{MAX_ALPHA, RasterCamera, RasterOptions};

/// The kind's name in checkpoints, the API and `--model`.
pub const KIND: &str = "splats";

/// The splats model.
pub struct SplatsModel {
    pub config: SplatsConfig,
    scene: Scene,
    params: Vec<f32>,
    layout: Layout,
    /// Each Gaussian's inverse 3D covariance (`xx xy xz yy yz zz`), for
    /// [`Model::render_rays`].
    inverse: OnceLock<Vec<[f32; 6]>>,
    /// What every view's projection derives from the parameters alone.
    intrinsics: OnceLock<raster::Intrinsics>,
    /// The training photos' colour corrections a bake fitted (`looks`);
    /// `None` for splats with one look only.
    looks: Option<Looks>,
}

impl SplatsModel {
    /// A model of the Gaussians in `params` (laid out as
    /// [`gaussians::Layout`] says at the configured degree).
    pub fn from_parts(config: SplatsConfig, scene: Scene, params: Vec<f32>) -> Result<Self, ModelError> {
        let Some(layout) = Layout::of_len(params.len(), config.sh_degree) else {
            let stride = Layout::stride(gaussians::sh_coeffs(config.sh_degree));
            return Err(ModelError::Config {
                kind: KIND,
                message: format!(
                    "{} parameters are not a whole number of Gaussians of {stride} values (SH degree {})",
                    params.len(),
                    config.sh_degree
                ),
            });
        };
        Ok(Self { config, scene, params, layout, inverse: OnceLock::new(), intrinsics: OnceLock::new(), looks: None })
    }

    /// The training photos' colour corrections (`None`: one look only).
    pub fn looks(&self) -> Option<&Looks> {
        self.looks.as_ref()
    }

    pub fn set_looks(&mut self, looks: Option<Looks>) {
        self.looks = looks;
    }

    /// The looks and the correction a view under `options` takes: its
    /// image's, if the splats have one for it (`None`: their own look).
    fn look(&self, options: &RenderOptions) -> Option<(&Looks, &ColourCorrection)> {
        let looks = self.looks.as_ref()?;
        Some((looks, looks.of(options.image?)?))
    }

    pub fn layout(&self) -> Layout {
        self.layout
    }

    /// The splats of the Gaussians `keep` (in that order) alone: what the
    /// export's cleanup and crop leave.
    pub fn keeping(&self, keep: &[usize]) -> Result<Self, ModelError> {
        let mut kept =
            Self::from_parts(self.config.clone(), self.scene.clone(), self.layout.select(&self.params, keep))?;
        kept.looks = self.looks.clone();
        Ok(kept)
    }

    /// Renders `camera` (world units).
    pub fn rasterise(&self, camera: &Camera, background: [f32; 3]) -> raster::Frame {
        let cam = RasterCamera::new(camera, &self.scene);
        let pre = self.intrinsics.get_or_init(|| raster::Intrinsics::of(&self.layout, &self.params));
        raster::forward_with(
            &self.layout,
            &self.params,
            Some(pre),
            &cam,
            &RasterOptions::for_scene(&self.scene),
            background,
        )
    }

    /// Renders `camera`'s colours, distances and opacities; a distorted
    /// camera through a pinhole camera around it, resampled
    /// ([`lens`]). The colours take the correction of the training photo
    /// `options` names, if the splats have one (their own look else).
    pub fn render_view(
        &self,
        camera: &Camera,
        background: [f32; 3],
        options: &RenderOptions,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (mut rgb, depth, opacity) = if camera.distortion.is_identity() {
            let f = self.rasterise(camera, background);
            (f.rgb, f.depth, f.opacity)
        } else {
            let pin = lens::pinhole_around(camera);
            let f = self.rasterise(&pin, background);
            let at = lens::Resampling::new(camera, &pin);
            (at.apply(&f.rgb, 3, &background), at.apply(&f.depth, 1, &[0.0]), at.apply(&f.opacity, 1, &[0.0]))
        };
        if let Some((looks, correction)) = self.look(options) {
            looks.correct(correction, &mut rgb, &opacity, background);
        }
        (rgb, depth, opacity)
    }
}

/// What a model that draws whole views itself offers
/// ([`Model::rasteriser`]).
pub trait Rasteriser {
    /// Renders `camera` (world units) with `options`: colours `[h x w x
    /// 3]` on `background`, distances from the camera (model units) and
    /// opacities.
    fn render_view(
        &self,
        camera: &Camera,
        background: [f32; 3],
        options: &RenderOptions,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>);
}

impl Rasteriser for SplatsModel {
    fn render_view(
        &self,
        camera: &Camera,
        background: [f32; 3],
        options: &RenderOptions,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        SplatsModel::render_view(self, camera, background, options)
    }
}

/// Splats with looks offer them as a per-image appearance: a view takes a
/// training photo's colour correction as a capture model's view takes its
/// embedding. The corrections are not parameters (they are not trained by
/// gradient), so there is no row.
impl Appearance for SplatsModel {
    fn images(&self) -> Vec<u32> {
        self.looks.as_ref().map(|l| l.images.clone()).unwrap_or_default()
    }

    fn row(&self, _image: u32) -> Option<std::ops::Range<usize>> {
        None
    }

    fn embedding(&self, options: &RenderOptions) -> Option<Vec<f32>> {
        // A photo the splats have no look for has no embedding.
        let correction = if options.image.is_some() { self.look(options)?.1 } else { &ColourCorrection::IDENTITY };
        Some(correction.0.iter().flatten().copied().collect())
    }
}

impl Model for SplatsModel {
    super::model_accessors!(params_mut: inverse, intrinsics);

    /// Never called: the trainer refuses a kind that does not train on
    /// rays (`ModelSpec::trains_on_rays`); splats are optimised on whole
    /// images by `bake`. Adds nothing.
    fn train_rays(&self, _rays: &[TrainRay], _ctx: &StepCtx, _grads: &mut [f32]) -> BatchStats {
        BatchStats::default()
    }

    fn rasteriser(&self) -> Option<&dyn Rasteriser> {
        Some(self)
    }

    fn appearance(&self) -> Option<&dyn Appearance> {
        self.looks.is_some().then_some(self as &dyn Appearance)
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        self.looks.as_ref().map(Looks::tensors).unwrap_or_default()
    }

    /// Takes back the looks, if the checkpoint has them (splats baked
    /// before looks were fitted have none).
    fn restore_state(&mut self, state: StateSource<'_>, _step: u64) -> Result<(), ModelError> {
        self.looks = match (state(looks::IMAGES), state(looks::CORRECTIONS), state(looks::BACKGROUND)) {
            (None, None, None) => None,
            (Some(images), Some(values), Some(background)) => Some(
                Looks::from_tensors(&images, &values, &background)
                    .map_err(|message| ModelError::Config { kind: KIND, message })?,
            ),
            _ => {
                let names = [looks::IMAGES, looks::CORRECTIONS, looks::BACKGROUND].join(", ");
                return Err(ModelError::MissingState(names));
            }
        };
        Ok(())
    }

    /// Each ray on its own, through every Gaussian it passes near, at the
    /// point of the ray where the Gaussian is densest (slow: views are
    /// rasterised whole instead, `Model::rasteriser`; this serves callers
    /// that have rays, not a camera).
    fn render_rays(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        options: &RenderOptions,
        out: &mut [RayOutput],
    ) -> BatchStats {
        let look = self.look(options);
        let inverse = self.inverse.get_or_init(|| inverse_covariances(&self.layout, &self.params));
        let mut basis = [0.0f32; crate::engine::nn::sh::WIDTH];
        let mut hits: Vec<(f32, f32, usize)> = Vec::new();
        for (ray, o) in rays.iter().zip(out.iter_mut()) {
            hits.clear();
            let (ro, rd) = (ray.origin.to_array(), ray.dir.to_array());
            for (i, inv) in inverse.iter().enumerate() {
                let g = self.layout.get(&self.params, i);
                let d = [g.mean[0] - ro[0], g.mean[1] - ro[1], g.mean[2] - ro[2]];
                let sd = sym_mul(inv, rd);
                let dsd = rd[0] * sd[0] + rd[1] * sd[1] + rd[2] * sd[2];
                if dsd.is_nan() || dsd <= 0.0 {
                    continue;
                }
                let along = d[0] * sd[0] + d[1] * sd[1] + d[2] * sd[2];
                let t = along / dsd;
                let sdd = sym_mul(inv, d);
                let q = d[0] * sdd[0] + d[1] * sdd[1] + d[2] * sdd[2] - t * along;
                let a = (sigmoid(g.opacity_logit) * (-0.5 * q).exp()).min(MAX_ALPHA);
                if t > self.scene.near && a >= 1.0 / 255.0 {
                    hits.push((t, a, i));
                }
            }
            hits.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.2.cmp(&b.2)));
            let mut tr = 1.0f32;
            *o = RayOutput::default();
            for &(t, a, i) in &hits {
                let g = self.layout.get(&self.params, i);
                let c = sh_colour(&g, self.layout.k, rd, &mut basis);
                for k in 0..3 {
                    o.rgb[k] += a * tr * c[k].max(0.0);
                }
                o.depth += a * tr * t;
                tr *= 1.0 - a;
                mark_median(&mut o.median, tr, t);
                if tr < 1e-4 {
                    break;
                }
            }
            for k in 0..3 {
                o.rgb[k] += tr * background[k];
            }
            o.opacity = 1.0 - tr;
            if let Some((looks, correction)) = look {
                looks.correct(correction, &mut o.rgb, &[o.opacity], background);
            }
        }
        BatchStats { rays: rays.len() as u64, ..Default::default() }
    }
}

/// `S v` for the symmetric `S` (`xx xy xz yy yz zz`).
fn sym_mul(s: &[f32; 6], v: [f32; 3]) -> [f32; 3] {
    [
        s[0] * v[0] + s[1] * v[1] + s[2] * v[2],
        s[1] * v[0] + s[3] * v[1] + s[4] * v[2],
        s[2] * v[0] + s[4] * v[1] + s[5] * v[2],
    ]
}

/// Each Gaussian's inverse covariance: `R S⁻² Rᵀ`.
fn inverse_covariances(layout: &Layout, params: &[f32]) -> Vec<[f32; 6]> {
    (0..layout.n)
        .map(|i| {
            let g = layout.get(params, i);
            let neg = g.log_scale.map(|s| -s);
            covariance(neg, g.rotation).0
        })
        .collect()
}

#[cfg(test)]
mod raster_tests;
