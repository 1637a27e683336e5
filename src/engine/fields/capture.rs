//! The field of the real-capture model (design `real-captures.md` 2.2 and
//! 2.6): the fast model's networks (`nets`: a hash grid, a density MLP whose
//! first output is log-density and the rest geometry features, a colour MLP
//! on those and the spherical-harmonics code of the direction), but
//! - over all of space: positions go through a [`SpaceMap`] (a scene
//!   contraction, or NDC) into the grid's unit cube instead of a box map, so
//!   the grid's finest level must be finer (most of the cube is spent on the
//!   background);
//! - starting nearly transparent: `σ = init_density · exp(clamp(raw))`
//!   (nerfacto's `average_init_density`: fewer early floaters);
//! - with a per-image appearance embedding folded into the first colour
//!   layer's bias ([`Appearance`]): the image of each sample comes from
//!   [`Points::image`]; samples without one (new views) use the appearance
//!   set with [`CaptureField::set_view_appearance`].
//!
//! With an NDC map, points outside the frustum (`u` outside the open unit
//! cube) get no density (nerfacto's selector). Its last colour layer is the
//! dot-product one (`ColorHead::Dots`); for rendering, the grid can be
//! read from a half-precision table, and for training its gradient can be
//! deferred ([`CaptureField::begin_deferring`]).

use super::nets::{self, ColorHead, Nets};
use super::space::SpaceMap;
use super::{Field, Points};
use crate::engine::nn::appearance::{Appearance, AppearanceBatch};
use crate::engine::nn::hashgrid::{GridRecord, HalfTable, HashGrid, HashGridConfig};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::rng::Rng;

/// Maps model-space points `pos` (`[n x 3]`) into the grid's unit cube
/// (`unit`, `[n x 3]`). For NDC, `mask` gets 1 for points inside the open
/// cube and 0 for the others (which get no density); a contraction keeps
/// every finite point inside, and `mask` is left empty.
pub(super) fn to_grid(space: &SpaceMap, pos: &[f32], unit: &mut Vec<f32>, mask: &mut Vec<f32>) {
    unit.clear();
    mask.clear();
    for p in pos.chunks_exact(3) {
        unit.extend_from_slice(&space.map([p[0], p[1], p[2]]));
    }
    if matches!(space, SpaceMap::Ndc(_)) {
        mask.extend(unit.chunks_exact(3).map(|u| f32::from(u.iter().all(|&v| v > 0.0 && v < 1.0))));
    }
}

/// Sizes of a [`CaptureField`].
#[derive(Clone, Debug, PartialEq)]
pub struct CaptureFieldConfig {
    pub grid: HashGridConfig,
    /// Hidden width of both MLPs.
    pub hidden: usize,
    /// Outputs of the density MLP: log-density and geometry features.
    pub geo_features: usize,
    /// Density of the untrained field (the scale of the activation).
    pub init_density: f32,
    /// Images with an appearance embedding, and its size (0: none).
    pub max_images: usize,
    pub appearance_dim: usize,
}

/// The capture field over a flat parameter buffer.
pub struct CaptureField {
    space: SpaceMap,
    nets: Nets,
    appearance: Appearance,
}

/// Activations of a forward pass over `n` samples, and the appearance of
/// samples without an image; one per thread, reused across passes.
#[derive(Default)]
pub struct Ctx {
    /// The networks' activations, with the samples' grid coordinates and
    /// NDC mask.
    nets: nets::Ctx,
    /// The per-image biases of the samples of the last density pass (no
    /// samples when it had no images).
    app: AppearanceBatch,
    /// The colour layer's bias for samples without an image (`[hidden]`;
    /// empty: none).
    view_bias: Vec<f32>,
}

impl CaptureField {
    /// Lays out the field's parameters: the hash grid, `density.0-1`,
    /// `color.0-2` and the appearance (`appearance.embedding`,
    /// `appearance.proj`).
    pub fn new(layout: &mut ParamLayout, space: SpaceMap, c: &CaptureFieldConfig) -> Self {
        let (h, g) = (c.hidden, c.geo_features);
        let nets = Nets::new(layout, c.grid.clone(), h, g, ColorHead::Dots, c.init_density);
        let fan_in = g + crate::engine::nn::sh::WIDTH + c.appearance_dim;
        let appearance = Appearance::new(layout, "appearance", c.max_images, c.appearance_dim, h, fan_in);
        Self { space, nets, appearance }
    }

    /// Initialises the field's ranges of `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.nets.init(params, rng);
        self.appearance.init(params, rng);
    }

    /// The per-image appearance embeddings.
    pub fn appearance(&self) -> &Appearance {
        &self.appearance
    }

    /// The map from model space into the grid's cube.
    pub fn space(&self) -> &SpaceMap {
        &self.space
    }

    /// Sets the appearance of samples without an image (new views, and
    /// every colour from [`Field::color_rows`]): the embedding `e`
    /// (`[appearance_dim]`), or none (a zero embedding, as an untrained
    /// image has).
    pub fn set_view_appearance(&self, params: &[f32], e: Option<&[f32]>, ctx: &mut Ctx) {
        ctx.view_bias.clear();
        if let Some(e) = e.filter(|e| self.appearance.enabled() && e.len() == self.appearance.dim) {
            ctx.view_bias.resize(self.nets.c1.outputs, 0.0);
            self.appearance.bias_of(params, e, &mut ctx.view_bias);
        }
    }

    /// The main grid's table of `params` in half precision, for rendering
    /// ([`HashGrid::half_table`]; `None` where the CPU cannot use one).
    pub fn half_table(&self, params: &[f32]) -> Option<HalfTable> {
        self.nets.half_table(params)
    }

    /// Makes the density passes of `ctx` read the grid from `table` (a
    /// [`Self::half_table`] of the parameters they are given) instead of
    /// the parameters, or from the parameters again (`None`). For rendering
    /// only: the backward pass needs the f32 table's encoding.
    pub fn set_render_table(&self, table: Option<std::sync::Arc<HalfTable>>, ctx: &mut Ctx) {
        self.nets.set_render_table(table, &mut ctx.nets);
    }

    /// Adds each sample's appearance to the first colour layer's
    /// pre-activations `a1` (`[n x hidden]`): its image's when the last
    /// density pass had images (`app`), else the view appearance (`view`,
    /// when set).
    fn add_appearance(&self, app: &AppearanceBatch, view: &[f32], a1: &mut [f32]) {
        let h = self.nets.c1.outputs;
        if app.len() * h == a1.len() {
            self.appearance.add_bias(app, a1);
        } else if view.len() == h {
            for row in a1.chunks_exact_mut(h) {
                for (a, &b) in row.iter_mut().zip(view) {
                    *a += b;
                }
            }
        }
    }
}

impl Field for CaptureField {
    type Ctx = Ctx;

    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut Ctx) {
        let c = &mut ctx.nets;
        c.n = pts.pos.len() / 3;
        to_grid(&self.space, pts.pos, &mut c.unit, &mut c.mask);
        if pts.image.len() == c.n && c.n > 0 {
            self.appearance.gather(params, pts.image, &mut ctx.app);
        } else {
            ctx.app.clear_samples();
        }
        self.nets.forward_density(params, c);
    }

    fn compact(&self, ctx: &mut Ctx, keep: &[usize]) {
        if ctx.app.len() == ctx.nets.n {
            ctx.app.compact(keep);
        }
        self.nets.compact(&mut ctx.nets, keep);
    }

    fn color(&self, params: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        let (app, view) = (&ctx.app, &ctx.view_bias);
        self.nets.forward_color(params, dirs, &mut ctx.nets, |a1| self.add_appearance(app, view, a1));
    }

    fn sigma<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        self.nets.sigma(&ctx.nets)
    }

    fn rgb<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        self.nets.rgb(&ctx.nets)
    }

    fn save_row(&self, ctx: &Ctx, i: usize, rows: &mut Vec<f32>) {
        self.nets.save_row(&ctx.nets, i, rows);
    }

    /// Colours rows saved by [`Field::save_row`] with the view appearance
    /// ([`CaptureField::set_view_appearance`]): rows carry no image.
    fn color_rows(&self, params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut Ctx) {
        ctx.app.clear_samples();
        let (app, view) = (&ctx.app, &ctx.view_bias);
        self.nets.color_rows(params, rows, dirs, &mut ctx.nets, |a1| self.add_appearance(app, view, a1));
    }

    /// The gradient of the parameters, including the embeddings of the
    /// images of the last density pass. A pass without images (the view
    /// appearance) gives the appearance parameters no gradient.
    fn backward(&self, p: &[f32], ctx: &mut Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        self.nets.backward(p, &mut ctx.nets, dsigma, drgb, grads, None);
        self.appearance_backward(p, ctx, grads);
    }
}

impl CaptureField {
    /// [`Field::backward`] (the same parameter gradients, bit for bit), and
    /// also the gradients with respect to the inputs of the last density
    /// pass (after any [`Field::compact`]) and colour pass, for camera pose
    /// refinement: read them with [`CaptureField::input_grads`]. `pos` and
    /// `dirs` (`[n x 3]` each, model space) are what those passes were
    /// given.
    ///
    /// The positions' gradient flows through both outputs (the density and
    /// the colour's geometry features both come from the hash grid,
    /// [`HashGrid::backward_with_input_grad`]), then through the space map
    /// ([`SpaceMap::vjp`]). The directions' gradient comes from the colour
    /// network's spherical-harmonics input
    /// ([`sh::encode_backward`](crate::engine::nn::sh::encode_backward)).
    #[allow(clippy::too_many_arguments)]
    pub fn backward_with_input_grads(
        &self,
        params: &[f32],
        ctx: &mut Ctx,
        pos: &[f32],
        dirs: &[f32],
        dsigma: &[f32],
        drgb: &[f32],
        grads: &mut [f32],
    ) {
        self.nets.backward(params, &mut ctx.nets, dsigma, drgb, grads, Some(dirs));
        self.appearance_backward(params, ctx, grads);
        let vjp = |i: usize, du| self.space.vjp([pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]], du);
        self.nets.position_grads(&mut ctx.nets, vjp);
    }

    /// From now on [`Field::backward`] with `ctx` records the hash grid's
    /// part (its points and output gradients) instead of adding it to the
    /// gradient, into `record`'s buffers (cleared, and lent to `ctx`:
    /// `record` is left empty meanwhile), until
    /// [`CaptureField::end_deferring`]. Passes with input gradients (pose
    /// refinement) still scatter at once.
    pub fn begin_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        self.nets.begin_deferring(&mut ctx.nets, record);
    }

    /// Ends [`CaptureField::begin_deferring`]: `record` gets back its
    /// buffers with what was recorded, for [`HashGrid::scatter`]
    /// (and `ctx` what `record` held: pass an empty one).
    pub fn end_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        self.nets.end_deferring(&mut ctx.nets, record);
    }

    /// The hash grid (its table's gradient is what
    /// [`CaptureField::begin_deferring`] defers).
    pub fn grid(&self) -> &HashGrid {
        &self.nets.grid
    }

    /// dL/d(position) (model space) and dL/d(direction), `[n x 3]` each, of
    /// the last [`CaptureField::backward_with_input_grads`].
    pub fn input_grads<'c>(&self, ctx: &'c Ctx) -> (&'c [f32], &'c [f32]) {
        self.nets.input_grads(&ctx.nets)
    }

    /// The appearance's part of a backward pass, after the networks': the
    /// gradient of the embeddings of the last density pass's images (and of
    /// their projection) from that of the first colour layer's
    /// pre-activations. The two fill disjoint ranges of `grads`, so their
    /// order moves no bit.
    fn appearance_backward(&self, p: &[f32], ctx: &mut Ctx, grads: &mut [f32]) {
        let n = ctx.nets.n;
        if n > 0 && ctx.app.len() == n {
            self.appearance.backward(p, &mut ctx.app, self.nets.d_color_pre(&ctx.nets), grads);
        }
    }
}

#[cfg(test)]
#[path = "capture_tests.rs"]
mod tests;
