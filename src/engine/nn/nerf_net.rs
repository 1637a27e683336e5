//! The network of the original NeRF: positional encodings, an 8x256 ReLU
//! trunk with the input concatenated again after the 4th layer, a density
//! head, a 256-wide feature that meets the encoded direction in a 128-wide
//! layer, and a sigmoid RGB head. Forward returns a context that backward
//! takes back.

use crate::engine::nn::encoding::{encode, encoded_width};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward, sigmoid, softplus, softplus_grad};
use crate::engine::rng::Rng;

/// The network's shape. `Default` is the paper's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NetConfig {
    /// Frequencies of the position encoding (10).
    pub pos_freqs: usize,
    /// Frequencies of the direction encoding (4).
    pub dir_freqs: usize,
    /// Trunk width (256).
    pub width: usize,
    /// Trunk depth (8).
    pub depth: usize,
    /// The encoded position is concatenated to the output of this many
    /// trunk layers (4, i.e. it enters the 5th layer).
    pub skip: usize,
    /// Width of the direction-dependent layer (128).
    pub dir_width: usize,
}

impl Default for NetConfig {
    fn default() -> Self {
        Self { pos_freqs: 10, dir_freqs: 4, width: 256, depth: 8, skip: 4, dir_width: 128 }
    }
}

/// One NeRF MLP whose parameters live in a shared flat buffer.
#[derive(Clone, Debug)]
pub struct NerfNet {
    pub config: NetConfig,
    trunk: Vec<Linear>,
    sigma: Linear,
    feature: Linear,
    dir: Linear,
    rgb: Linear,
}

/// Saved activations of a forward pass over `n` samples.
#[derive(Default, Debug)]
pub struct NetCtx {
    pub n: usize,
    xenc: Vec<f32>,
    denc: Vec<f32>,
    h: Vec<Vec<f32>>,
    feat: Vec<f32>,
    hd: Vec<f32>,
    sigma_raw: Vec<f32>,
    /// Activated density per sample.
    pub sigma: Vec<f32>,
    /// Colour per sample, `[n x 3]` in [0, 1].
    pub rgb: Vec<f32>,
    // backward scratch
    dh: Vec<f32>,
    dh2: Vec<f32>,
    dfeat: Vec<f32>,
    dhd: Vec<f32>,
}

impl NetCtx {
    /// Keeps samples `keep` (sorted) of the last forward pass: every saved
    /// activation, so a backward pass over the kept samples is exact.
    pub fn compact(&mut self, keep: &[usize]) {
        let n = self.n;
        let rows = |v: &mut Vec<f32>| {
            if let Some(width) = v.len().checked_div(n) {
                crate::engine::nn::gather_rows(v, width, keep);
            }
        };
        for v in [&mut self.xenc, &mut self.denc, &mut self.feat, &mut self.hd, &mut self.sigma_raw] {
            rows(v);
        }
        for v in [&mut self.sigma, &mut self.rgb] {
            rows(v);
        }
        for h in &mut self.h {
            rows(h);
        }
        self.n = keep.len();
    }
}

fn resize(v: &mut Vec<f32>, len: usize) {
    v.resize(len, 0.0);
}

impl NerfNet {
    pub fn new(layout: &mut ParamLayout, prefix: &str, config: NetConfig) -> Self {
        let xw = encoded_width(3, config.pos_freqs);
        let dw = encoded_width(3, config.dir_freqs);
        let mut trunk = Vec::with_capacity(config.depth);
        for i in 0..config.depth {
            let inputs = if i == 0 {
                xw
            } else if i == config.skip + 1 && config.skip + 1 < config.depth {
                config.width + xw
            } else {
                config.width
            };
            trunk.push(Linear::new(layout, &format!("{prefix}.trunk{i}"), inputs, config.width));
        }
        let sigma = Linear::new(layout, &format!("{prefix}.sigma"), config.width, 1);
        let feature = Linear::new(layout, &format!("{prefix}.feature"), config.width, config.width);
        let dir = Linear::new(layout, &format!("{prefix}.dir"), config.width + dw, config.dir_width);
        let rgb = Linear::new(layout, &format!("{prefix}.rgb"), config.dir_width, 3);
        Self { config, trunk, sigma, feature, dir, rgb }
    }

    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        for l in self.trunk.iter().chain([&self.sigma, &self.feature, &self.dir, &self.rgb]) {
            l.init(params, rng);
        }
    }

    fn xw(&self) -> usize {
        encoded_width(3, self.config.pos_freqs)
    }
    fn dw(&self) -> usize {
        encoded_width(3, self.config.dir_freqs)
    }

    /// Evaluates `n` samples at `pts` (`[n x 3]`, normalised coordinates)
    /// seen along unit directions `dirs` (`[n x 3]`); results in
    /// `ctx.sigma` and `ctx.rgb`, activations kept for [`NerfNet::backward`].
    pub fn forward(&self, params: &[f32], pts: &[f32], dirs: &[f32], n: usize, ctx: &mut NetCtx) {
        let (xw, dw, w) = (self.xw(), self.dw(), self.config.width);
        ctx.n = n;
        resize(&mut ctx.xenc, n * xw);
        resize(&mut ctx.denc, n * dw);
        encode(&pts[..n * 3], 3, self.config.pos_freqs, &mut ctx.xenc);
        encode(&dirs[..n * 3], 3, self.config.dir_freqs, &mut ctx.denc);
        ctx.h.resize_with(self.config.depth, Vec::new);
        for i in 0..self.config.depth {
            let (before, rest) = ctx.h.split_at_mut(i);
            let out = &mut rest[0];
            resize(out, n * w);
            let l = &self.trunk[i];
            if i == 0 {
                l.forward(params, &[(&ctx.xenc, xw)], n, out);
            } else if l.inputs == w + xw {
                l.forward(params, &[(&before[i - 1], w), (&ctx.xenc, xw)], n, out);
            } else {
                l.forward(params, &[(&before[i - 1], w)], n, out);
            }
            relu(out);
        }
        let last = &ctx.h[self.config.depth - 1];
        resize(&mut ctx.sigma_raw, n);
        self.sigma.forward(params, &[(last, w)], n, &mut ctx.sigma_raw);
        resize(&mut ctx.feat, n * w);
        self.feature.forward(params, &[(last, w)], n, &mut ctx.feat);
        resize(&mut ctx.hd, n * self.config.dir_width);
        self.dir.forward(params, &[(&ctx.feat, w), (&ctx.denc, dw)], n, &mut ctx.hd);
        relu(&mut ctx.hd);
        resize(&mut ctx.rgb, n * 3);
        self.rgb.forward(params, &[(&ctx.hd, self.config.dir_width)], n, &mut ctx.rgb);
        for v in &mut ctx.rgb {
            *v = sigmoid(*v);
        }
        resize(&mut ctx.sigma, n);
        for (s, &r) in ctx.sigma.iter_mut().zip(&ctx.sigma_raw) {
            *s = softplus(r);
        }
    }

    /// Accumulates parameter gradients into `grads` given dL/dsigma and
    /// dL/drgb (`[n x 3]`) for the samples of the last forward pass.
    pub fn backward(&self, params: &[f32], ctx: &mut NetCtx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        let n = ctx.n;
        let (xw, dw, w, dwid) = (self.xw(), self.dw(), self.config.width, self.config.dir_width);
        let depth = self.config.depth;
        // RGB head: d(raw) = drgb * s (1 - s)
        let mut draw: Vec<f32> = drgb[..n * 3].iter().zip(&ctx.rgb).map(|(&g, &s)| g * s * (1.0 - s)).collect();
        resize(&mut ctx.dhd, n * dwid);
        self.rgb.backward(params, &[(&ctx.hd, dwid)], &draw, n, grads, &mut [Some(&mut ctx.dhd)]);
        relu_backward(&ctx.hd, &mut ctx.dhd);
        resize(&mut ctx.dfeat, n * w);
        self.dir.backward(
            params,
            &[(&ctx.feat, w), (&ctx.denc, dw)],
            &ctx.dhd,
            n,
            grads,
            &mut [Some(&mut ctx.dfeat), None],
        );
        let last = &ctx.h[depth - 1];
        resize(&mut ctx.dh, n * w);
        self.feature.backward(params, &[(last, w)], &ctx.dfeat, n, grads, &mut [Some(&mut ctx.dh)]);
        // density head: dh += dsigma_raw * w_sigma^T
        draw.clear();
        draw.extend(dsigma[..n].iter().zip(&ctx.sigma_raw).map(|(&g, &r)| g * softplus_grad(r)));
        resize(&mut ctx.dh2, n * w);
        self.sigma.backward(params, &[(last, w)], &draw, n, grads, &mut [Some(&mut ctx.dh2)]);
        for (a, b) in ctx.dh.iter_mut().zip(&ctx.dh2) {
            *a += b;
        }
        for i in (0..depth).rev() {
            relu_backward(&ctx.h[i], &mut ctx.dh);
            let l = &self.trunk[i];
            if i == 0 {
                l.backward(params, &[(&ctx.xenc, xw)], &ctx.dh, n, grads, &mut [None]);
            } else {
                resize(&mut ctx.dh2, n * w);
                let prev = &ctx.h[i - 1];
                if l.inputs == w + xw {
                    l.backward(
                        params,
                        &[(prev, w), (&ctx.xenc, xw)],
                        &ctx.dh,
                        n,
                        grads,
                        &mut [Some(&mut ctx.dh2), None],
                    );
                } else {
                    l.backward(params, &[(prev, w)], &ctx.dh, n, grads, &mut [Some(&mut ctx.dh2)]);
                }
                std::mem::swap(&mut ctx.dh, &mut ctx.dh2);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dense(l: &Linear, p: &[f64], x: &[f64]) -> Vec<f64> {
        (0..l.outputs)
            .map(|o| p[l.b.start + o] + (0..l.inputs).map(|i| x[i] * p[l.w.start + i * l.outputs + o]).sum::<f64>())
            .collect()
    }

    fn enc(x: &[f64], freqs: usize) -> Vec<f64> {
        let mut out = x.to_vec();
        for k in 0..freqs {
            let f = (1u64 << k) as f64;
            out.extend(x.iter().map(|v| (v * f).sin()));
            out.extend(x.iter().map(|v| (v * f).cos()));
        }
        out
    }

    /// An independent f64 implementation of the forward pass, sample by sample.
    fn reference(net: &NerfNet, p: &[f64], pt: &[f64], dir: &[f64]) -> (f64, [f64; 3]) {
        let relu = |v: Vec<f64>| v.into_iter().map(|x| x.max(0.0)).collect::<Vec<_>>();
        let xe = enc(pt, net.config.pos_freqs);
        let mut h = relu(dense(&net.trunk[0], p, &xe));
        for l in &net.trunk[1..] {
            let mut input = h.clone();
            if l.inputs > net.config.width {
                input.extend(&xe);
            }
            h = relu(dense(l, p, &input));
        }
        let raw = dense(&net.sigma, p, &h)[0];
        let sigma = if raw > 20.0 { raw } else { raw.exp().ln_1p() };
        let mut f = dense(&net.feature, p, &h);
        f.extend(enc(dir, net.config.dir_freqs));
        let hd = relu(dense(&net.dir, p, &f));
        let c = dense(&net.rgb, p, &hd);
        let s = |v: f64| 1.0 / (1.0 + (-v).exp());
        (sigma, [s(c[0]), s(c[1]), s(c[2])])
    }

    #[test]
    fn network_matches_f64_reference_and_finite_differences() {
        let cfg = NetConfig { pos_freqs: 2, dir_freqs: 1, width: 8, depth: 4, skip: 1, dir_width: 6 };
        let mut layout = ParamLayout::default();
        let net = NerfNet::new(&mut layout, "t", cfg);
        let mut rng = Rng::new(11);
        let mut params = vec![0.0f32; layout.len];
        net.init(&mut params, &mut rng);
        for p in params.iter_mut() {
            *p += 0.05 * rng.normal(); // non-zero biases too
        }
        let n = 5;
        let pts: Vec<f32> = (0..n * 3).map(|_| rng.f32() * 2.0 - 1.0).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|i| [0.6f32, i as f32 * 0.1, 0.8]).collect();
        let gs: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
        let gc: Vec<f32> = (0..n * 3).map(|_| rng.normal()).collect();
        let to64 = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
        let (pts64, dirs64) = (to64(&pts), to64(&dirs));
        let objective = |p: &[f64]| -> f64 {
            (0..n)
                .map(|i| {
                    let (s, c) = reference(&net, p, &pts64[3 * i..3 * i + 3], &dirs64[3 * i..3 * i + 3]);
                    s * gs[i] as f64 + (0..3).map(|k| c[k] * gc[3 * i + k] as f64).sum::<f64>()
                })
                .sum()
        };
        let mut ctx = NetCtx::default();
        net.forward(&params, &pts, &dirs, n, &mut ctx);
        let p64 = to64(&params);
        // The f32 forward agrees with the f64 reference.
        for i in 0..n {
            let (s, c) = reference(&net, &p64, &pts64[3 * i..3 * i + 3], &dirs64[3 * i..3 * i + 3]);
            assert!((s - ctx.sigma[i] as f64).abs() < 1e-5 * (1.0 + s.abs()));
            for k in 0..3 {
                assert!((c[k] - ctx.rgb[3 * i + k] as f64).abs() < 1e-5);
            }
        }
        let mut grads = vec![0.0f32; layout.len];
        net.backward(&params, &mut ctx, &gs, &gc, &mut grads);
        // Central differences in f64 over every parameter.
        let h = 1e-6;
        for (name, range) in &layout.names {
            for i in range.clone() {
                let mut p = p64.clone();
                p[i] += h;
                let fp = objective(&p);
                p[i] -= 2.0 * h;
                let fm = objective(&p);
                let num = (fp - fm) / (2.0 * h);
                let ana = grads[i] as f64;
                assert!((num - ana).abs() < 1e-4 * (1.0 + num.abs()), "{name}[{i}]: numeric {num}, analytic {ana}");
            }
        }
    }
}
