//! Fully connected layers over a flat parameter buffer, with their backward
//! passes. Activations are row-major `[n x width]` matrices; weights are
//! row-major `[inputs x outputs]`, so `y = x W + b` is one GEMM.
//!
//! A layer can take its input as several column blocks (for NeRF's skip
//! connection and the direction input) without copying them together: each
//! block multiplies its own rows of `W`.

use std::ops::Range;

/// Named ranges in a flat parameter buffer.
#[derive(Clone, Debug, Default)]
pub struct ParamLayout {
    pub len: usize,
    pub names: Vec<(String, Range<usize>)>,
}

impl ParamLayout {
    pub fn add(&mut self, name: &str, len: usize) -> Range<usize> {
        let r = self.len..self.len + len;
        self.len += len;
        self.names.push((name.to_string(), r.clone()));
        r
    }
}

pub use crate::engine::nn::gemm::gemm;

/// A dense layer `y = [x_1 .. x_k] W + b`.
#[derive(Clone, Debug)]
pub struct Linear {
    pub inputs: usize,
    pub outputs: usize,
    pub w: Range<usize>,
    pub b: Range<usize>,
}

impl Linear {
    pub fn new(layout: &mut ParamLayout, name: &str, inputs: usize, outputs: usize) -> Self {
        let w = layout.add(&format!("{name}.w"), inputs * outputs);
        let b = layout.add(&format!("{name}.b"), outputs);
        Self { inputs, outputs, w, b }
    }

    /// He-uniform weights (for ReLU networks), zero bias.
    pub fn init(&self, params: &mut [f32], rng: &mut crate::engine::rng::Rng) {
        let bound = (6.0 / self.inputs as f32).sqrt();
        for p in &mut params[self.w.clone()] {
            *p = (rng.f32() * 2.0 - 1.0) * bound;
        }
        params[self.b.clone()].fill(0.0);
    }

    /// `y[n x outputs] = sum_i x_i[n x width_i] W_i + b` where the blocks'
    /// widths add up to `inputs`.
    pub fn forward(&self, params: &[f32], xs: &[(&[f32], usize)], n: usize, y: &mut [f32]) {
        debug_assert_eq!(xs.iter().map(|x| x.1).sum::<usize>(), self.inputs);
        let out = self.outputs;
        let y = &mut y[..n * out];
        let b = &params[self.b.clone()];
        for row in y.chunks_exact_mut(out) {
            row.copy_from_slice(b);
        }
        let w = &params[self.w.clone()];
        let mut row0 = 0;
        for &(x, width) in xs {
            let wi = &w[row0 * out..(row0 + width) * out];
            gemm(n, width, out, x, (width as isize, 1), wi, (out as isize, 1), 1.0, y, (out as isize, 1));
            row0 += width;
        }
    }

    /// Accumulates `dW += x^T dy`, `db += sum(dy)` into `grads` and, for each
    /// block that wants it, writes `dx_i = dy W_i^T`.
    pub fn backward(
        &self,
        params: &[f32],
        xs: &[(&[f32], usize)],
        dy: &[f32],
        n: usize,
        grads: &mut [f32],
        dxs: &mut [Option<&mut [f32]>],
    ) {
        let out = self.outputs;
        let dy = &dy[..n * out];
        {
            let db = &mut grads[self.b.clone()];
            for row in dy.chunks_exact(out) {
                for (g, d) in db.iter_mut().zip(row) {
                    *g += d;
                }
            }
        }
        let w = &params[self.w.clone()];
        let mut row0 = 0;
        for (bi, &(x, width)) in xs.iter().enumerate() {
            let gw = &mut grads[self.w.start + row0 * out..self.w.start + (row0 + width) * out];
            // dW_i[width x out] += x_i^T[width x n] dy[n x out]
            gemm(width, n, out, x, (1, width as isize), dy, (out as isize, 1), 1.0, gw, (out as isize, 1));
            if let Some(Some(dx)) = dxs.get_mut(bi) {
                let wi = &w[row0 * out..(row0 + width) * out];
                // dx_i[n x width] = dy[n x out] W_i^T[out x width]
                gemm(n, out, width, dy, (out as isize, 1), wi, (1, out as isize), 0.0, dx, (width as isize, 1));
            }
            row0 += width;
        }
    }
}

/// Products of layers with few outputs or few inputs (width not a
/// multiple of 8, which the AVX2 kernel of `gemm` leaves to the general
/// GEMM, whose packing of the whole `[n x inputs]` activation matrix then
/// costs more than the product): written as dot products over contiguous
/// rows, for single-block layers. The real-capture model's proposal
/// networks (`16 -> 1`, and a 10-wide grid encoding) and colour head
/// (`64 -> 3`) use them; the other models keep `forward`/`backward`.
impl Linear {
    /// [`Linear::forward`] of one input block `x` (`[n x inputs]`), one
    /// dot product per output (for few outputs).
    pub fn forward_dots(&self, params: &[f32], x: &[f32], n: usize, y: &mut [f32]) {
        let (k, out) = (self.inputs, self.outputs);
        let (w, b) = (&params[self.w.clone()], &params[self.b.clone()]);
        // The columns of W as contiguous rows.
        let wt: Vec<f32> = (0..out).flat_map(|o| (0..k).map(move |i| w[i * out + o])).collect();
        for (row, yr) in x[..n * k].chunks_exact(k).zip(y[..n * out].chunks_exact_mut(out)) {
            for ((yo, col), &bo) in yr.iter_mut().zip(wt.chunks_exact(k)).zip(b) {
                *yo = bo + dot(row, col);
            }
        }
    }

    /// The parameter gradients of [`Linear::forward_dots`] (`dW += x^T dy`,
    /// `db += sum(dy)`), accumulated into `grads` (for few outputs).
    pub fn backward_dots(&self, x: &[f32], dy: &[f32], n: usize, grads: &mut [f32]) {
        let (k, out) = (self.inputs, self.outputs);
        // dW^T, row o = sum_i dy[i][o] x_i: axpys over contiguous rows.
        let mut dwt = vec![0.0f32; out * k];
        let mut db = vec![0.0f32; out];
        for (row, dr) in x[..n * k].chunks_exact(k).zip(dy[..n * out].chunks_exact(out)) {
            for ((acc, &d), g) in dwt.chunks_exact_mut(k).zip(dr).zip(db.iter_mut()) {
                *g += d;
                for (a, &v) in acc.iter_mut().zip(row) {
                    *a += d * v;
                }
            }
        }
        let gw = &mut grads[self.w.clone()];
        for o in 0..out {
            for i in 0..k {
                gw[i * out + o] += dwt[o * k + i];
            }
        }
        for (g, d) in grads[self.b.clone()].iter_mut().zip(&db) {
            *g += d;
        }
    }

    /// `dx = dy W^T` (`[n x inputs]`, overwritten) of a single-block
    /// layer: the GEMM [`Linear::backward`] makes for it, without the
    /// parameter gradients (for a layer whose own are [`Linear::backward_dots`]).
    pub fn input_grad(&self, params: &[f32], dy: &[f32], n: usize, dx: &mut [f32]) {
        let (k, out) = (self.inputs, self.outputs);
        let w = &params[self.w.clone()];
        gemm(n, out, k, dy, (out as isize, 1), w, (1, out as isize), 0.0, dx, (k as isize, 1));
    }

    /// `dx = dy W^T` (`[n x inputs]`, overwritten) as one dot product per
    /// input over a contiguous row of `W` (for few inputs).
    pub fn input_grad_dots(&self, params: &[f32], dy: &[f32], n: usize, dx: &mut [f32]) {
        let (k, out) = (self.inputs, self.outputs);
        let w = &params[self.w.clone()];
        for (dr, xr) in dy[..n * out].chunks_exact(out).zip(dx[..n * k].chunks_exact_mut(k)) {
            for (x, wrow) in xr.iter_mut().zip(w.chunks_exact(out)) {
                *x = dot(dr, wrow);
            }
        }
    }
}

/// `a . b` over the shorter of the two, in eight running sums (which the
/// compiler keeps in one vector register; a single running sum would be a
/// chain of dependent adds).
#[inline]
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f32; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for l in 0..8 {
            acc[l] += ca[l] * cb[l];
        }
    }
    let tail = n / 8 * 8;
    let rest: f32 = a[tail..].iter().zip(&b[tail..]).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + rest
}

/// In-place ReLU.
pub fn relu(x: &mut [f32]) {
    for v in x {
        *v = v.max(0.0);
    }
}

/// `dy *= (y > 0)`: the ReLU backward, from the layer's output.
pub fn relu_backward(y: &[f32], dy: &mut [f32]) {
    // An unconditional select, not a conditional store: the compiler
    // vectorises it (a branch per value was 17% of a capture training step).
    for (d, &v) in dy.iter_mut().zip(y) {
        *d = if v <= 0.0 { 0.0 } else { *d };
    }
}

/// Numerically safe logistic function.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// `ln(1 + e^x)` without overflow.
#[inline]
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 { x } else { x.exp().ln_1p() }
}

/// The derivative of [`softplus`]: the logistic function.
#[inline]
pub fn softplus_grad(x: f32) -> f32 {
    sigmoid(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    /// f64 reference of `sum(y * g)` for the layer, used for finite differences.
    fn objective(l: &Linear, p: &[f64], xs: &[Vec<f64>], widths: &[usize], n: usize, g: &[f64]) -> f64 {
        let mut total = 0.0;
        for r in 0..n {
            for o in 0..l.outputs {
                let mut acc = p[l.b.start + o];
                let mut row0 = 0;
                for (x, &wd) in xs.iter().zip(widths) {
                    for i in 0..wd {
                        acc += x[r * wd + i] * p[l.w.start + (row0 + i) * l.outputs + o];
                    }
                    row0 += wd;
                }
                total += acc * g[r * l.outputs + o];
            }
        }
        total
    }

    #[test]
    fn linear_gradients_match_finite_differences() {
        let mut layout = ParamLayout::default();
        let _pad = layout.add("pad", 3);
        let l = Linear::new(&mut layout, "l", 5, 4);
        let widths = [3usize, 2];
        let n = 6;
        let mut rng = Rng::new(3);
        let params: Vec<f32> = (0..layout.len).map(|_| rng.normal()).collect();
        let x0: Vec<f32> = (0..n * 3).map(|_| rng.normal()).collect();
        let x1: Vec<f32> = (0..n * 2).map(|_| rng.normal()).collect();
        let g: Vec<f32> = (0..n * 4).map(|_| rng.normal()).collect();

        let mut y = vec![0.0; n * 4];
        l.forward(&params, &[(&x0, 3), (&x1, 2)], n, &mut y);
        let p64: Vec<f64> = params.iter().map(|&v| v as f64).collect();
        let xs64 = vec![x0.iter().map(|&v| v as f64).collect::<Vec<_>>(), x1.iter().map(|&v| v as f64).collect()];
        let g64: Vec<f64> = g.iter().map(|&v| v as f64).collect();
        // Forward agrees with the f64 reference.
        let f = objective(&l, &p64, &xs64, &widths, n, &g64);
        let fy: f64 = y.iter().zip(&g).map(|(a, b)| (*a as f64) * (*b as f64)).sum();
        assert!((f - fy).abs() < 1e-4, "{f} vs {fy}");

        let mut grads = vec![0.0f32; layout.len];
        let mut dx0 = vec![0.0f32; n * 3];
        let mut dx1 = vec![0.0f32; n * 2];
        l.backward(&params, &[(&x0, 3), (&x1, 2)], &g, n, &mut grads, &mut [Some(&mut dx0), Some(&mut dx1)]);
        assert!(grads[..3].iter().all(|&v| v == 0.0), "padding untouched");
        let h = 1e-6;
        for i in 3..layout.len {
            let mut pp = p64.clone();
            pp[i] += h;
            let fp = objective(&l, &pp, &xs64, &widths, n, &g64);
            pp[i] -= 2.0 * h;
            let fm = objective(&l, &pp, &xs64, &widths, n, &g64);
            let num = (fp - fm) / (2.0 * h);
            assert!((num - grads[i] as f64).abs() < 1e-3 * (1.0 + num.abs()), "param {i}: {num} vs {}", grads[i]);
        }
        for (bi, dx) in [dx0, dx1].iter().enumerate() {
            for i in 0..dx.len() {
                let mut xs = xs64.clone();
                xs[bi][i] += h;
                let fp = objective(&l, &p64, &xs, &widths, n, &g64);
                xs[bi][i] -= 2.0 * h;
                let fm = objective(&l, &p64, &xs, &widths, n, &g64);
                let num = (fp - fm) / (2.0 * h);
                assert!((num - dx[i] as f64).abs() < 1e-3 * (1.0 + num.abs()), "x{bi}[{i}]");
            }
        }
    }

    /// The dot-product forms agree with `forward` and `backward` (GEMM):
    /// same outputs, parameter and input gradients, up to rounding.
    #[test]
    fn dot_product_forms_match_the_gemm_forms() {
        for (inputs, outputs) in [(16usize, 1usize), (64, 3), (10, 16), (5, 7)] {
            let mut layout = ParamLayout::default();
            let _pad = layout.add("pad", 2);
            let l = Linear::new(&mut layout, "l", inputs, outputs);
            let n = 13;
            let mut rng = Rng::new(inputs as u64);
            let params: Vec<f32> = (0..layout.len).map(|_| rng.normal()).collect();
            let x: Vec<f32> = (0..n * inputs).map(|_| rng.normal()).collect();
            let dy: Vec<f32> = (0..n * outputs).map(|_| rng.normal()).collect();
            let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(p, q)| (p - q).abs() < 1e-4 * (1.0 + q.abs()));
            let (mut y, mut want) = (vec![0.0; n * outputs], vec![0.0; n * outputs]);
            l.forward_dots(&params, &x, n, &mut y);
            l.forward(&params, &[(&x, inputs)], n, &mut want);
            assert!(close(&y, &want), "{inputs}->{outputs}: {y:?} vs {want:?}");
            let (mut g, mut gw) = (vec![0.5f32; layout.len], vec![0.5f32; layout.len]);
            let (mut dx, mut dxw) = (vec![9.0; n * inputs], vec![0.0; n * inputs]);
            l.backward_dots(&x, &dy, n, &mut g);
            l.input_grad_dots(&params, &dy, n, &mut dx);
            let mut dx_gemm = vec![9.0; n * inputs];
            l.input_grad(&params, &dy, n, &mut dx_gemm);
            assert!(close(&dx_gemm, &dx), "{inputs}->{outputs}: input gradients by GEMM");
            l.backward(&params, &[(&x, inputs)], &dy, n, &mut gw, &mut [Some(&mut dxw)]);
            assert!(close(&g, &gw), "{inputs}->{outputs}: parameter gradients");
            assert!(close(&dx, &dxw), "{inputs}->{outputs}: input gradients");
            assert_eq!(g[..2], [0.5, 0.5], "padding untouched");
        }
    }

    #[test]
    fn activations_and_derivatives() {
        for &x in &[-100.0f32, -5.0, -0.3, 0.0, 0.7, 4.0, 50.0, 1e30] {
            let s = sigmoid(x);
            assert!((0.0..=1.0).contains(&s) && s.is_finite());
            let sp = softplus(x);
            assert!(sp >= 0.0 && sp.is_finite());
            // finite-difference derivative of softplus, in f64
            if x.abs() < 60.0 {
                let xf = x as f64;
                let f = |v: f64| (1.0 + v.exp()).ln();
                let num = (f(xf + 1e-6) - f(xf - 1e-6)) / 2e-6;
                assert!((num - softplus_grad(x) as f64).abs() < 1e-5, "{x}");
            }
        }
        let mut y = vec![-1.0, 0.0, 2.0];
        relu(&mut y);
        assert_eq!(y, vec![0.0, 0.0, 2.0]);
        let mut d = vec![1.0, 1.0, 1.0];
        relu_backward(&y, &mut d);
        assert_eq!(d, vec![0.0, 0.0, 1.0]);
    }
}
