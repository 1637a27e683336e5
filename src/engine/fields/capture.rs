//! The field of the real-capture model (design `real-captures.md` 2.2 and
//! 2.6): the fast model's networks (a hash grid, a density MLP whose first
//! output is log-density and the rest geometry features, a colour MLP on
//! those and the spherical-harmonics code of the direction), but
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
//! cube) get no density (nerfacto's selector).

use super::size;
use super::space::SpaceMap;
use super::{Field, Points};
use crate::engine::nn::appearance::{Appearance, AppearanceBatch};
use crate::engine::nn::hashgrid::{GridRecord, HalfTable, HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward, sigmoid};
use crate::engine::nn::move_rows;
use crate::engine::nn::sh;
use crate::engine::rng::Rng;

/// Density activation of the capture and proposal fields:
/// `init · exp(clamp(raw, -15, 15))`. Its derivative is taken as the
/// density itself (straight through the clamp, as the fast model's), which
/// stays finite.
#[inline]
pub(super) fn density_activation(init: f32, raw: f32) -> f32 {
    init * raw.clamp(-15.0, 15.0).exp()
}

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
    grid: HashGrid,
    d1: Linear,
    d2: Linear,
    c1: Linear,
    c2: Linear,
    c3: Linear,
    appearance: Appearance,
    init_density: f32,
}

/// Activations of a forward pass over `n` samples, and the appearance of
/// samples without an image; one per thread, reused across passes.
#[derive(Default)]
pub struct Ctx {
    n: usize,
    unit: Vec<f32>,
    mask: Vec<f32>,
    enc: Vec<f32>,
    h1: Vec<f32>,
    geo: Vec<f32>,
    sigma: Vec<f32>,
    shd: Vec<f32>,
    a1: Vec<f32>,
    a2: Vec<f32>,
    rgb: Vec<f32>,
    /// The per-image biases of the samples of the last density pass (no
    /// samples when it had no images).
    app: AppearanceBatch,
    /// The colour layer's bias for samples without an image (`[hidden]`;
    /// empty: none).
    view_bias: Vec<f32>,
    /// The grid's table in half precision, read instead of the parameters'
    /// while rendering ([`CaptureField::set_render_table`]); never set for
    /// a pass that is differentiated.
    half: Option<std::sync::Arc<HalfTable>>,
    // backward scratch
    draw: Vec<f32>,
    d_a: Vec<f32>,
    d_b: Vec<f32>,
    d_geo: Vec<f32>,
    d_enc: Vec<f32>,
    /// Whether [`Field::backward`] records the grid's backward pass into
    /// `record` instead of scattering it ([`CaptureField::begin_deferring`]).
    defer: bool,
    record: GridRecord,
    // input gradients (`CaptureField::backward_with_input_grads` only)
    d_shd: Vec<f32>,
    d_unit: Vec<f32>,
    d_pos: Vec<f32>,
    d_dirs: Vec<f32>,
}

impl CaptureField {
    /// Lays out the field's parameters: the hash grid, `density.0-1`,
    /// `color.0-2` and the appearance (`appearance.embedding`,
    /// `appearance.proj`).
    pub fn new(layout: &mut ParamLayout, space: SpaceMap, c: &CaptureFieldConfig) -> Self {
        let grid = HashGrid::new(layout, c.grid.clone());
        let (h, g) = (c.hidden, c.geo_features);
        let d1 = Linear::new(layout, "density.0", grid.width(), h);
        let d2 = Linear::new(layout, "density.1", h, g);
        let c1 = Linear::new(layout, "color.0", g + sh::WIDTH, h);
        let c2 = Linear::new(layout, "color.1", h, h);
        let c3 = Linear::new(layout, "color.2", h, 3);
        let fan_in = g + sh::WIDTH + c.appearance_dim;
        let appearance = Appearance::new(layout, "appearance", c.max_images, c.appearance_dim, h, fan_in);
        Self { space, grid, d1, d2, c1, c2, c3, appearance, init_density: c.init_density }
    }

    /// Initialises the field's ranges of `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.grid.init(params, rng);
        for l in [&self.d1, &self.d2, &self.c1, &self.c2, &self.c3] {
            l.init(params, rng);
        }
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
            ctx.view_bias.resize(self.c1.outputs, 0.0);
            self.appearance.bias_of(params, e, &mut ctx.view_bias);
        }
    }

    /// The main grid's table of `params` in half precision, for rendering
    /// ([`HashGrid::half_table`]; `None` where the CPU cannot use one).
    pub fn half_table(&self, params: &[f32]) -> Option<HalfTable> {
        self.grid.half_table(params)
    }

    /// Makes the density passes of `ctx` read the grid from `table` (a
    /// [`Self::half_table`] of the parameters they are given) instead of
    /// the parameters, or from the parameters again (`None`). For rendering
    /// only: the backward pass needs the f32 table's encoding.
    pub fn set_render_table(&self, table: Option<std::sync::Arc<HalfTable>>, ctx: &mut Ctx) {
        ctx.half = table;
    }

    /// Densities (and geometry features) of the first `ctx.n` unit-cube
    /// points in `ctx.unit`.
    fn forward_density(&self, p: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (gw, h, g) = (self.grid.width(), self.d1.outputs, self.d2.outputs);
        size(&mut ctx.enc, n * gw);
        size(&mut ctx.h1, n * h);
        size(&mut ctx.geo, n * g);
        size(&mut ctx.sigma, n);
        if n == 0 {
            return;
        }
        match &ctx.half {
            Some(table) => self.grid.forward_half(table, &ctx.unit[..n * 3], &mut ctx.enc),
            None => self.grid.forward(p, &ctx.unit[..n * 3], &mut ctx.enc),
        }
        self.d1.forward(p, &[(&ctx.enc, gw)], n, &mut ctx.h1);
        relu(&mut ctx.h1[..n * h]);
        self.d2.forward(p, &[(&ctx.h1, h)], n, &mut ctx.geo);
        for (i, (s, row)) in ctx.sigma[..n].iter_mut().zip(ctx.geo.chunks_exact(g)).enumerate() {
            *s = density_activation(self.init_density, row[0]) * ctx.mask.get(i).copied().unwrap_or(1.0);
        }
    }

    /// Colours of the first `n` samples of the last density pass (or of
    /// the rows `ctx.geo` holds), seen along `dirs` (`[n x 3]`).
    fn forward_color(&self, p: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (h, g) = (self.c1.outputs, self.d2.outputs);
        size(&mut ctx.shd, n * sh::WIDTH);
        size(&mut ctx.a1, n * h);
        size(&mut ctx.a2, n * h);
        size(&mut ctx.rgb, n * 3);
        if n == 0 {
            return;
        }
        sh::encode(&dirs[..n * 3], &mut ctx.shd);
        self.c1.forward(p, &[(&ctx.geo, g), (&ctx.shd, sh::WIDTH)], n, &mut ctx.a1);
        if ctx.app.len() == n {
            self.appearance.add_bias(&ctx.app, &mut ctx.a1[..n * h]);
        } else if ctx.view_bias.len() == h {
            for row in ctx.a1[..n * h].chunks_exact_mut(h) {
                for (a, &b) in row.iter_mut().zip(&ctx.view_bias) {
                    *a += b;
                }
            }
        }
        relu(&mut ctx.a1[..n * h]);
        self.c2.forward(p, &[(&ctx.a1, h)], n, &mut ctx.a2);
        relu(&mut ctx.a2[..n * h]);
        // Three outputs: dot products (see `Linear::forward_dots`).
        self.c3.forward_dots(p, &ctx.a2, n, &mut ctx.rgb);
        for v in &mut ctx.rgb[..n * 3] {
            *v = sigmoid(*v);
        }
    }
}

impl Field for CaptureField {
    type Ctx = Ctx;

    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut Ctx) {
        ctx.n = pts.pos.len() / 3;
        to_grid(&self.space, pts.pos, &mut ctx.unit, &mut ctx.mask);
        if pts.image.len() == ctx.n && ctx.n > 0 {
            self.appearance.gather(params, pts.image, &mut ctx.app);
        } else {
            ctx.app.clear_samples();
        }
        self.forward_density(params, ctx);
    }

    fn compact(&self, ctx: &mut Ctx, keep: &[usize]) {
        move_rows(&mut ctx.unit, 3, keep);
        if !ctx.mask.is_empty() {
            move_rows(&mut ctx.mask, 1, keep);
            ctx.mask.truncate(keep.len());
        }
        move_rows(&mut ctx.enc, self.grid.width(), keep);
        move_rows(&mut ctx.h1, self.d1.outputs, keep);
        move_rows(&mut ctx.geo, self.d2.outputs, keep);
        move_rows(&mut ctx.sigma, 1, keep);
        if ctx.app.len() == ctx.n {
            ctx.app.compact(keep);
        }
        ctx.n = keep.len();
    }

    fn color(&self, params: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        self.forward_color(params, dirs, ctx);
    }

    fn sigma<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    fn rgb<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.rgb[..3 * ctx.n]
    }

    fn save_row(&self, ctx: &Ctx, i: usize, rows: &mut Vec<f32>) {
        let g = self.d2.outputs;
        rows.extend_from_slice(&ctx.geo[i * g..(i + 1) * g]);
    }

    /// Colours rows saved by [`Field::save_row`] with the view appearance
    /// ([`CaptureField::set_view_appearance`]): rows carry no image.
    fn color_rows(&self, params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut Ctx) {
        ctx.n = dirs.len() / 3;
        ctx.geo = rows;
        ctx.app.clear_samples();
        self.forward_color(params, dirs, ctx);
    }

    /// The gradient of the parameters, including the embeddings of the
    /// images of the last density pass. A pass without images (the view
    /// appearance) gives the appearance parameters no gradient.
    fn backward(&self, p: &[f32], ctx: &mut Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        self.backward_inner(p, ctx, dsigma, drgb, grads, None);
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
    /// network's spherical-harmonics input ([`sh::encode_backward`]).
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
        self.backward_inner(params, ctx, dsigma, drgb, grads, Some(dirs));
        let n = ctx.n;
        size(&mut ctx.d_pos, n * 3);
        if n == 0 {
            return;
        }
        for ((x, du), dx) in
            pos[..3 * n].chunks_exact(3).zip(ctx.d_unit.chunks_exact(3)).zip(ctx.d_pos.chunks_exact_mut(3))
        {
            dx.copy_from_slice(&self.space.vjp([x[0], x[1], x[2]], [du[0], du[1], du[2]]));
        }
    }

    /// From now on [`Field::backward`] with `ctx` records the hash grid's
    /// part (its points and output gradients) instead of adding it to the
    /// gradient, into `record`'s buffers (cleared, and lent to `ctx`:
    /// `record` is left empty meanwhile), until
    /// [`CaptureField::end_deferring`]. Passes with input gradients (pose
    /// refinement) still scatter at once.
    pub fn begin_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        std::mem::swap(&mut ctx.record, record);
        ctx.record.clear();
        ctx.defer = true;
    }

    /// Ends [`CaptureField::begin_deferring`]: `record` gets back its
    /// buffers with what was recorded, for [`HashGrid::scatter`]
    /// (and `ctx` what `record` held: pass an empty one).
    pub fn end_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        ctx.defer = false;
        std::mem::swap(&mut ctx.record, record);
    }

    /// The hash grid (its table's gradient is what
    /// [`CaptureField::begin_deferring`] defers).
    pub fn grid(&self) -> &HashGrid {
        &self.grid
    }

    /// dL/d(position) (model space) and dL/d(direction), `[n x 3]` each, of
    /// the last [`CaptureField::backward_with_input_grads`].
    pub fn input_grads<'c>(&self, ctx: &'c Ctx) -> (&'c [f32], &'c [f32]) {
        (&ctx.d_pos[..3 * ctx.n], &ctx.d_dirs[..3 * ctx.n])
    }

    /// The backward pass; with `dirs`, also dL/du of the grid coordinates
    /// (`ctx.d_unit`) and dL/d(direction) (`ctx.d_dirs`).
    fn backward_inner(
        &self,
        p: &[f32],
        ctx: &mut Ctx,
        dsigma: &[f32],
        drgb: &[f32],
        grads: &mut [f32],
        dirs: Option<&[f32]>,
    ) {
        debug_assert!(ctx.half.is_none(), "a backward pass over a half-precision render pass");
        let n = ctx.n;
        if dirs.is_some() {
            ctx.d_dirs.clear();
            ctx.d_dirs.resize(n * 3, 0.0);
            size(&mut ctx.d_unit, n * 3);
        }
        if n == 0 {
            return;
        }
        let (h, g, gw) = (self.c1.outputs, self.d2.outputs, self.grid.width());
        size(&mut ctx.draw, n * 3);
        for ((d, &dc), &s) in ctx.draw[..n * 3].iter_mut().zip(&drgb[..n * 3]).zip(&ctx.rgb) {
            *d = dc * s * (1.0 - s);
        }
        size(&mut ctx.d_a, n * h);
        self.c3.backward_dots(&ctx.a2, &ctx.draw, n, grads);
        self.c3.input_grad(p, &ctx.draw, n, &mut ctx.d_a);
        relu_backward(&ctx.a2[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_b, n * h);
        self.c2.backward(p, &[(&ctx.a1, h)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_b)]);
        relu_backward(&ctx.a1[..n * h], &mut ctx.d_b[..n * h]);
        if ctx.app.len() == n {
            self.appearance.backward(p, &mut ctx.app, &ctx.d_b[..n * h], grads);
        }
        size(&mut ctx.d_geo, n * g);
        let d_shd = match dirs {
            Some(_) => {
                size(&mut ctx.d_shd, n * sh::WIDTH);
                Some(&mut ctx.d_shd[..])
            }
            None => None,
        };
        let blocks = [(&ctx.geo[..], g), (&ctx.shd[..], sh::WIDTH)];
        self.c1.backward(p, &blocks, &ctx.d_b, n, grads, &mut [Some(&mut ctx.d_geo), d_shd]);
        // dσ/draw = σ (zero where the NDC selector zeroed σ).
        for ((row, &ds), &s) in ctx.d_geo.chunks_exact_mut(g).zip(&dsigma[..n]).zip(&ctx.sigma) {
            row[0] += ds * s;
        }
        self.d2.backward(p, &[(&ctx.h1, h)], &ctx.d_geo, n, grads, &mut [Some(&mut ctx.d_a)]);
        relu_backward(&ctx.h1[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_enc, n * gw);
        self.d1.backward(p, &[(&ctx.enc, gw)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_enc)]);
        let Some(dirs) = dirs else {
            if ctx.defer {
                self.grid.record(&ctx.unit[..n * 3], &ctx.d_enc, &mut ctx.record);
            } else {
                self.grid.backward(&ctx.unit[..n * 3], &ctx.d_enc, grads);
            }
            return;
        };
        self.grid.backward_with_input_grad(p, &ctx.unit[..n * 3], &ctx.d_enc, grads, &mut ctx.d_unit);
        sh::encode_backward(&dirs[..n * 3], &ctx.d_shd[..n * sh::WIDTH], &mut ctx.d_dirs);
    }
}

#[cfg(test)]
#[path = "capture_tests.rs"]
mod tests;
