//! Fields: what a radiance field says about points in model space.
//!
//! A field answers two questions separately (as nerfstudio's fields do): the
//! density of a batch of samples, which is all an occupancy grid or the
//! early-termination test needs, and the colour of some of those samples
//! seen along their directions. A forward pass keeps what its backward needs
//! in a context the caller owns and hands back (tiny-cuda-nn's style), so
//! one thread reuses its buffers across batches. Parameters are the field's
//! named ranges of the model's one flat buffer (`nn::linear::ParamLayout`),
//! so Adam, checkpoints and the divergence guard treat every field alike.
//!
//! Shapes: `n` samples per pass; positions and directions `[n x 3]`,
//! densities `[n]`, colours `[n x 3]` in [0, 1].
//!
//! `space` holds the maps from model space into a grid's unit cube for
//! scenes that do not fit a box (contraction, NDC), with their gradients.
//! The real-capture model's fields work in that mapped space: `capture`
//! (the hash-grid field with a per-image appearance) and `proposal` (the
//! small density-only networks that place its samples). `hash_grid` and
//! `capture` are built on the same networks (`nets`: hash grid, density
//! MLP, colour MLP), each with its own map into the grid's cube and its
//! own additions.

pub mod capture;
pub mod hash_grid;
pub mod mlp;
mod nets;
pub mod proposal;
pub mod space;

/// The samples a field is asked about: `n = pos.len() / 3` rows.
#[derive(Clone, Copy, Debug)]
pub struct Points<'a> {
    /// Positions in model space, `[n x 3]`.
    pub pos: &'a [f32],
    /// Unit view directions, `[n x 3]`.
    pub dirs: &'a [f32],
    /// Per sample, the index of the training image its ray came from
    /// (`[n]`, empty when rendering a new view). The fields here ignore it;
    /// a field with per-image appearance reads it.
    pub image: &'a [u32],
}

/// A radiance field over a flat parameter buffer.
pub trait Field: Send + Sync {
    /// Saved activations and scratch of one thread, reused across passes.
    type Ctx: Default + Send;

    /// Evaluates the densities of `pts` (read them with [`Field::sigma`]),
    /// keeping what [`Field::color`] and [`Field::backward`] need.
    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut Self::Ctx);

    /// Keeps the samples `keep` (sorted indices) of the last density pass.
    fn compact(&self, ctx: &mut Self::Ctx, keep: &[usize]);

    /// Evaluates the colours of the samples of the last density pass (after
    /// any [`Field::compact`]) seen along `dirs` (read them with [`Field::rgb`]).
    fn color(&self, params: &[f32], dirs: &[f32], ctx: &mut Self::Ctx);

    /// Densities of the last pass, `[n]`.
    fn sigma<'c>(&self, ctx: &'c Self::Ctx) -> &'c [f32];

    /// Colours of the last colour pass, `[n x 3]`.
    fn rgb<'c>(&self, ctx: &'c Self::Ctx) -> &'c [f32];

    /// Appends to `rows` what the colour of sample `i` of the last density
    /// pass needs, so it can be coloured later with other samples
    /// ([`Field::color_rows`]); the render loop gathers the samples that
    /// matter over several density passes and colours them once.
    fn save_row(&self, ctx: &Self::Ctx, i: usize, rows: &mut Vec<f32>);

    /// Colours `[n x 3]` of samples from rows [`Field::save_row`] wrote, seen
    /// along `dirs` (`[n x 3]`); read them with [`Field::rgb`].
    fn color_rows(&self, params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut Self::Ctx);

    /// Accumulates into `grads` the gradient of a loss given dL/dsigma
    /// (`[n]`) and dL/drgb (`[n x 3]`) of the last density and colour pass.
    fn backward(&self, params: &[f32], ctx: &mut Self::Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]);
}

/// Makes `v` hold at least `n` values. Buffers never shrink, so reusing
/// one for chunks of varying size does not zero-fill it again (that was 4%
/// of training time); readers take the first `ctx.n` rows.
pub(crate) fn size(v: &mut Vec<f32>, n: usize) {
    if v.len() < n {
        v.resize(n, 0.0);
    }
}

/// Densities `[n]` of `field` at model-space points `pos` (`[n x 3]`),
/// evaluated in parallel chunks of `chunk` points (what an occupancy grid
/// asks). Directions do not change a density; the fields get +z.
pub fn densities<F: Field>(field: &F, params: &[f32], pos: &[f32], chunk: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let mut out = vec![0.0f32; pos.len() / 3];
    out.par_chunks_mut(chunk).zip(pos.par_chunks(3 * chunk)).for_each(|(o, p)| {
        let dirs = [0.0f32, 0.0, 1.0].repeat(o.len());
        let mut ctx = F::Ctx::default();
        field.density(params, Points { pos: p, dirs: &dirs, image: &[] }, &mut ctx);
        o.copy_from_slice(field.sigma(&ctx));
    });
    out
}

/// A field small enough to check by hand, for tests of the parts that take
/// any field: density `softplus(a . p + b)`, colour channel `k`
/// `sigmoid(c . p + d + k / 4)`, parameters `[a0 a1 a2 b c0 c1 c2 d]`.
#[cfg(test)]
pub mod toy {
    use super::{Field, Points};
    use crate::engine::nn::gather_rows;
    use crate::engine::nn::linear::{sigmoid, softplus, softplus_grad};

    pub struct Toy;

    #[derive(Default)]
    pub struct ToyCtx {
        pos: Vec<f32>,
        raw: Vec<f32>,
        sigma: Vec<f32>,
        rgb: Vec<f32>,
    }

    fn dot(w: &[f32], p: &[f32]) -> f32 {
        w[0] * p[0] + w[1] * p[1] + w[2] * p[2]
    }

    impl Field for Toy {
        type Ctx = ToyCtx;

        fn density(&self, w: &[f32], pts: Points<'_>, ctx: &mut ToyCtx) {
            ctx.pos = pts.pos.to_vec();
            ctx.raw = pts.pos.chunks_exact(3).map(|p| dot(&w[0..3], p) + w[3]).collect();
            ctx.sigma = ctx.raw.iter().map(|&r| softplus(r)).collect();
        }

        fn compact(&self, ctx: &mut ToyCtx, keep: &[usize]) {
            gather_rows(&mut ctx.pos, 3, keep);
            gather_rows(&mut ctx.raw, 1, keep);
            gather_rows(&mut ctx.sigma, 1, keep);
        }

        fn color(&self, w: &[f32], _dirs: &[f32], ctx: &mut ToyCtx) {
            ctx.rgb = ctx
                .pos
                .chunks_exact(3)
                .flat_map(|p| {
                    let z = dot(&w[4..7], p) + w[7];
                    [sigmoid(z), sigmoid(z + 0.25), sigmoid(z + 0.5)]
                })
                .collect();
        }

        fn sigma<'c>(&self, ctx: &'c ToyCtx) -> &'c [f32] {
            &ctx.sigma
        }

        fn rgb<'c>(&self, ctx: &'c ToyCtx) -> &'c [f32] {
            &ctx.rgb
        }

        fn save_row(&self, ctx: &ToyCtx, i: usize, rows: &mut Vec<f32>) {
            rows.extend_from_slice(&ctx.pos[3 * i..3 * i + 3]);
        }

        fn color_rows(&self, w: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut ToyCtx) {
            ctx.pos = rows;
            self.color(w, dirs, ctx);
        }

        fn backward(&self, _w: &[f32], ctx: &mut ToyCtx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
            for (i, p) in ctx.pos.chunks_exact(3).enumerate() {
                let ds = dsigma[i] * softplus_grad(ctx.raw[i]);
                let s = &ctx.rgb[3 * i..3 * i + 3];
                let dz: f32 = (0..3).map(|k| drgb[3 * i + k] * s[k] * (1.0 - s[k])).sum();
                for a in 0..3 {
                    grads[a] += ds * p[a];
                    grads[4 + a] += dz * p[a];
                }
                grads[3] += ds;
                grads[7] += dz;
            }
        }
    }
}
