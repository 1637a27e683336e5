//! The structural dissimilarity of a drawn view against a photo, and its
//! gradient with respect to the drawn view: the D-SSIM term of 3DGS's loss.
//! SSIM as `metrics` scores it (an 11x11 Gaussian window of sigma 1.5,
//! 'valid' boundaries, each channel apart); a photo's NaN values (no loss)
//! take the drawn value there, held fixed.

use rayon::prelude::*;

use crate::engine::metrics::{self, SSIM_WINDOW};

const C1: f32 = metrics::C1 as f32;
const C2: f32 = metrics::C2 as f32;

/// The metric's window, in f32.
fn window() -> [f32; SSIM_WINDOW] {
    metrics::gaussian_kernel().map(|v| v as f32)
}

/// `a` (`w x h`) correlated with the window both ways, 'valid': `(w-10) x (h-10)`.
fn blur(a: &[f32], w: usize, h: usize, g: &[f32; SSIM_WINDOW]) -> Vec<f32> {
    let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut rows = vec![0.0f32; ow * h];
    rows.par_chunks_mut(ow).enumerate().for_each(|(j, row)| {
        let src = &a[j * w..(j + 1) * w];
        for (i, o) in row.iter_mut().enumerate() {
            *o = g.iter().zip(&src[i..i + SSIM_WINDOW]).map(|(g, v)| g * v).sum();
        }
    });
    let mut out = vec![0.0f32; ow * oh];
    out.par_chunks_mut(ow).enumerate().for_each(|(j, row)| {
        for (k, gk) in g.iter().enumerate() {
            for (o, v) in row.iter_mut().zip(&rows[(j + k) * ow..(j + k + 1) * ow]) {
                *o += gk * v;
            }
        }
    });
    out
}

/// The adjoint of `blur`: `d` (`(w-10) x (h-10)`) spread back onto `w x h`
/// (each value gathering what the window took from it).
fn blur_adjoint(d: &[f32], w: usize, h: usize, g: &[f32; SSIM_WINDOW]) -> Vec<f32> {
    let (ow, oh) = (w + 1 - SSIM_WINDOW, h + 1 - SSIM_WINDOW);
    let mut rows = vec![0.0f32; ow * h];
    rows.par_chunks_mut(ow).enumerate().for_each(|(r, row)| {
        // Output row j took input row r with weight g[r - j].
        for j in r.saturating_sub(SSIM_WINDOW - 1)..=r.min(oh - 1) {
            let gk = g[r - j];
            for (o, v) in row.iter_mut().zip(&d[j * ow..(j + 1) * ow]) {
                *o += gk * v;
            }
        }
    });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(j, row)| {
        let src = &rows[j * ow..(j + 1) * ow];
        for (q, o) in row.iter_mut().enumerate() {
            let lo = q.saturating_sub(SSIM_WINDOW - 1);
            *o = (lo..=q.min(ow - 1)).map(|i| g[q - i] * src[i]).sum();
        }
    });
    out
}

/// The mean SSIM of `x` against `y` (both `[h x w x 3]`) over every map
/// value of the three channels, and its gradient with respect to `x`
/// (`None` for an image under 11 pixels either way).
pub fn ssim_and_gradient(x: &[f32], y: &[f32], w: usize, h: usize) -> Option<(f64, Vec<f32>)> {
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return None;
    }
    let g = window();
    let n = (w + 1 - SSIM_WINDOW) * (h + 1 - SSIM_WINDOW);
    let scale = 1.0 / (3 * n) as f32;
    let mut grad = vec![0.0f32; w * h * 3];
    let mut total = 0.0f64;
    for c in 0..3 {
        let xs: Vec<f32> = (0..w * h).map(|p| x[3 * p + c]).collect();
        let ys: Vec<f32> =
            (0..w * h).map(|p| if y[3 * p + c].is_nan() { x[3 * p + c] } else { y[3 * p + c] }).collect();
        let sq = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| a * b).collect::<Vec<f32>>();
        let (mx, my) = (blur(&xs, w, h, &g), blur(&ys, w, h, &g));
        let (exx, eyy, exy) =
            (blur(&sq(&xs, &xs), w, h, &g), blur(&sq(&ys, &ys), w, h, &g), blur(&sq(&xs, &ys), w, h, &g));
        let (mut d_mu, mut d_exx, mut d_exy) = (vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]);
        for p in 0..n {
            let (ux, uy) = (mx[p], my[p]);
            let a1 = 2.0 * ux * uy + C1;
            let a2 = 2.0 * (exy[p] - ux * uy) + C2;
            let b1 = ux * ux + uy * uy + C1;
            let b2 = exx[p] - ux * ux + eyy[p] - uy * uy + C2;
            let s = a1 * a2 / (b1 * b2);
            total += s as f64;
            d_mu[p] = scale * s * (2.0 * uy / a1 - 2.0 * uy / a2 - 2.0 * ux / b1 + 2.0 * ux / b2);
            d_exx[p] = -scale * s / b2;
            d_exy[p] = scale * s * 2.0 / a2;
        }
        let (gm, gxx, gxy) =
            (blur_adjoint(&d_mu, w, h, &g), blur_adjoint(&d_exx, w, h, &g), blur_adjoint(&d_exy, w, h, &g));
        for p in 0..w * h {
            grad[3 * p + c] = gm[p] + 2.0 * xs[p] * gxx[p] + ys[p] * gxy[p];
        }
    }
    Some((total / (3 * n) as f64, grad))
}

/// SSIM in f64 straight from its definition, window by window (a
/// photo's NaN value takes the drawn one): the tests' reference.
#[cfg(test)]
pub(crate) fn ssim_f64(x: &[f64], y: &[f64], w: usize, h: usize) -> f64 {
    let g = metrics::gaussian_kernel();
    let (c1, c2) = (metrics::C1, metrics::C2);
    let mut total = 0.0;
    let mut n = 0;
    for c in 0..3 {
        for j in 0..=h - SSIM_WINDOW {
            for i in 0..=w - SSIM_WINDOW {
                let (mut ux, mut uy, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for b in 0..SSIM_WINDOW {
                    for a in 0..SSIM_WINDOW {
                        let k = 3 * ((j + b) * w + i + a) + c;
                        let wt = g[a] * g[b];
                        let (xv, yv) = (x[k], if y[k].is_nan() { x[k] } else { y[k] });
                        ux += wt * xv;
                        uy += wt * yv;
                        xx += wt * xv * xv;
                        yy += wt * yv * yv;
                        xy += wt * xv * yv;
                    }
                }
                let (sx, sy, sxy) = (xx - ux * ux, yy - uy * uy, xy - ux * uy);
                total += (2.0 * ux * uy + c1) * (2.0 * sxy + c2) / ((ux * ux + uy * uy + c1) * (sx + sy + c2));
                n += 1;
            }
        }
    }
    total / n as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    fn images(w: usize, h: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let mut rng = Rng::new(seed);
        let y: Vec<f32> = (0..w * h * 3).map(|_| rng.f32()).collect();
        let x = y.iter().map(|v| (v + 0.3 * (rng.f32() - 0.5)).clamp(0.0, 1.0)).collect();
        (x, y)
    }

    #[test]
    fn the_mean_is_the_definitions_and_the_metrics() {
        let (w, h) = (17, 14);
        let (x, y) = images(w, h, 3);
        let (s, _) = ssim_and_gradient(&x, &y, w, h).unwrap();
        let to64 = |a: &[f32]| a.iter().map(|&v| v as f64).collect::<Vec<f64>>();
        let want = ssim_f64(&to64(&x), &to64(&y), w, h);
        assert!((s - want).abs() < 1e-5, "{s} against {want}");
        let score = metrics::ssim(&x, &y, w, h, 3).unwrap();
        assert!((s - score).abs() < 1e-4, "{s} against the metric's {score}");
        let (same, _) = ssim_and_gradient(&y, &y, w, h).unwrap();
        assert!((same - 1.0).abs() < 1e-5, "an image against itself: {same}");
    }

    #[test]
    fn the_gradient_is_the_definitions_by_central_differences() {
        let (w, h) = (15, 13);
        let (x, mut y) = images(w, h, 9);
        y[3 * (4 * w + 5) + 1] = f32::NAN;
        let (_, grad) = ssim_and_gradient(&x, &y, w, h).unwrap();
        let (x64, y64): (Vec<f64>, Vec<f64>) =
            (x.iter().map(|&v| v as f64).collect(), y.iter().map(|&v| v as f64).collect());
        let mut rng = Rng::new(1);
        // Every value of a corner, an edge and the middle, and random others.
        let picks: Vec<usize> = [0, 3 * (w - 1) + 2, 3 * (6 * w + 7), 3 * (4 * w + 5) + 1]
            .into_iter()
            .chain((0..40).map(|_| rng.below((w * h * 3) as u64) as usize))
            .collect();
        for k in picks {
            let h_ = 1e-4;
            let at = |d: f64| {
                let mut p = x64.clone();
                p[k] += d;
                // A NaN photo value follows the drawn one: held fixed at x.
                let mut q = y64.clone();
                if q[k].is_nan() {
                    q[k] = x64[k];
                }
                ssim_f64(&p, &q, w, h)
            };
            let fd = (at(h_) - at(-h_)) / (2.0 * h_);
            let an = grad[k] as f64;
            assert!((an - fd).abs() <= 2e-3 * fd.abs().max(an.abs()) + 2e-6, "[{k}]: analytic {an}, differences {fd}");
        }
    }
}
