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

pub mod hash_grid;
pub mod mlp;

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
