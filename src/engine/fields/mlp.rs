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

#[cfg(test)]
mod tests {
    use super::*;

    /// Compacting a pass keeps every activation: the gradient of the kept
    /// samples equals that of a pass over them alone.
    #[test]
    fn compacted_pass_trains_like_a_pass_over_the_kept_samples() {
        let config = NetConfig { pos_freqs: 3, dir_freqs: 2, width: 16, depth: 4, skip: 1, dir_width: 8 };
        let mut layout = ParamLayout::default();
        let field = MlpField::new(&mut layout, "f", config);
        let mut params = vec![0.0; layout.len];
        let mut rng = Rng::new(3);
        field.init(&mut params, &mut rng);
        let n = 9;
        let pos: Vec<f32> = (0..3 * n).map(|_| rng.f32() - 0.5).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|i| [0.6f32, 0.0, 0.8].map(|d| d + 0.01 * i as f32)).collect();
        let keep = [0usize, 3, 4, 8];
        let ds: Vec<f32> = (0..keep.len()).map(|_| rng.normal()).collect();
        let dc: Vec<f32> = (0..3 * keep.len()).map(|_| rng.normal()).collect();
        let pass = |pos: &[f32], dirs: &[f32], compact: bool| {
            let mut ctx = NetCtx::default();
            field.density(&params, Points { pos, dirs, image: &[] }, &mut ctx);
            if compact {
                field.compact(&mut ctx, &keep);
            }
            field.color(&params, dirs, &mut ctx);
            let out = (field.sigma(&ctx).to_vec(), field.rgb(&ctx).to_vec());
            let mut grads = vec![0.0; params.len()];
            field.backward(&params, &mut ctx, &ds, &dc, &mut grads);
            (out, grads)
        };
        let rows = |v: &[f32]| keep.iter().flat_map(|&i| v[3 * i..3 * i + 3].to_vec()).collect::<Vec<f32>>();
        let (sub_out, sub_grads) = pass(&rows(&pos), &rows(&dirs), false);
        let (out, grads) = pass(&pos, &dirs, true);
        assert_eq!(out, sub_out);
        assert!(sub_grads.iter().any(|g| *g != 0.0));
        for (a, b) in grads.iter().zip(&sub_grads) {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
        }
    }
}
