//! The classic model's field: NeRF's MLP (`nn::nerf_net`) on frequency
//! encodings of the position and direction. The network computes density
//! and colour in one pass, so its density pass keeps the colours and its
//! colour pass hands them over.

use super::{Field, Points};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::nerf_net::{NerfNet, NetConfig, NetCtx};
use crate::engine::rng::Rng;

/// One NeRF MLP as a field.
pub struct MlpField {
    net: NerfNet,
}

impl MlpField {
    /// Lays out the network's parameters in `layout` under `prefix`.
    pub fn new(layout: &mut ParamLayout, prefix: &str, config: NetConfig) -> Self {
        Self { net: NerfNet::new(layout, prefix, config) }
    }

    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.net.init(params, rng);
    }
}

impl Field for MlpField {
    type Ctx = NetCtx;

    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut NetCtx) {
        let n = pts.pos.len() / 3;
        self.net.forward(params, pts.pos, pts.dirs, n, ctx);
    }

    fn compact(&self, ctx: &mut NetCtx, keep: &[usize]) {
        ctx.compact(keep);
    }

    fn color(&self, _params: &[f32], _dirs: &[f32], _ctx: &mut NetCtx) {}

    fn sigma<'c>(&self, ctx: &'c NetCtx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    fn rgb<'c>(&self, ctx: &'c NetCtx) -> &'c [f32] {
        &ctx.rgb[..3 * ctx.n]
    }

    fn save_row(&self, ctx: &NetCtx, i: usize, rows: &mut Vec<f32>) {
        rows.extend_from_slice(&ctx.rgb[3 * i..3 * i + 3]);
    }

    fn color_rows(&self, _params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut NetCtx) {
        ctx.n = dirs.len() / 3;
        ctx.rgb = rows;
    }

    fn backward(&self, params: &[f32], ctx: &mut NetCtx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        self.net.backward(params, ctx, dsigma, drgb, grads);
    }
}
