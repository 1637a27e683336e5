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
//!
//! [`composite`] and [the forward] serve every model: with
//! [`CompositeOptions`] off they are the plain quadrature above; a model of
//! real photographs turns on an opaque last interval, and a regulariser
//! (`regularize`) adds a gradient on the weights themselves
//! (design `real-captures.md` 2.5).

use super::InputError;

/// Optical depth of one interval, safe for infinite density and zero length.
#[inline]
pub fn optical_depth(sigma: f32, delta: f32) -> f32 {
    if delta <= 0.0 || sigma <= 0.0 || sigma.is_nan() { 0.0 } else { sigma * delta }
}

/// The transmittance along a ray, interval by interval: the weights of
/// [`composite`] and [`composite`], which rendering in rounds
/// (`render::rounds`, and the capture model's proposal levels, `models::capture::levels`)
/// also takes, resuming where a round ended.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transmittance {
    /// Optical depth so far.
    tau: f32,
    trans: f32,
}

impl Default for Transmittance {
    fn default() -> Self {
        Self { tau: 0.0, trans: 1.0 }
    }
}

impl Transmittance {
    /// The transmittance before the next interval.
    pub fn value(&self) -> f32 {
        self.trans
    }

    /// The weight of the next interval (density `sigma`, length `delta`);
    /// an `opaque` one takes all the transmittance left.
    #[inline]
    pub fn step(&mut self, sigma: f32, delta: f32, opaque: bool) -> f32 {
        self.tau += optical_depth(sigma, delta);
        let next = if opaque { 0.0 } else { (-self.tau).exp() };
        let w = self.trans - next;
        self.trans = next;
        w
    }
}

/// Records `t` as a ray's median depth (`Composite::median`) when its
/// transmittance, after the sample at `t`, has fallen to one half for the
/// first time (`median` is 0 until then).
pub fn mark_median(median: &mut f32, transmittance: f32, t: f32) {
    if *median == 0.0 && transmittance <= 0.5 {
        *median = t;
    }
}

/// What compositing one ray produced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Composite {
    pub rgb: [f32; 3],
    pub depth: f32,
    /// Accumulated opacity `1 - T_n`.
    pub opacity: f32,
    /// The distance of the sample at which the opacity reaches one half
    /// (RadSplat's median depth: on a surface where the expected depth of
    /// a ray across an edge lies between two); 0 when it never does.
    pub median: f32,
    /// How many samples were composited before transmittance fell below the
    /// early-termination threshold (all of them when it never did).
    pub used: usize,
}

/// How [`composite`] composites one ray.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CompositeOptions {
    /// Colour seen through whatever the ray leaves transparent.
    pub background: [f32; 3],
    /// Transmittance below which compositing stops (0: composite every
    /// sample); the weights of the samples after that are zero.
    pub min_transmittance: f32,
    /// The last interval absorbs all the light that reaches it (`alpha = 1`,
    /// whatever its density), so nothing shows the background (mip-NeRF
    /// 360's `opaque_background`: photographs have no see-through pixels).
    /// Its density then gets no gradient. When compositing stops early the
    /// last interval is never reached and the background shows as usual
    /// (by less than `min_transmittance`).
    pub opaque_last: bool,
}

/// One ray's samples as the compositor reads them, their lengths checked:
/// `n` densities, `[n x 3]` colours, `n` distances `t` and `n` interval
/// lengths `delta`.
#[derive(Clone, Copy, Debug)]
pub struct RaySamples<'a> {
    sigma: &'a [f32],
    rgb: &'a [f32],
    t: &'a [f32],
    delta: &'a [f32],
}

impl<'a> RaySamples<'a> {
    /// The samples, or which slice does not fit `sigma`'s length.
    pub fn new(sigma: &'a [f32], rgb: &'a [f32], t: &'a [f32], delta: &'a [f32]) -> Result<Self, InputError> {
        let n = sigma.len();
        InputError::check_len("rgb", 3 * n, rgb.len())?;
        InputError::check_len("t", n, t.len())?;
        InputError::check_len("delta", n, delta.len())?;
        Ok(Self { sigma, rgb, t, delta })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.sigma.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sigma.is_empty()
    }
}

/// The gradient arriving at one ray's composite.
#[derive(Clone, Copy, Debug, Default)]
pub struct Upstream<'a> {
    /// dL/dC, the gradient on the ray's colour.
    pub rgb: [f32; 3],
    /// dL/dD, the gradient on its depth.
    pub depth: f32,
    /// dL/dw_i, `[n]`: a loss on the weights themselves (a regulariser such
    /// as `regularize::distortion`, or the interlevel loss on a proposal's
    /// weights). `None` is the same as all zeros.
    pub weights: Option<&'a [f32]>,
}

/// Composites `s` as `opts` say, writing the
/// weights `[n]` into `weights`. Fails only when `weights` does not hold
/// one value per sample.
pub fn composite(s: RaySamples<'_>, opts: &CompositeOptions, weights: &mut [f32]) -> Result<Composite, InputError> {
    let n = s.len();
    InputError::check_len("weights", n, weights.len())?;
    let mut out = Composite { used: n, ..Default::default() };
    let mut along = Transmittance::default();
    for i in 0..n {
        if along.value() < opts.min_transmittance {
            out.used = i;
            weights[i..n].fill(0.0);
            break;
        }
        let w = along.step(s.sigma[i], s.delta[i], opts.opaque_last && i + 1 == n);
        weights[i] = w;
        for c in 0..3 {
            out.rgb[c] += w * s.rgb[3 * i + c];
        }
        out.depth += w * s.t[i];
        mark_median(&mut out.median, along.value(), s.t[i]);
    }
    let trans = along.value();
    out.opacity = 1.0 - trans;
    for c in 0..3 {
        out.rgb[c] += trans * opts.background[c];
    }
    Ok(out)
}

/// Backward of [`composite`] over the `used` samples it composited:
/// given the [`Upstream`] gradient, writes dL/dsigma_i into `dsigma` (`[n]`)
/// and dL/dc_i into `drgb` (`[n x 3]`); samples after `used` get zeros.
///
/// With `g_i = dL/dw_i` (colour and depth through `w_i`, plus
/// `upstream.weights`), `dL/dsigma_i = delta_i (T_{i+1} g_i - sum_{j>i} w_j
/// g_j - T_n g.bg)`. An opaque last interval has `T_n = 0` and its density
/// no gradient: `w_{n-1} = T_{n-1}` does not depend on it.
pub fn composite_backward(
    s: RaySamples<'_>,
    weights: &[f32],
    opts: &CompositeOptions,
    used: usize,
    upstream: Upstream<'_>,
    dsigma: &mut [f32],
    drgb: &mut [f32],
) -> Result<(), InputError> {
    let n = s.len();
    InputError::check_len("weights", n, weights.len())?;
    InputError::check_len("dsigma", n, dsigma.len())?;
    InputError::check_len("drgb", 3 * n, drgb.len())?;
    if let Some(extra) = upstream.weights {
        InputError::check_len("upstream weights", n, extra.len())?;
    }
    let used = used.min(n);
    let opaque = opts.opaque_last && used == n && n > 0;
    // T_{i+1} exactly from optical depths rather than from the weights'
    // differences (which lose precision when T is tiny).
    let mut tau = 0.0f32;
    for i in 0..used {
        tau += optical_depth(s.sigma[i], s.delta[i]);
        dsigma[i] = (-tau).exp(); // T_{i+1}, temporarily
    }
    if opaque {
        dsigma[n - 1] = 0.0; // T_n: nothing passes the opaque end
    }
    let trans_end = if used > 0 { dsigma[used - 1] } else { 1.0 };
    let (g, bg) = (upstream.rgb, opts.background);
    // suffix = sum_{j>i} w_j g_j + T_n g.bg
    let gbg = g[0] * bg[0] + g[1] * bg[1] + g[2] * bg[2];
    let mut suffix = trans_end * gbg;
    for i in (0..used).rev() {
        let c = &s.rgb[3 * i..3 * i + 3];
        let gc = g[0] * c[0] + g[1] * c[1] + g[2] * c[2] + upstream.depth * s.t[i];
        let gc = match upstream.weights {
            Some(extra) => gc + extra[i],
            None => gc,
        };
        let t_next = dsigma[i];
        let d = if s.delta[i] > 0.0 { s.delta[i] } else { 0.0 };
        dsigma[i] = if opaque && i + 1 == n { 0.0 } else { d * (t_next * gc - suffix) };
        suffix += weights[i] * gc;
        for k in 0..3 {
            drgb[3 * i + k] = weights[i] * g[k];
        }
    }
    for i in used..n {
        dsigma[i] = 0.0;
        drgb[3 * i..3 * i + 3].fill(0.0);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`composite`] with a background and an early stop only.
    fn plain(
        sigma: &[f32],
        rgb: &[f32],
        t: &[f32],
        delta: &[f32],
        bg: [f32; 3],
        min_t: f32,
        w: &mut [f32],
    ) -> Composite {
        let s = RaySamples::new(sigma, rgb, t, delta).unwrap();
        let opts = CompositeOptions { background: bg, min_transmittance: min_t, opaque_last: false };
        composite(s, &opts, w).unwrap()
    }

    /// [`composite_backward`] of [`plain`], for colour and depth gradients.
    #[allow(clippy::too_many_arguments)]
    fn plain_backward(
        (sigma, rgb, t, delta): (&[f32], &[f32], &[f32], &[f32]),
        w: &[f32],
        bg: [f32; 3],
        used: usize,
        g: [f32; 3],
        gd: f32,
        ds: &mut [f32],
        dc: &mut [f32],
    ) {
        let s = RaySamples::new(sigma, rgb, t, delta).unwrap();
        let opts = CompositeOptions { background: bg, min_transmittance: 0.0, opaque_last: false };
        let up = Upstream { rgb: g, depth: gd, weights: None };
        composite_backward(s, w, &opts, used, up, ds, dc).unwrap();
    }

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
        let c = plain(&sigma, &rgb, &t, &delta, [0.0, 0.0, 1.0], 0.0, &mut w);
        assert!((w[0] - 0.5).abs() < 1e-6 && (w[1] - 0.25).abs() < 1e-6);
        assert!((c.rgb[0] - 0.5).abs() < 1e-6);
        assert!((c.rgb[1] - 0.25).abs() < 1e-6);
        assert!((c.rgb[2] - 0.25).abs() < 1e-6);
        assert!((c.depth - 1.0).abs() < 1e-6); // 0.5*1 + 0.25*2
        assert!((c.opacity - 0.75).abs() < 1e-6);
    }

    #[test]
    fn the_median_is_the_sample_where_the_opacity_reaches_one_half() {
        // alpha = 0.2 a sample: T = 0.8, 0.64, 0.512, 0.4096, ...
        let sd = -(0.8f32).ln();
        let t = [1.0, 2.0, 3.0, 4.0, 5.0];
        let mut w = [0.0; 5];
        let c = plain(&[sd; 5], &[0.5; 15], &t, &[1.0; 5], [0.0; 3], 0.0, &mut w);
        assert_eq!(c.median, 4.0);
        // The expected depth of the same ray lies before it.
        assert!(c.depth / c.opacity < 3.0, "{c:?}");
        // Three samples never reach one half.
        let c = plain(&[sd; 3], &[0.5; 9], &t[..3], &[1.0; 3], [0.0; 3], 0.0, &mut w[..3]);
        assert_eq!((c.median, c.opacity > 0.48), (0.0, true), "{c:?}");
    }

    #[test]
    fn empty_ray_shows_background_and_opaque_ray_hides_it() {
        let mut w = [0.0; 3];
        let c = plain(&[0.0; 3], &[0.5; 9], &[1.0, 2.0, 3.0], &[1.0; 3], [0.2, 0.3, 0.4], 0.0, &mut w);
        assert_eq!(c.rgb, [0.2, 0.3, 0.4]);
        assert_eq!(c.opacity, 0.0);
        let c = plain(&[f32::INFINITY; 3], &[0.5; 9], &[1.0, 2.0, 3.0], &[1.0; 3], [0.2, 0.3, 0.4], 0.0, &mut w);
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
        let c = plain(&sigma, &rgb, &t, &delta, bg, 0.0, &mut w);
        let mut ds = [0.0; 5];
        let mut dc = [0.0; 15];
        plain_backward((&sigma, &rgb, &t, &delta), &w, bg, c.used, g, gd, &mut ds, &mut dc);
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
        let full = plain(&sigma, &rgb, &t, &delta, [1.0; 3], 0.0, &mut w);
        let eps = 1e-4;
        let cut = plain(&sigma, &rgb, &t, &delta, [1.0; 3], eps, &mut w);
        assert!(cut.used < n, "terminated early");
        for k in 0..3 {
            assert!((full.rgb[k] - cut.rgb[k]).abs() <= eps, "{:?} {:?}", full.rgb, cut.rgb);
        }
    }

    /// f64 reference of [`composite`] (no early stop): colour, depth and
    /// weights; with `opaque_last` the last interval has `alpha = 1`.
    fn reference_with(
        sigma: &[f64],
        rgb: &[f64],
        t: &[f64],
        delta: &[f64],
        bg: [f64; 3],
        opaque_last: bool,
    ) -> ([f64; 3], f64, Vec<f64>) {
        let n = sigma.len();
        let mut trans = 1.0;
        let (mut c, mut d, mut w) = ([0.0; 3], 0.0, vec![0.0; n]);
        for i in 0..n {
            let a = if opaque_last && i + 1 == n { 1.0 } else { 1.0 - (-sigma[i] * delta[i]).exp() };
            w[i] = trans * a;
            for k in 0..3 {
                c[k] += w[i] * rgb[3 * i + k];
            }
            d += w[i] * t[i];
            trans *= 1.0 - a;
        }
        for k in 0..3 {
            c[k] += trans * bg[k];
        }
        (c, d, w)
    }

    fn f64v(v: &[f32]) -> Vec<f64> {
        v.iter().map(|&x| x as f64).collect()
    }

    /// Checks [the forward] against central differences of the
    /// f64 reference for `L = g.C + gd D + sum_i e_i w_i`.
    fn check_backward_with(opaque_last: bool, extra: Option<&[f32]>) {
        let sigma = [0.3f32, 1.7, 0.05, 2.5, 0.9, 0.6];
        let rgb: Vec<f32> = (0..18).map(|i| ((i * 7 % 10) as f32) / 10.0).collect();
        let t = [1.0f32, 1.3, 1.6, 2.0, 2.2, 2.6];
        let delta = [0.3f32, 0.3, 0.4, 0.2, 0.5, 0.4];
        let opts = CompositeOptions { background: [0.9, 0.1, 0.5], min_transmittance: 0.0, opaque_last };
        let up = Upstream { rgb: [0.7, -1.1, 0.4], depth: 0.3, weights: extra };
        let s = RaySamples::new(&sigma, &rgb, &t, &delta).unwrap();
        let mut w = [0.0; 6];
        let c = composite(s, &opts, &mut w).unwrap();
        let (mut ds, mut dc) = ([0.0; 6], [0.0; 18]);
        composite_backward(s, &w, &opts, c.used, up, &mut ds, &mut dc).unwrap();
        let (s64, c64, t64, d64) = (f64v(&sigma), f64v(&rgb), f64v(&t), f64v(&delta));
        let bg64 = opts.background.map(|v| v as f64);
        let e64 = extra.map_or(vec![0.0; 6], f64v);
        let obj = |s: &[f64], c: &[f64]| {
            let (col, dep, w) = reference_with(s, c, &t64, &d64, bg64, opaque_last);
            let reg: f64 = w.iter().zip(&e64).map(|(w, e)| w * e).sum();
            (0..3).map(|k| col[k] * up.rgb[k] as f64).sum::<f64>() + dep * up.depth as f64 + reg
        };
        // The forward agrees with the reference.
        let (rc, rd, rw) = reference_with(&s64, &c64, &t64, &d64, bg64, opaque_last);
        for k in 0..3 {
            assert!((rc[k] - c.rgb[k] as f64).abs() < 1e-6, "{rc:?} {:?}", c.rgb);
        }
        assert!((rd - c.depth as f64).abs() < 1e-6);
        assert!(rw.iter().zip(&w).all(|(a, &b)| (a - b as f64).abs() < 1e-6), "{rw:?} {w:?}");
        let h = 1e-7;
        for i in 0..6 {
            let (mut a, mut b) = (s64.clone(), s64.clone());
            a[i] += h;
            b[i] -= h;
            let num = (obj(&a, &c64) - obj(&b, &c64)) / (2.0 * h);
            assert!((num - ds[i] as f64).abs() < 1e-5, "sigma {i} ({opaque_last}): {num} vs {}", ds[i]);
        }
        if opaque_last {
            assert_eq!(ds[5], 0.0, "an opaque last interval's density gets no gradient");
        }
        for i in 0..18 {
            let (mut a, mut b) = (c64.clone(), c64.clone());
            a[i] += h;
            b[i] -= h;
            let num = (obj(&s64, &a) - obj(&s64, &b)) / (2.0 * h);
            assert!((num - dc[i] as f64).abs() < 1e-5, "rgb {i} ({opaque_last})");
        }
    }

    #[test]
    fn opaque_last_backward_matches_finite_differences_in_f64() {
        check_backward_with(true, None);
    }

    #[test]
    fn weight_gradient_backward_matches_finite_differences_in_f64() {
        let extra = [0.8f32, -0.4, 1.3, 0.2, -0.9, 0.5];
        check_backward_with(false, Some(&extra));
        check_backward_with(true, Some(&extra));
    }

    #[test]
    fn opaque_last_hides_the_background() {
        // sigma delta = ln 2 then 0 (empty last interval): weights 1/2 and the
        // remaining 1/2, nothing of the background.
        let l2 = std::f32::consts::LN_2;
        let sigma = [l2, 0.0];
        let s = RaySamples::new(&sigma, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0], &[1.0, 2.0], &[1.0, 0.5]).unwrap();
        let opts = CompositeOptions { background: [0.0, 0.0, 1.0], min_transmittance: 0.0, opaque_last: true };
        let mut w = [0.0; 2];
        let c = composite(s, &opts, &mut w).unwrap();
        assert_eq!(w, [0.5, 0.5]);
        assert_eq!((c.rgb, c.depth, c.opacity), ([0.5, 0.5, 0.0], 1.5, 1.0));
    }

    #[test]
    fn slices_that_do_not_fit_are_errors_naming_them() {
        let err = RaySamples::new(&[1.0; 3], &[0.5; 8], &[1.0; 3], &[0.1; 3]).unwrap_err();
        assert_eq!(err, InputError::Length { what: "rgb", expected: 9, got: 8 });
        let err = RaySamples::new(&[1.0; 3], &[0.5; 9], &[1.0; 3], &[0.1; 2]).unwrap_err();
        assert_eq!(err, InputError::Length { what: "delta", expected: 3, got: 2 });
        let s = RaySamples::new(&[1.0; 3], &[0.5; 9], &[1.0, 2.0, 3.0], &[0.1; 3]).unwrap();
        let opts = CompositeOptions::default();
        let err = composite(s, &opts, &mut [0.0; 2]).unwrap_err();
        assert_eq!(err, InputError::Length { what: "weights", expected: 3, got: 2 });
        let w = [0.1; 3];
        let up = Upstream { weights: Some(&[1.0; 4]), ..Default::default() };
        let err = composite_backward(s, &w, &opts, 3, up, &mut [0.0; 3], &mut [0.0; 9]).unwrap_err();
        assert_eq!(err, InputError::Length { what: "upstream weights", expected: 3, got: 4 });
        let err = composite_backward(s, &w, &opts, 3, Upstream::default(), &mut [0.0; 3], &mut [0.0; 6]);
        assert_eq!(err.unwrap_err(), InputError::Length { what: "drgb", expected: 9, got: 6 });
    }
}
