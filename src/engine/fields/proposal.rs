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

use super::capture::to_grid;
use super::nets::density_activation;
use super::size;
use super::space::SpaceMap;
use crate::engine::nn::hashgrid::{HalfTable, HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward};
use crate::engine::rng::Rng;

/// Most grid levels [`ProposalField::density`]'s fused render pass keeps in
/// registers (more: the pass over all points, as training's).
#[cfg(target_arch = "x86_64")]
const FUSED_LEVELS: usize = 16;

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
    /// The rows the backward pass keeps (those with a gradient).
    keep: Vec<usize>,
    /// The grid's table in half precision, read instead of the parameters'
    /// while rendering ([`ProposalField::set_render_table`]).
    half: Option<std::sync::Arc<HalfTable>>,
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
    /// with [`ProposalField::sigma`]. With a render table (x86_64, which a
    /// half table implies), eight points at a time in one fused pass: the
    /// map, the encoding, both layers and the activation in registers
    /// ([`Self::density_fused`]: the same densities but for the order of
    /// the sums, no activations kept: nothing to differentiate).
    pub fn density(&self, params: &[f32], pos: &[f32], ctx: &mut ProposalCtx) {
        #[cfg(target_arch = "x86_64")]
        if let Some(table) = &ctx.half
            && self.grid.levels() <= FUSED_LEVELS
        {
            let n = pos.len() / 3;
            ctx.n = n;
            size(&mut ctx.sigma, n);
            // The map stays out of the AVX code: called from it, it ran 4
            // times slower (baseline SSE code between AVX instructions).
            to_grid(&self.space, pos, &mut ctx.unit, &mut ctx.mask);
            // SAFETY: a half table exists only where AVX2, FMA and F16C do.
            unsafe { self.density_fused(params, table, &ctx.unit, &ctx.mask, &mut ctx.sigma[..n]) };
            return;
        }
        self.density_unfused(params, pos, ctx);
    }

    /// The densities of `pos` one stage at a time over all points, keeping
    /// the encoding and hidden activations in `ctx` for the backward pass.
    fn density_unfused(&self, params: &[f32], pos: &[f32], ctx: &mut ProposalCtx) {
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

    /// [`Self::density`] into `sigma` of the points whose grid coordinates
    /// are `unit` (`to_grid`'s, with its `mask`), from the half table
    /// `table`, eight at a time.
    ///
    /// # Safety
    /// AVX2, FMA and F16C must be available; `table` must be this field's
    /// grid's.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn density_fused(&self, params: &[f32], table: &HalfTable, unit: &[f32], mask: &[f32], sigma: &mut [f32]) {
        use std::arch::x86_64::*;

        use crate::engine::nn::hashgrid::{FEATURES, sanitize};
        let n = sigma.len();
        let (inputs, hidden) = (self.l1.inputs, self.l1.outputs);
        assert!(unit.len() >= 3 * n && inputs == FEATURES * self.grid.levels() && inputs <= 2 * FUSED_LEVELS);
        let (w1, b1) = (&params[self.l1.w.clone()], &params[self.l1.b.clone()]);
        let (w2, b2) = (&params[self.l2.w.clone()], params[self.l2.b.start]);
        assert!(w1.len() == inputs * hidden && b1.len() == hidden && w2.len() == hidden);
        let mut features = [_mm256_setzero_ps(); 2 * FUSED_LEVELS];
        let mut u = [[0f32; 8]; 3];
        let mut raw = [0f32; 8];
        for g in (0..n).step_by(8) {
            let m = 8.min(n - g);
            for j in 0..8 {
                for a in 0..3 {
                    u[a][j] = if j < m { sanitize(unit[3 * (g + j) + a]) } else { 0.0 };
                }
            }
            // SAFETY: AVX2, FMA and F16C (this function's features); the
            // table is the grid's (the caller's guarantee); every weight
            // index is below the lengths asserted above.
            unsafe {
                let (x, y, z) =
                    (_mm256_loadu_ps(u[0].as_ptr()), _mm256_loadu_ps(u[1].as_ptr()), _mm256_loadu_ps(u[2].as_ptr()));
                self.grid.encode8_half(table, x, y, z, &mut features);
                let mut r = _mm256_set1_ps(b2);
                for o in 0..hidden {
                    let mut h = _mm256_set1_ps(*b1.get_unchecked(o));
                    for (i, f) in features[..inputs].iter().enumerate() {
                        h = _mm256_fmadd_ps(*f, _mm256_set1_ps(*w1.get_unchecked(i * hidden + o)), h);
                    }
                    r = _mm256_fmadd_ps(_mm256_max_ps(h, _mm256_setzero_ps()), _mm256_set1_ps(*w2.get_unchecked(o)), r);
                }
                _mm256_storeu_ps(raw.as_mut_ptr(), r);
            }
            for j in 0..m {
                // An NDC point outside the open cube has no density (`to_grid`'s mask).
                sigma[g + j] = density_activation(self.init_density, raw[j]) * mask.get(g + j).copied().unwrap_or(1.0);
            }
        }
    }

    /// Densities of the last pass, `[n]`.
    pub fn sigma<'c>(&self, ctx: &'c ProposalCtx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    /// Accumulates into `grads` the gradient of a loss given dL/dσ (`[n]`)
    /// of the last [`ProposalField::density`] pass. It is the pass's last
    /// use: the pass's activations are compacted to the samples with a
    /// gradient (afterwards only [`ProposalField::sigma`] reads the pass).
    pub fn backward(&self, params: &[f32], ctx: &mut ProposalCtx, dsigma: &[f32], grads: &mut [f32]) {
        debug_assert!(ctx.half.is_none(), "a backward pass over a half-precision render pass");
        let (gw, h) = (self.grid.width(), self.l1.outputs);
        size(&mut ctx.d_raw, ctx.n);
        // dσ/draw = σ (zero where the mask zeroed σ).
        for ((d, &ds), &s) in ctx.d_raw[..ctx.n].iter_mut().zip(&dsigma[..ctx.n]).zip(&ctx.sigma) {
            *d = ds * s;
        }
        // Most samples get no gradient at all: the interlevel loss pulls up
        // a level's weights only where they fall short of the final ones,
        // and each weight depends on the densities in front of it only, so
        // every sample behind a ray's last such interval has dσ = 0 (over
        // 70% of gold_cape's while training). Their rows would add zeros.
        let n = compact_rows(ctx, gw, h);
        if n == 0 {
            return;
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

/// Moves the rows of the samples with a gradient (`d_raw != 0`) to the
/// front of the backward pass's inputs (grid coordinates, encoding, hidden
/// layer and `d_raw`), in order; returns how many there are.
fn compact_rows(ctx: &mut ProposalCtx, gw: usize, h: usize) -> usize {
    let n = ctx.n;
    ctx.keep.clear();
    ctx.keep.extend((0..n).filter(|&i| ctx.d_raw[i] != 0.0));
    if ctx.keep.len() == n {
        return n;
    }
    for (j, &i) in ctx.keep.iter().enumerate() {
        // `j <= i`: each row moves forward, onto one already moved or dropped.
        if i != j {
            ctx.unit.copy_within(3 * i..3 * i + 3, 3 * j);
            ctx.enc.copy_within(gw * i..gw * (i + 1), gw * j);
            ctx.h.copy_within(h * i..h * (i + 1), h * j);
            ctx.d_raw[j] = ctx.d_raw[i];
        }
    }
    ctx.keep.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::fields::space::Norm;

    /// A buffer of `len` parameters with `f`'s initialised and every value
    /// then moved by `scale` times a normal draw, so every range has a
    /// gradient.
    fn perturbed_params(f: &ProposalField, len: usize, rng: &mut Rng, scale: f32) -> Vec<f32> {
        let mut params = vec![0.0f32; len];
        f.init(&mut params, rng);
        for p in params.iter_mut() {
            *p += scale * rng.normal();
        }
        params
    }

    /// The samples without a gradient are dropped before the backward
    /// pass: it gives what a pass over the other samples alone gives (up to
    /// rounding: the matrix kernels group the rows in other blocks); with
    /// no gradient at all, nothing; and the densities stay readable.
    #[test]
    fn samples_without_a_gradient_are_skipped() {
        let grid = HashGridConfig { levels: 4, log2_table: 8, base_resolution: 4, finest_resolution: 32 };
        let mut layout = ParamLayout::default();
        let f = ProposalField::new(&mut layout, "p", SpaceMap::Contract { norm: Norm::Linf }, grid, 16, 1.0);
        let mut rng = Rng::new(9);
        let params = perturbed_params(&f, layout.len, &mut rng, 0.3);
        let n = 70;
        let pos = points(&mut rng, n);
        let g: Vec<f32> = (0..n).map(|i| if i % 5 == 0 || (i / 7) % 3 == 1 { rng.normal() } else { 0.0 }).collect();
        let kept: Vec<usize> = (0..n).filter(|&i| g[i] != 0.0).collect();
        assert!(kept.len() > 10 && kept.len() < n / 2);
        let mut c = ProposalCtx::default();
        f.density(&params, &pos, &mut c);
        let sigma = f.sigma(&c).to_vec();
        let mut grads = vec![0.0f32; layout.len];
        f.backward(&params, &mut c, &g, &mut grads);
        assert_eq!(f.sigma(&c), &sigma[..]);

        let sub_pos: Vec<f32> = kept.iter().flat_map(|&i| pos[3 * i..3 * i + 3].to_vec()).collect();
        let sub_g: Vec<f32> = kept.iter().map(|&i| g[i]).collect();
        let mut s = ProposalCtx::default();
        f.density(&params, &sub_pos, &mut s);
        let mut want = vec![0.0f32; layout.len];
        f.backward(&params, &mut s, &sub_g, &mut want);
        assert!(want.iter().filter(|v| **v != 0.0).count() > 50);
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        for (i, (a, b)) in grads.iter().zip(&want).enumerate() {
            assert!((a - b).abs() <= 1e-6 * scale, "parameter {i}: {a} against {b}");
        }

        let mut none = vec![0.0f32; layout.len];
        f.density(&params, &pos, &mut c);
        f.backward(&params, &mut c, &vec![0.0; n], &mut none);
        assert!(none.iter().all(|v| *v == 0.0));
    }

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
            let params = perturbed_params(&f, layout.len, &mut rng, 0.3);
            let n = 15;
            let pos = points(&mut rng, n);
            // Some samples without a gradient (the backward pass drops their rows).
            let g: Vec<f32> = (0..n).map(|i| if i % 4 == 1 || i == n - 1 { 0.0 } else { rng.normal() }).collect();
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

    /// The fused render pass (a half table set) gives the densities of the
    /// pass over all points from the same half table, to the order of the
    /// sums, for both contractions and NDC (zero outside its frustum), at
    /// counts that leave a partial group of 8, and nothing at 0 points.
    #[test]
    fn the_fused_render_pass_matches_the_staged_one() {
        let spaces = [
            SpaceMap::Contract { norm: Norm::Linf },
            SpaceMap::Contract { norm: Norm::L2 },
            crate::engine::fields::space::test_ndc(),
        ];
        let grid = HashGridConfig { levels: 5, log2_table: 10, base_resolution: 4, finest_resolution: 64 };
        for space in spaces {
            let is_ndc = matches!(space, SpaceMap::Ndc(_));
            let mut layout = ParamLayout::default();
            let _pad = layout.add("pad", 3);
            let f = ProposalField::new(&mut layout, "p", space, grid.clone(), 16, 0.7);
            let mut rng = Rng::new(11);
            let params = perturbed_params(&f, layout.len, &mut rng, 0.2);
            let Some(table) = f.half_table(&params).map(std::sync::Arc::new) else {
                eprintln!("no AVX2/FMA/F16C here: the fused pass does not exist on this CPU");
                return;
            };
            for n in [0, 1, 8, 21] {
                // NDC looks down -z: points in front of the camera, some outside its frustum.
                let mut pos = points(&mut rng, n);
                if is_ndc {
                    pos.chunks_mut(3).for_each(|p| p[2] = -p[2].abs() - 0.6);
                }
                let (mut fused, mut staged) = (ProposalCtx::default(), ProposalCtx::default());
                f.set_render_table(Some(table.clone()), &mut fused);
                f.set_render_table(Some(table.clone()), &mut staged);
                f.density(&params, &pos, &mut fused);
                f.density_unfused(&params, &pos, &mut staged);
                assert!(fused.enc.is_empty(), "the fused pass keeps no activations");
                let (a, b) = (f.sigma(&fused), f.sigma(&staged));
                assert_eq!(a.len(), n);
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    assert!((x - y).abs() <= 1e-5 * y.abs() + 1e-12, "{i} of {n}: {x} against {y}");
                }
                if is_ndc && n == 21 {
                    let outside = b.iter().filter(|&&v| v == 0.0).count();
                    assert!(outside > 0 && outside < n, "{outside} of {n} points outside the frustum");
                }
            }
        }
    }
}
