//! The networks of the hash-grid fields, the fast model's (`hash_grid`) and
//! the real-capture model's (`capture`): a multiresolution hash grid over
//! the unit cube, a tiny density MLP whose first output is log-density and
//! the rest geometry features, and a tiny colour MLP on those features and
//! the spherical-harmonics code of the direction.
//!
//! A field maps its points into the cube (a box map, or a scene contraction
//! or NDC with a mask of the points outside), and keeps what is its own
//! around these passes (the capture field's per-image appearance, added to
//! the first colour layer's pre-activations). The two fields were trained
//! with slightly different arithmetic; [`Nets::new`]'s options keep each
//! one's, bit for bit (`tests/train_bits.rs`).

use std::sync::Arc;

use super::size;
use crate::engine::nn::hashgrid::{GridRecord, HalfTable, HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward, sigmoid};
use crate::engine::nn::move_rows;
use crate::engine::nn::sh;
use crate::engine::rng::Rng;

/// Density activation of the hash-grid, capture and proposal fields:
/// `init · exp(clamp(raw, -15, 15))`. Its derivative is taken as the
/// density itself (straight through the clamp), which stays finite. With
/// `init = 1` (the fast model's) the product is exact: `exp(clamp(raw))`.
#[inline]
pub(super) fn density_activation(init: f32, raw: f32) -> f32 {
    init * raw.clamp(-15.0, 15.0).exp()
}

/// How the last colour layer (`hidden -> 3`) computes its products. Both
/// give the same colours but for the order of the sums; each field keeps
/// the one it has always trained with, since a switch would move every bit
/// of its training runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ColorHead {
    /// GEMMs ([`Linear::forward`], [`Linear::backward`]): the fast model's.
    Gemm,
    /// Dot products ([`Linear::forward_dots`], [`Linear::backward_dots`],
    /// [`Linear::input_grad`]), faster for three outputs: the capture
    /// model's.
    Dots,
}

/// The networks over a flat parameter buffer.
pub(super) struct Nets {
    pub(super) grid: HashGrid,
    d1: Linear,
    d2: Linear,
    /// The first colour layer (its outputs: the hidden width).
    pub(super) c1: Linear,
    c2: Linear,
    c3: Linear,
    head: ColorHead,
    /// The scale of the density activation ([`density_activation`]).
    init_density: f32,
}

/// Activations of a forward pass over `n` samples, and the scratch of its
/// backward pass; one per thread, reused across passes.
#[derive(Default)]
pub struct Ctx {
    pub(super) n: usize,
    /// The samples' grid coordinates, `[n x 3]` (the field's map sets them).
    pub(super) unit: Vec<f32>,
    /// Per sample, 1 inside the field's domain and 0 outside (no density
    /// there); empty: all inside. The field's map sets it.
    pub(super) mask: Vec<f32>,
    enc: Vec<f32>,
    h1: Vec<f32>,
    geo: Vec<f32>,
    sigma: Vec<f32>,
    shd: Vec<f32>,
    a1: Vec<f32>,
    a2: Vec<f32>,
    rgb: Vec<f32>,
    /// The grid's table in half precision, read instead of the parameters'
    /// while rendering ([`Nets::set_render_table`]); never set for a pass
    /// that is differentiated.
    half: Option<Arc<HalfTable>>,
    // backward scratch
    draw: Vec<f32>,
    d_a: Vec<f32>,
    d_b: Vec<f32>,
    d_geo: Vec<f32>,
    d_enc: Vec<f32>,
    /// Whether [`Nets::backward`] records the grid's backward pass into
    /// `record` instead of scattering it ([`Nets::begin_deferring`]).
    defer: bool,
    record: GridRecord,
    // input gradients (`backward` with directions only)
    d_shd: Vec<f32>,
    /// dL/du of the grid coordinates, `[n x 3]`.
    d_unit: Vec<f32>,
    /// dL/d(position) in model space ([`Nets::position_grads`]).
    d_pos: Vec<f32>,
    d_dirs: Vec<f32>,
}

impl Nets {
    /// Lays out the grid, `density.0-1` (grid -> `hidden` -> `geo`) and
    /// `color.0-2` (`geo` + direction code -> `hidden` -> `hidden` -> 3).
    pub(super) fn new(
        layout: &mut ParamLayout,
        grid: HashGridConfig,
        hidden: usize,
        geo: usize,
        head: ColorHead,
        init_density: f32,
    ) -> Self {
        let grid = HashGrid::new(layout, grid);
        let d1 = Linear::new(layout, "density.0", grid.width(), hidden);
        let d2 = Linear::new(layout, "density.1", hidden, geo);
        let c1 = Linear::new(layout, "color.0", geo + sh::WIDTH, hidden);
        let c2 = Linear::new(layout, "color.1", hidden, hidden);
        let c3 = Linear::new(layout, "color.2", hidden, 3);
        Self { grid, d1, d2, c1, c2, c3, head, init_density }
    }

    /// Initialises the networks' ranges of `params`.
    pub(super) fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.grid.init(params, rng);
        for l in [&self.d1, &self.d2, &self.c1, &self.c2, &self.c3] {
            l.init(params, rng);
        }
    }

    /// The grid's table of `params` in half precision, for rendering
    /// ([`HashGrid::half_table`]; `None` where the CPU cannot use one).
    pub(super) fn half_table(&self, params: &[f32]) -> Option<HalfTable> {
        self.grid.half_table(params)
    }

    /// Makes the density passes of `ctx` read the grid from `table` (a
    /// [`Self::half_table`] of the parameters they are given) instead of
    /// the parameters, or from the parameters again (`None`). For rendering
    /// only: the backward pass needs the f32 table's encoding.
    pub(super) fn set_render_table(&self, table: Option<Arc<HalfTable>>, ctx: &mut Ctx) {
        ctx.half = table;
    }

    /// Densities (and geometry features) of the first `ctx.n` points of
    /// `ctx.unit`, zero where `ctx.mask` says outside.
    pub(super) fn forward_density(&self, p: &[f32], ctx: &mut Ctx) {
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

    /// Colours of the first `n` samples of the last density pass (or of the
    /// rows `ctx.geo` holds), seen along `dirs` (`[n x 3]`). `bias` may add
    /// to the first colour layer's pre-activations (`[n x hidden]`) before
    /// its ReLU; its gradient is then [`Self::d_color_pre`]'s.
    pub(super) fn forward_color(&self, p: &[f32], dirs: &[f32], ctx: &mut Ctx, bias: impl FnOnce(&mut [f32])) {
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
        bias(&mut ctx.a1[..n * h]);
        relu(&mut ctx.a1[..n * h]);
        self.c2.forward(p, &[(&ctx.a1, h)], n, &mut ctx.a2);
        relu(&mut ctx.a2[..n * h]);
        match self.head {
            ColorHead::Gemm => self.c3.forward(p, &[(&ctx.a2, h)], n, &mut ctx.rgb),
            // Three outputs: dot products (see `Linear::forward_dots`).
            ColorHead::Dots => self.c3.forward_dots(p, &ctx.a2, n, &mut ctx.rgb),
        }
        for v in &mut ctx.rgb[..n * 3] {
            *v = sigmoid(*v);
        }
    }

    /// [`Self::forward_color`] of rows [`Self::save_row`] wrote.
    pub(super) fn color_rows(
        &self,
        p: &[f32],
        rows: Vec<f32>,
        dirs: &[f32],
        ctx: &mut Ctx,
        bias: impl FnOnce(&mut [f32]),
    ) {
        ctx.n = dirs.len() / 3;
        ctx.geo = rows;
        self.forward_color(p, dirs, ctx, bias);
    }

    /// Keeps the samples `keep` (sorted indices) of the last density pass.
    pub(super) fn compact(&self, ctx: &mut Ctx, keep: &[usize]) {
        move_rows(&mut ctx.unit, 3, keep);
        if !ctx.mask.is_empty() {
            move_rows(&mut ctx.mask, 1, keep);
            ctx.mask.truncate(keep.len());
        }
        move_rows(&mut ctx.enc, self.grid.width(), keep);
        move_rows(&mut ctx.h1, self.d1.outputs, keep);
        move_rows(&mut ctx.geo, self.d2.outputs, keep);
        move_rows(&mut ctx.sigma, 1, keep);
        ctx.n = keep.len();
    }

    /// Densities of the last pass, `[n]`.
    pub(super) fn sigma<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    /// Colours of the last colour pass, `[n x 3]`.
    pub(super) fn rgb<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.rgb[..3 * ctx.n]
    }

    /// Appends sample `i`'s geometry features (what its colour needs).
    pub(super) fn save_row(&self, ctx: &Ctx, i: usize, rows: &mut Vec<f32>) {
        let g = self.d2.outputs;
        rows.extend_from_slice(&ctx.geo[i * g..(i + 1) * g]);
    }
}

/// The backward pass.
impl Nets {
    /// Accumulates into `grads` the gradient of both passes given dL/dσ and
    /// dL/drgb (the grid's part is recorded instead while deferring). Given
    /// `dirs` (`[n x 3]`, the directions of the colour pass), also the input
    /// gradients: dL/du of the grid coordinates (for
    /// [`Self::position_grads`]) and dL/d(direction) (the grid's part is
    /// then always added at once). Without, it makes exactly the calls it
    /// always made; with, the parameter gradients are the same.
    pub(super) fn backward(
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
        self.backward_color(p, ctx, drgb, grads, dirs.is_some());
        let (h, g, gw) = (self.c1.outputs, self.d2.outputs, self.grid.width());
        // dσ/draw = σ (zero where the mask zeroed σ).
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

    /// The colour MLP's part of [`Self::backward`] (of `n > 0` samples):
    /// its parameter gradients, dL/d(geometry features) into `ctx.d_geo`,
    /// and with `inputs` dL/d(direction code) into `ctx.d_shd`.
    fn backward_color(&self, p: &[f32], ctx: &mut Ctx, drgb: &[f32], grads: &mut [f32], inputs: bool) {
        let n = ctx.n;
        let (h, g) = (self.c1.outputs, self.d2.outputs);
        size(&mut ctx.draw, n * 3);
        for ((d, &dc), &s) in ctx.draw[..n * 3].iter_mut().zip(&drgb[..n * 3]).zip(&ctx.rgb) {
            *d = dc * s * (1.0 - s);
        }
        size(&mut ctx.d_a, n * h);
        match self.head {
            ColorHead::Gemm => {
                let dx = &mut [Some(&mut ctx.d_a[..])];
                self.c3.backward(p, &[(&ctx.a2, h)], &ctx.draw, n, grads, dx);
            }
            ColorHead::Dots => {
                self.c3.backward_dots(&ctx.a2, &ctx.draw, n, grads);
                self.c3.input_grad(p, &ctx.draw, n, &mut ctx.d_a);
            }
        }
        relu_backward(&ctx.a2[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_b, n * h);
        self.c2.backward(p, &[(&ctx.a1, h)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_b)]);
        relu_backward(&ctx.a1[..n * h], &mut ctx.d_b[..n * h]);
        size(&mut ctx.d_geo, n * g);
        let d_shd = if inputs {
            size(&mut ctx.d_shd, n * sh::WIDTH);
            Some(&mut ctx.d_shd[..])
        } else {
            None
        };
        let blocks = [(&ctx.geo[..], g), (&ctx.shd[..], sh::WIDTH)];
        self.c1.backward(p, &blocks, &ctx.d_b, n, grads, &mut [Some(&mut ctx.d_geo), d_shd]);
    }

    /// dL/d(the first colour layer's pre-activations), `[n x hidden]`, of
    /// the last [`Self::backward`] (what a `bias` of
    /// [`Self::forward_color`] gets).
    pub(super) fn d_color_pre<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.d_b[..ctx.n * self.c1.outputs]
    }

    /// Sets dL/d(position) of each sample of the last [`Self::backward`]
    /// with directions from its dL/du: `vjp(i, du)` through the field's map
    /// of sample `i`.
    pub(super) fn position_grads(&self, ctx: &mut Ctx, mut vjp: impl FnMut(usize, [f32; 3]) -> [f32; 3]) {
        let n = ctx.n;
        size(&mut ctx.d_pos, n * 3);
        for (i, (dx, du)) in ctx.d_pos[..3 * n].chunks_exact_mut(3).zip(ctx.d_unit.chunks_exact(3)).enumerate() {
            dx.copy_from_slice(&vjp(i, [du[0], du[1], du[2]]));
        }
    }

    /// dL/d(position) (model space) and dL/d(direction), `[n x 3]` each, of
    /// the last [`Self::backward`] with directions and
    /// [`Self::position_grads`].
    pub(super) fn input_grads<'c>(&self, ctx: &'c Ctx) -> (&'c [f32], &'c [f32]) {
        (&ctx.d_pos[..3 * ctx.n], &ctx.d_dirs[..3 * ctx.n])
    }

    /// From now on [`Self::backward`] with `ctx` records the grid's part
    /// (its points and output gradients) instead of adding it to the
    /// gradient, into `record`'s buffers (cleared, and lent to `ctx`:
    /// `record` is left empty meanwhile), until [`Self::end_deferring`].
    /// Passes with input gradients still scatter at once.
    pub(super) fn begin_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        std::mem::swap(&mut ctx.record, record);
        ctx.record.clear();
        ctx.defer = true;
    }

    /// Ends [`Self::begin_deferring`]: `record` gets back its buffers with
    /// what was recorded, for [`HashGrid::scatter`] (and `ctx` what `record`
    /// held: pass an empty one).
    pub(super) fn end_deferring(&self, ctx: &mut Ctx, record: &mut GridRecord) {
        ctx.defer = false;
        std::mem::swap(&mut ctx.record, record);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The analytic gradient of `sum(sigma*gs + rgb*gc)` against central
    /// differences of the same f32 forward passes summed in f64, on a small
    /// config (a relative tolerance suited to f32 forward passes), for
    /// both fields' options.
    #[test]
    fn network_gradients_match_finite_differences_in_f64() {
        for (head, init) in [(ColorHead::Gemm, 1.0), (ColorHead::Dots, 0.3)] {
            let grid = HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 };
            let mut layout = ParamLayout::default();
            let nets = Nets::new(&mut layout, grid, 8, 4, head, init);
            let mut rng = Rng::new(5);
            let mut params = vec![0.0f32; layout.len];
            for l in [&nets.d1, &nets.d2, &nets.c1, &nets.c2, &nets.c3] {
                l.init(&mut params, &mut rng);
            }
            for p in params.iter_mut() {
                *p += 0.3 * rng.normal();
            }
            let checked = check_against_differences(&nets, &layout, &params, &mut rng);
            assert!(checked > 200, "{head:?}: {checked}");
        }
    }

    /// Checks every parameter's gradient of a pass over 4 random points;
    /// returns how many it checked.
    fn check_against_differences(nets: &Nets, layout: &ParamLayout, params: &[f32], rng: &mut Rng) -> usize {
        let n = 4;
        let unit: Vec<f32> = (0..n * 3).map(|_| rng.f32()).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|i| [0.6f32, 0.1 * i as f32, 0.8]).collect();
        let gs: Vec<f32> = (0..n).map(|_| rng.normal() * 0.1).collect();
        let gc: Vec<f32> = (0..n * 3).map(|_| rng.normal()).collect();
        let run = |p: &[f32]| -> (f64, Ctx) {
            let mut c = Ctx { n, unit: unit.clone(), ..Default::default() };
            nets.forward_density(p, &mut c);
            nets.forward_color(p, &dirs, &mut c, |_| {});
            let v = c.sigma.iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                + c.rgb.iter().zip(&gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
            (v, c)
        };
        let (_, mut c) = run(params);
        let mut grads = vec![0.0f32; layout.len];
        nets.backward(params, &mut c, &gs, &gc, &mut grads, None);
        let mut checked = 0;
        for (name, range) in &layout.names {
            for i in range.clone() {
                let h = 1e-3f32 * (1.0 + params[i].abs());
                let mut p = params.to_vec();
                p[i] += h;
                let fp = run(&p).0;
                p[i] -= 2.0 * h;
                let fm = run(&p).0;
                let num = (fp - fm) / (2.0 * h as f64);
                let ana = grads[i] as f64;
                assert!((num - ana).abs() < 2e-3 + 2e-2 * num.abs(), "{name}[{i}]: numeric {num}, analytic {ana}");
                checked += 1;
            }
        }
        checked
    }
}
