//! Volume rendering by quadrature (Max 1995, as used by NeRF), for one ray
//! at a time, with its backward pass.
//!
//! For samples `i = 0..n` with density `sigma_i >= 0`, interval length
//! `delta_i >= 0`, colour `c_i` and distance `t_i`:
//! `alpha_i = 1 - exp(-sigma_i delta_i)`,
//! `T_i = prod_{j<i} (1 - alpha_j) = exp(-sum_{j<i} sigma_j delta_j)`,
//! `w_i = T_i alpha_i`, colour `C = sum w_i c_i + T_n bg`,
//! depth `D = sum w_i t_i`, opacity `A = sum w_i = 1 - T_n`.
//!
//! Extreme inputs are safe: `sigma * delta` is taken as 0 when `delta` is 0
//! (even for infinite density), and every quantity stays finite for finite or
//! infinite densities.

/// Optical depth of one interval, safe for infinite density and zero length.
#[inline]
pub fn optical_depth(sigma: f32, delta: f32) -> f32 {
    if delta <= 0.0 || sigma <= 0.0 || sigma.is_nan() { 0.0 } else { sigma * delta }
}

/// What compositing one ray produced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Composite {
    pub rgb: [f32; 3],
    pub depth: f32,
    /// Accumulated opacity `1 - T_n`.
    pub opacity: f32,
    /// How many samples were composited before transmittance fell below the
    /// early-termination threshold (all of them when it never did).
    pub used: usize,
}

/// Composites `sigma.len()` samples; `rgb` is `[n x 3]`. Writes the weights
/// into `weights` (needed by the backward pass and by hierarchical sampling).
/// Stops early once transmittance drops below `min_transmittance` (pass 0 to
/// composite every sample); the weights of skipped samples are set to zero.
pub fn composite(
    sigma: &[f32],
    rgb: &[f32],
    t: &[f32],
    delta: &[f32],
    background: [f32; 3],
    min_transmittance: f32,
    weights: &mut [f32],
) -> Composite {
    let n = sigma.len();
    let mut out = Composite { used: n, ..Default::default() };
    let mut tau = 0.0f32; // optical depth so far
    let mut trans = 1.0f32;
    for i in 0..n {
        if trans < min_transmittance {
            out.used = i;
            weights[i..n].fill(0.0);
            break;
        }
        tau += optical_depth(sigma[i], delta[i]);
        let next = (-tau).exp();
        let w = trans - next;
        weights[i] = w;
        for c in 0..3 {
            out.rgb[c] += w * rgb[3 * i + c];
        }
        out.depth += w * t[i];
        trans = next;
    }
    out.opacity = 1.0 - trans;
    for c in 0..3 {
        out.rgb[c] += trans * background[c];
    }
    out
}

/// Backward of [`composite`] (over the samples it used): given `dl_drgb`
/// (dL/dC) and `dl_ddepth`, writes dL/dsigma_i and dL/dc_i.
///
/// `dC/dsigma_i = delta_i (T_{i+1} c_i - sum_{j>i} w_j c_j - T_n bg)`, and
/// likewise for depth with `t_i` in place of `c_i` and no background.
#[allow(clippy::too_many_arguments)]
pub fn composite_backward(
    sigma: &[f32],
    rgb: &[f32],
    t: &[f32],
    delta: &[f32],
    weights: &[f32],
    background: [f32; 3],
    used: usize,
    dl_drgb: [f32; 3],
    dl_ddepth: f32,
    dsigma: &mut [f32],
    drgb: &mut [f32],
) {
    let n = sigma.len();
    let used = used.min(n);
    // Recompute T_{i+1} exactly from optical depths rather than from the
    // differences above (which lose precision when T is tiny).
    let mut tau = 0.0f32;
    for i in 0..used {
        tau += optical_depth(sigma[i], delta[i]);
        dsigma[i] = (-tau).exp(); // T_{i+1}, temporarily
    }
    let trans_end = if used > 0 { dsigma[used - 1] } else { 1.0 };
    // suffix = sum_{j>i} w_j (g.c_j + gd t_j) + T_n g.bg
    let gbg = dl_drgb[0] * background[0] + dl_drgb[1] * background[1] + dl_drgb[2] * background[2];
    let mut suffix = trans_end * gbg;
    for i in (0..used).rev() {
        let c = &rgb[3 * i..3 * i + 3];
        let gc = dl_drgb[0] * c[0] + dl_drgb[1] * c[1] + dl_drgb[2] * c[2] + dl_ddepth * t[i];
        let t_next = dsigma[i];
        let d = if delta[i] > 0.0 { delta[i] } else { 0.0 };
        dsigma[i] = d * (t_next * gc - suffix);
        suffix += weights[i] * gc;
        for k in 0..3 {
            drgb[3 * i + k] = weights[i] * dl_drgb[k];
        }
    }
    for i in used..n {
        dsigma[i] = 0.0;
        drgb[3 * i..3 * i + 3].fill(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference(sigma: &[f64], rgb: &[f64], t: &[f64], delta: &[f64], bg: [f64; 3]) -> ([f64; 3], f64) {
        let mut trans = 1.0;
        let mut c = [0.0; 3];
        let mut d = 0.0;
        for i in 0..sigma.len() {
            let a = 1.0 - (-sigma[i] * delta[i]).exp();
            let w = trans * a;
            for k in 0..3 {
                c[k] += w * rgb[3 * i + k];
            }
            d += w * t[i];
            trans *= 1.0 - a;
        }
        for k in 0..3 {
            c[k] += trans * bg[k];
        }
        (c, d)
    }

    #[test]
    fn hand_computed_two_samples() {
        // sigma delta = ln 2 for both: alpha = 1/2, weights 1/2 and 1/4, T_n = 1/4.
        let l2 = std::f32::consts::LN_2;
        let sigma = [l2, 2.0 * l2];
        let delta = [1.0, 0.5];
        let rgb = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let t = [1.0, 2.0];
        let mut w = [0.0; 2];
        let c = composite(&sigma, &rgb, &t, &delta, [0.0, 0.0, 1.0], 0.0, &mut w);
        assert!((w[0] - 0.5).abs() < 1e-6 && (w[1] - 0.25).abs() < 1e-6);
        assert!((c.rgb[0] - 0.5).abs() < 1e-6);
        assert!((c.rgb[1] - 0.25).abs() < 1e-6);
        assert!((c.rgb[2] - 0.25).abs() < 1e-6);
        assert!((c.depth - 1.0).abs() < 1e-6); // 0.5*1 + 0.25*2
        assert!((c.opacity - 0.75).abs() < 1e-6);
    }

    #[test]
    fn empty_ray_shows_background_and_opaque_ray_hides_it() {
        let mut w = [0.0; 3];
        let c = composite(&[0.0; 3], &[0.5; 9], &[1.0, 2.0, 3.0], &[1.0; 3], [0.2, 0.3, 0.4], 0.0, &mut w);
        assert_eq!(c.rgb, [0.2, 0.3, 0.4]);
        assert_eq!(c.opacity, 0.0);
        let c = composite(&[f32::INFINITY; 3], &[0.5; 9], &[1.0, 2.0, 3.0], &[1.0; 3], [0.2, 0.3, 0.4], 0.0, &mut w);
        assert_eq!(c.rgb, [0.5; 3]);
        assert_eq!(w, [1.0, 0.0, 0.0]);
        assert_eq!(c.opacity, 1.0);
    }

    #[test]
    fn backward_matches_finite_differences_in_f64() {
        let sigma = [0.3f32, 1.7, 0.05, 2.5, 0.9];
        let rgb: Vec<f32> = (0..15).map(|i| ((i * 7 % 10) as f32) / 10.0).collect();
        let t = [1.0f32, 1.3, 1.6, 2.0, 2.2];
        let delta = [0.3f32, 0.3, 0.4, 0.2, 0.5];
        let bg = [0.9f32, 0.1, 0.5];
        let g = [0.7f32, -1.1, 0.4];
        let gd = 0.3f32;
        let mut w = [0.0; 5];
        let c = composite(&sigma, &rgb, &t, &delta, bg, 0.0, &mut w);
        let mut ds = [0.0; 5];
        let mut dc = [0.0; 15];
        composite_backward(&sigma, &rgb, &t, &delta, &w, bg, c.used, g, gd, &mut ds, &mut dc);
        let f64v = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
        let (s64, c64, t64, d64) = (f64v(&sigma), f64v(&rgb), f64v(&t), f64v(&delta));
        let bg64 = [bg[0] as f64, bg[1] as f64, bg[2] as f64];
        let obj = |s: &[f64], c: &[f64]| {
            let (col, dep) = reference(s, c, &t64, &d64, bg64);
            (0..3).map(|k| col[k] * g[k] as f64).sum::<f64>() + dep * gd as f64
        };
        // forward agrees with the f64 reference
        let (rc, rd) = reference(&s64, &c64, &t64, &d64, bg64);
        for k in 0..3 {
            assert!((rc[k] - c.rgb[k] as f64).abs() < 1e-6);
        }
        assert!((rd - c.depth as f64).abs() < 1e-6);
        let h = 1e-7;
        for i in 0..5 {
            let mut a = s64.clone();
            a[i] += h;
            let mut b = s64.clone();
            b[i] -= h;
            let num = (obj(&a, &c64) - obj(&b, &c64)) / (2.0 * h);
            assert!((num - ds[i] as f64).abs() < 1e-5, "sigma {i}: {num} vs {}", ds[i]);
        }
        for i in 0..15 {
            let mut a = c64.clone();
            a[i] += h;
            let mut b = c64.clone();
            b[i] -= h;
            let num = (obj(&s64, &a) - obj(&s64, &b)) / (2.0 * h);
            assert!((num - dc[i] as f64).abs() < 1e-5, "rgb {i}");
        }
    }

    #[test]
    fn early_termination_changes_colour_by_less_than_threshold() {
        let n = 64;
        let sigma: Vec<f32> = (0..n).map(|i| if i > 10 { 30.0 } else { 0.1 }).collect();
        let rgb: Vec<f32> = (0..3 * n).map(|i| (i % 5) as f32 / 4.0).collect();
        let t: Vec<f32> = (0..n).map(|i| 2.0 + i as f32 * 0.05).collect();
        let delta = vec![0.05f32; n];
        let mut w = vec![0.0; n];
        let full = composite(&sigma, &rgb, &t, &delta, [1.0; 3], 0.0, &mut w);
        let eps = 1e-4;
        let cut = composite(&sigma, &rgb, &t, &delta, [1.0; 3], eps, &mut w);
        assert!(cut.used < n, "terminated early");
        for k in 0..3 {
            assert!((full.rgb[k] - cut.rgb[k]).abs() <= eps, "{:?} {:?}", full.rgb, cut.rgb);
        }
    }
}
