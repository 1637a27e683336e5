//! A proposal density network (mip-NeRF 360's proposal MLP, nerfacto's
//! `HashMLPDensityField`; design `real-captures.md` 2.4): a small hash grid
//! of a few coarse levels and a tiny MLP in the same mapped space as the
//! main field, giving a density and nothing else. Its densities only decide
//! where the next level's samples go, so it can be far cheaper than the main
//! field: it is trained by the interlevel loss to bound the main field's
//! weights from above, never by the photographs directly.
//!
//! Density `σ = init_density · exp(clamp(raw, -15, 15))`, as the capture
//! field's (nerfacto's `average_init_density · trunc_exp`), with the same
//! straight-through derivative `dσ/draw = σ`; zero outside an NDC frustum.

use super::capture::{density_activation, to_grid};
use super::space::SpaceMap;
use crate::engine::nn::hashgrid::{HalfTable, HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward};
use crate::engine::rng::Rng;

/// A proposal network: hash grid, one hidden ReLU layer, one density.
pub struct ProposalField {
    space: SpaceMap,
    grid: HashGrid,
    l1: Linear,
    l2: Linear,
    init_density: f32,
}

/// One thread's activations of a [`ProposalField::density`] pass over `n`
/// points, kept for [`ProposalField::backward`].
#[derive(Default)]
pub struct ProposalCtx {
    n: usize,
    unit: Vec<f32>,
    /// 1 inside the mapped domain, 0 outside (empty: all inside).
    mask: Vec<f32>,
    enc: Vec<f32>,
    h: Vec<f32>,
    raw: Vec<f32>,
    sigma: Vec<f32>,
    d_raw: Vec<f32>,
    d_h: Vec<f32>,
    d_enc: Vec<f32>,
    /// The grid's table in half precision, read instead of the parameters'
    /// while rendering ([`ProposalField::set_render_table`]).
    half: Option<std::sync::Arc<HalfTable>>,
}

/// Makes `v` hold at least `n` values (buffers never shrink; readers take
/// the first `n`).
fn size(v: &mut Vec<f32>, n: usize) {
    if v.len() < n {
        v.resize(n, 0.0);
    }
}

impl ProposalField {
    /// Lays out `{name}.hashgrid`, `{name}.0` (grid -> `hidden`) and
    /// `{name}.1` (`hidden` -> 1).
    pub fn new(
        layout: &mut ParamLayout,
        name: &str,
        space: SpaceMap,
        grid: HashGridConfig,
        hidden: usize,
        init_density: f32,
    ) -> Self {
        let grid = HashGrid::with_name(layout, &format!("{name}.hashgrid"), grid);
        let l1 = Linear::new(layout, &format!("{name}.0"), grid.width(), hidden);
        let l2 = Linear::new(layout, &format!("{name}.1"), hidden, 1);
        Self { space, grid, l1, l2, init_density }
    }

    /// Initialises the network's ranges of `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.grid.init(params, rng);
        self.l1.init(params, rng);
        self.l2.init(params, rng);
    }

    /// The grid's table of `params` in half precision, for rendering
    /// ([`HashGrid::half_table`]; `None` where the CPU cannot use one).
    pub fn half_table(&self, params: &[f32]) -> Option<HalfTable> {
        self.grid.half_table(params)
    }

    /// Makes the density passes of `ctx` read the grid from `table` (a
    /// [`Self::half_table`] of the parameters they are given), or from the
    /// parameters again (`None`). For rendering only.
    pub fn set_render_table(&self, table: Option<std::sync::Arc<HalfTable>>, ctx: &mut ProposalCtx) {
        ctx.half = table;
    }

    /// Densities of the model-space points `pos` (`[n x 3]`); read them
    /// with [`ProposalField::sigma`].
    pub fn density(&self, params: &[f32], pos: &[f32], ctx: &mut ProposalCtx) {
        let n = pos.len() / 3;
        ctx.n = n;
        to_grid(&self.space, pos, &mut ctx.unit, &mut ctx.mask);
        let (gw, h) = (self.grid.width(), self.l1.outputs);
        size(&mut ctx.enc, n * gw);
        size(&mut ctx.h, n * h);
        size(&mut ctx.raw, n);
        size(&mut ctx.sigma, n);
        if n == 0 {
            return;
        }
        match &ctx.half {
            Some(table) => self.grid.forward_half(table, &ctx.unit[..3 * n], &mut ctx.enc),
            None => self.grid.forward(params, &ctx.unit[..3 * n], &mut ctx.enc),
        }
        self.l1.forward(params, &[(&ctx.enc, gw)], n, &mut ctx.h);
        relu(&mut ctx.h[..n * h]);
        self.l2.forward_dots(params, &ctx.h, n, &mut ctx.raw);
        for (i, (s, &r)) in ctx.sigma[..n].iter_mut().zip(&ctx.raw).enumerate() {
            *s = density_activation(self.init_density, r) * ctx.mask.get(i).copied().unwrap_or(1.0);
        }
    }

    /// Densities of the last pass, `[n]`.
    pub fn sigma<'c>(&self, ctx: &'c ProposalCtx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    /// Accumulates into `grads` the gradient of a loss given dL/dσ (`[n]`)
    /// of the last [`ProposalField::density`] pass.
    pub fn backward(&self, params: &[f32], ctx: &mut ProposalCtx, dsigma: &[f32], grads: &mut [f32]) {
        debug_assert!(ctx.half.is_none(), "a backward pass over a half-precision render pass");
        let n = ctx.n;
        if n == 0 {
            return;
        }
        let (gw, h) = (self.grid.width(), self.l1.outputs);
        size(&mut ctx.d_raw, n);
        // dσ/draw = σ (zero where the mask zeroed σ).
        for ((d, &ds), &s) in ctx.d_raw[..n].iter_mut().zip(&dsigma[..n]).zip(&ctx.sigma) {
            *d = ds * s;
        }
        size(&mut ctx.d_h, n * h);
        // The 1-wide output's parameter gradients and the gradient of the
        // grid's 10-odd-wide encoding are dot products (see
        // `Linear::forward_dots`); the rest are GEMMs.
        self.l2.backward_dots(&ctx.h, &ctx.d_raw, n, grads);
        self.l2.input_grad(params, &ctx.d_raw, n, &mut ctx.d_h);
        relu_backward(&ctx.h[..n * h], &mut ctx.d_h[..n * h]);
        size(&mut ctx.d_enc, n * gw);
        self.l1.backward(params, &[(&ctx.enc, gw)], &ctx.d_h, n, grads, &mut [None]);
        self.l1.input_grad_dots(params, &ctx.d_h, n, &mut ctx.d_enc);
        self.grid.backward(&ctx.unit[..3 * n], &ctx.d_enc, grads);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::fields::space::Norm;

    /// Points at log-uniform distances from the origin: inside the unit
    /// cube and far out in the contracted shell. (Parameter gradients are
    /// linear in the tables, so points need not avoid cell faces.)
    fn points(rng: &mut Rng, n: usize) -> Vec<f32> {
        (0..n)
            .flat_map(|_| {
                let r = 10f32.powf(2.0 * rng.f32() - 1.0);
                [rng.normal() * r, rng.normal() * r, rng.normal() * r]
            })
            .collect()
    }

    /// dL/dθ of `L = Σ g_i σ_i` for every parameter of a small proposal
    /// network, against central differences of the f32 forward pass summed
    /// in f64.
    #[test]
    fn parameter_gradients_match_finite_differences_in_f64() {
        for norm in [Norm::Linf, Norm::L2] {
            let grid = HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 };
            let mut layout = ParamLayout::default();
            let _pad = layout.add("pad", 5);
            let f = ProposalField::new(&mut layout, "p", SpaceMap::Contract { norm }, grid, 6, 0.5);
            let mut rng = Rng::new(3);
            let mut params = vec![0.0f32; layout.len];
            f.init(&mut params, &mut rng);
            for p in params.iter_mut() {
                *p += 0.3 * rng.normal();
            }
            let n = 11;
            let pos = points(&mut rng, n);
            let g: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
            let run = |p: &[f32]| -> f64 {
                let mut c = ProposalCtx::default();
                f.density(p, &pos, &mut c);
                f.sigma(&c).iter().zip(&g).map(|(a, b)| *a as f64 * *b as f64).sum()
            };
            let mut c = ProposalCtx::default();
            f.density(&params, &pos, &mut c);
            assert!(f.sigma(&c).iter().all(|s| s.is_finite() && *s > 0.0));
            let mut grads = vec![0.0f32; layout.len];
            f.backward(&params, &mut c, &g, &mut grads);
            assert!(grads[..5].iter().all(|&v| v == 0.0), "other ranges untouched");
            let mut nonzero = 0;
            for (name, range) in &layout.names[1..] {
                for i in range.clone() {
                    let h = 1e-3f32 * (1.0 + params[i].abs());
                    let mut p = params.clone();
                    p[i] += h;
                    let fp = run(&p);
                    p[i] -= 2.0 * h;
                    let fm = run(&p);
                    let num = (fp - fm) / (2.0 * h as f64);
                    let ana = grads[i] as f64;
                    assert!(
                        (num - ana).abs() < 2e-3 + 2e-2 * num.abs(),
                        "{norm:?} {name}[{i}]: numeric {num}, analytic {ana}"
                    );
                    nonzero += (ana.abs() > 1e-3) as usize;
                }
            }
            assert!(nonzero > 40, "{norm:?}: only {nonzero} gradients are not tiny");
        }
    }

    /// The density is the activation of the network's output: at zero
    /// weights and biases every point gets exactly `init_density`.
    #[test]
    fn zero_network_gives_the_initial_density_everywhere() {
        let grid = HashGridConfig { levels: 2, log2_table: 6, base_resolution: 2, finest_resolution: 4 };
        let mut layout = ParamLayout::default();
        let f = ProposalField::new(&mut layout, "p", SpaceMap::Contract { norm: Norm::Linf }, grid, 4, 0.01);
        let params = vec![0.0f32; layout.len];
        let mut c = ProposalCtx::default();
        f.density(&params, &[0.0, 0.0, 0.0, 1e6, -3.0, 2.0], &mut c);
        assert_eq!(f.sigma(&c), &[0.01, 0.01]);
        f.density(&params, &[], &mut c);
        assert!(f.sigma(&c).is_empty());
    }
}
