//! Losses on the compositing weights of one ray, value and gradient side by
//! side (design `real-captures.md` 2.5). Both work on a [`Histogram`]: a
//! ray's sorted interval edges (in the normalised ray distance `s` of
//! `sampling::proposal::Warp`) and the weight of each interval.
//!
//! - [`distortion`]: mip-NeRF 360's distortion loss, which pulls a ray's
//!   weight together into as few and as short intervals as it can (fewer
//!   floaters and less haze), in O(n) by prefix sums (DVGO v2).
//! - [`Interlevel`]: mip-NeRF 360's proposal loss, the only training signal
//!   of a proposal density network: a proposal's histogram must bound the
//!   final one from above, interval by interval; O(n + m).
//!
//! Their gradients dL/dw go into `composite::composite_backward` as
//! `Upstream::weights`, which turns them into dL/dsigma.

use super::InputError;

/// A ray's weights over sorted intervals: `n + 1` finite, non-decreasing
/// edges and `n` weights (checked once, by [`Histogram::new`]).
#[derive(Clone, Copy, Debug)]
pub struct Histogram<'a> {
    edges: &'a [f32],
    weights: &'a [f32],
}

impl<'a> Histogram<'a> {
    /// The histogram, or why `edges` and `weights` do not make one.
    pub fn new(edges: &'a [f32], weights: &'a [f32]) -> Result<Self, InputError> {
        InputError::check_len("edges", weights.len() + 1, edges.len())?;
        InputError::check_sorted("edges", edges)?;
        Ok(Self { edges, weights })
    }

    /// Number of intervals.
    pub fn len(&self) -> usize {
        self.weights.len()
    }

    pub fn is_empty(&self) -> bool {
        self.weights.is_empty()
    }

    pub fn edges(&self) -> &'a [f32] {
        self.edges
    }

    pub fn weights(&self) -> &'a [f32] {
        self.weights
    }
}

/// The distortion loss of one ray (mip-NeRF 360, Eq. 15): with interval
/// midpoints `m_i` and widths `d_i`,
/// `L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i`.
/// Returns `L` (summed in f64) and adds `scale * dL/dw_i` to `dw` (`[n]`).
///
/// O(n) by prefix sums (DVGO v2): with `W_i = sum_{j<i} w_j`,
/// `M_i = sum_{j<i} w_j m_j` and totals `W`, `M`, the double sum is
/// `2 sum_i w_i (m_i W_i - M_i)` since the midpoints are sorted, and
/// `dL/dw_i = 2 [m_i (W_i - (W - W_i - w_i)) + (M - M_i - w_i m_i) - M_i]
/// + 2/3 w_i d_i`. Samples that were culled enter with `w = 0`.
pub fn distortion(h: Histogram<'_>, scale: f32, dw: &mut [f32]) -> Result<f64, InputError> {
    let n = h.len();
    InputError::check_len("dw", n, dw.len())?;
    let mid = |i: usize| 0.5 * (h.edges[i] as f64 + h.edges[i + 1] as f64);
    let (mut w_all, mut m_all) = (0.0f64, 0.0f64);
    for i in 0..n {
        let w = h.weights[i] as f64;
        w_all += w;
        m_all += w * mid(i);
    }
    let (mut w_before, mut m_before) = (0.0f64, 0.0f64);
    let (mut cross, mut own) = (0.0f64, 0.0f64);
    for i in 0..n {
        let (w, m) = (h.weights[i] as f64, mid(i));
        let width = h.edges[i + 1] as f64 - h.edges[i] as f64;
        cross += w * (m * w_before - m_before);
        own += w * w * width;
        let (w_after, m_after) = (w_all - w_before - w, m_all - m_before - w * m);
        let grad = 2.0 * (m * (w_before - w_after) + (m_after - m_before)) + 2.0 / 3.0 * w * width;
        dw[i] += (scale as f64 * grad) as f32;
        w_before += w;
        m_before += w * m;
    }
    Ok(2.0 * cross + own / 3.0)
}

/// The `eps` of the interlevel loss's denominator `w + eps` (multinerf and
/// nerfstudio use f32's machine epsilon): it only keeps an empty interval
/// from dividing by zero.
pub const INTERLEVEL_EPS: f64 = f32::EPSILON as f64;

/// The interlevel (proposal) loss, with the buffers it reuses from ray to
/// ray (one per thread).
///
/// For final intervals `[s_i, s_{i+1}]` with weights `w_i` (detached: no
/// gradient reaches them) and a proposal's intervals `(p_j, p_{j+1})` with
/// weights `v_j`, `outer_i` sums the `v_j` of the proposal intervals that
/// overlap the final one (`p_j < s_{i+1}` and `p_{j+1} > s_i`: sharing an
/// edge is not overlapping), and
/// `L = sum_i max(0, w_i - outer_i)^2 / (w_i + eps)`
/// (multinerf `lossfun_outer`, nerfstudio `interlevel_loss` for one level).
/// A proposal that covers less of the ray than the final intervals bounds
/// the uncovered part by nothing, so final weight there is all penalty
/// (and pulls on no proposal weight).
#[derive(Debug, Default)]
pub struct Interlevel {
    /// Prefix sums of the proposal weights, `[m + 1]`.
    cum: Vec<f64>,
    /// Difference array of the gradient, `[m + 1]`.
    diff: Vec<f64>,
}

impl Interlevel {
    /// `L` for one ray (summed in f64); adds `scale * dL/dv_j` to
    /// `d_proposal` (`[m]`). Negative or NaN final weights count as 0.
    ///
    /// O(n + m): both edge lists are sorted, so the first and last
    /// overlapping proposal intervals `lo_i`, `hi_i` only move forward with
    /// `i` (one sweep), `outer_i = C[hi_i + 1] - C[lo_i]` from prefix sums
    /// `C` of `v`, and `dL/dv_j = sum_{i: lo_i <= j <= hi_i}
    /// -2 max(0, w_i - outer_i) / (w_i + eps)` is gathered by a difference
    /// array (add at `lo_i`, subtract after `hi_i`, then a prefix sum).
    pub fn loss(
        &mut self,
        fine: Histogram<'_>,
        proposal: Histogram<'_>,
        scale: f32,
        d_proposal: &mut [f32],
    ) -> Result<f64, InputError> {
        let (n, m) = (fine.len(), proposal.len());
        InputError::check_len("d_proposal", m, d_proposal.len())?;
        let (s, p) = (fine.edges, proposal.edges);
        self.cum.clear();
        self.cum.push(0.0);
        let mut total = 0.0f64;
        for &v in proposal.weights {
            total += v as f64;
            self.cum.push(total);
        }
        self.diff.clear();
        self.diff.resize(m + 1, 0.0);
        // Proposal intervals lo..hi (exclusive) overlap final interval i:
        // lo is the first with p[lo + 1] > s[i], hi the count of those with
        // p[j] < s[i + 1].
        let (mut lo, mut hi) = (0usize, 0usize);
        let mut loss = 0.0f64;
        for i in 0..n {
            while lo < m && p[lo + 1] <= s[i] {
                lo += 1;
            }
            while hi < m && p[hi] < s[i + 1] {
                hi += 1;
            }
            let outer = if hi > lo { self.cum[hi] - self.cum[lo] } else { 0.0 };
            let w = fine.weights[i] as f64;
            let w = if w > 0.0 { w } else { 0.0 };
            let excess = (w - outer).max(0.0);
            if excess > 0.0 {
                loss += excess * excess / (w + INTERLEVEL_EPS);
                if hi > lo {
                    let g = -2.0 * excess / (w + INTERLEVEL_EPS);
                    self.diff[lo] += g;
                    self.diff[hi] -= g;
                }
            }
        }
        let mut acc = 0.0f64;
        for (d, step) in d_proposal.iter_mut().zip(&self.diff) {
            acc += step;
            *d += (scale as f64 * acc) as f32;
        }
        Ok(loss)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::render::composite::{CompositeOptions, RaySamples, Upstream, composite, composite_backward};
    use crate::engine::rng::Rng;
    use proptest::prelude::*;

    /// The double-sum definition, in f64.
    fn distortion_reference(edges: &[f64], w: &[f64]) -> f64 {
        let n = w.len();
        let mid: Vec<f64> = (0..n).map(|i| 0.5 * (edges[i] + edges[i + 1])).collect();
        let mut l = 0.0;
        for i in 0..n {
            for j in 0..n {
                l += w[i] * w[j] * (mid[i] - mid[j]).abs();
            }
            l += w[i] * w[i] * (edges[i + 1] - edges[i]) / 3.0;
        }
        l
    }

    /// `outer` by testing every pair of intervals, and the loss, in f64.
    fn interlevel_reference(s: &[f64], w: &[f64], p: &[f64], v: &[f64]) -> f64 {
        let mut l = 0.0;
        for i in 0..w.len() {
            let outer: f64 = (0..v.len()).filter(|&j| p[j] < s[i + 1] && p[j + 1] > s[i]).map(|j| v[j]).sum();
            let wi = w[i].max(0.0);
            let r = (wi - outer).max(0.0);
            l += r * r / (wi + INTERLEVEL_EPS);
        }
        l
    }

    fn f64v(v: &[f32]) -> Vec<f64> {
        v.iter().map(|&x| x as f64).collect()
    }

    /// Sorted edges in [0, 1] with some repeats (zero-width intervals).
    fn sorted_edges(raw: &[f32]) -> Vec<f32> {
        let mut e: Vec<f32> = raw.iter().map(|x| (x * 8.0).round() / 8.0).collect();
        e.sort_by(f32::total_cmp);
        e
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn distortion_is_the_double_sum(
            raw in proptest::collection::vec(0.0f32..1.0, 1..40),
            w in proptest::collection::vec(0.0f32..1.0, 40),
        ) {
            let edges = { let mut e = raw.clone(); e.sort_by(f32::total_cmp); e };
            let w = &w[..edges.len() - 1];
            let mut dw = vec![0.0; w.len()];
            let got = distortion(Histogram::new(&edges, w).unwrap(), 1.0, &mut dw).unwrap();
            let want = distortion_reference(&f64v(&edges), &f64v(w));
            prop_assert!((got - want).abs() <= 1e-9 * (1.0 + want), "{got} vs {want}");
        }

        #[test]
        fn interlevel_is_the_brute_force_outer(
            fine_raw in proptest::collection::vec(0.0f32..1.0, 1..30),
            prop_raw in proptest::collection::vec(0.0f32..1.0, 1..30),
            w in proptest::collection::vec(0.0f32..0.5, 30),
            v in proptest::collection::vec(0.0f32..0.5, 30),
        ) {
            // Rounded edges repeat and coincide across the two lists, so
            // shared edges and zero-width intervals are exercised; the two
            // lists generally cover different parts of [0, 1].
            let (s, p) = (sorted_edges(&fine_raw), sorted_edges(&prop_raw));
            let (w, v) = (&w[..s.len() - 1], &v[..p.len() - 1]);
            let mut d = vec![0.0; v.len()];
            let fine = Histogram::new(&s, w).unwrap();
            let proposal = Histogram::new(&p, v).unwrap();
            let got = Interlevel::default().loss(fine, proposal, 1.0, &mut d).unwrap();
            let want = interlevel_reference(&f64v(&s), &f64v(w), &f64v(&p), &f64v(v));
            prop_assert!((got - want).abs() <= 1e-9 * (1.0 + want), "{got} vs {want}");
        }
    }

    #[test]
    fn distortion_by_hand() {
        // Two intervals of width 1 with midpoints 0.5 and 2.5 (a gap between):
        // 2 w0 w1 |2.5 - 0.5| + (w0^2 + w1^2) / 3 = 2*0.5*0.25*2 + (0.25+0.0625)/3.
        let mut dw = [0.0; 3];
        let h = Histogram::new(&[0.0, 1.0, 2.0, 3.0], &[0.5, 0.0, 0.25]).unwrap();
        let l = distortion(h, 1.0, &mut dw).unwrap();
        assert!((l - (0.5 + 0.3125 / 3.0)).abs() < 1e-12, "{l}");
        // dL/dw0 = 2 w2 |m2 - m0| + 2/3 w0 = 1 + 1/3; dL/dw1 = 2(0.5*1 + 0.25*1) = 1.5.
        assert!((dw[0] - 4.0 / 3.0).abs() < 1e-6 && (dw[1] - 1.5).abs() < 1e-6, "{dw:?}");
    }

    #[test]
    fn distortion_gradient_matches_finite_differences_in_f64() {
        let mut rng = Rng::new(3);
        for n in [1usize, 2, 7, 32] {
            let mut edges: Vec<f32> = (0..=n).map(|_| rng.f32()).collect();
            edges.sort_by(f32::total_cmp);
            let w: Vec<f32> = (0..n).map(|_| rng.f32()).collect();
            let scale = 0.37f32;
            let mut dw = vec![0.25; n]; // gradients are added to what is there
            distortion(Histogram::new(&edges, &w).unwrap(), scale, &mut dw).unwrap();
            let (e64, w64) = (f64v(&edges), f64v(&w));
            for i in 0..n {
                let h = 1e-6;
                let (mut a, mut b) = (w64.clone(), w64.clone());
                a[i] += h;
                b[i] -= h;
                let num = (distortion_reference(&e64, &a) - distortion_reference(&e64, &b)) / (2.0 * h);
                let got = (dw[i] - 0.25) as f64 / scale as f64;
                assert!((num - got).abs() < 1e-5 * (1.0 + num.abs()), "n {n} w{i}: {num} vs {got}");
            }
        }
    }

    /// f64 weights of densities `sigma` over intervals `delta`.
    fn weights_f64(sigma: &[f64], delta: &[f64]) -> Vec<f64> {
        let mut trans = 1.0;
        sigma
            .iter()
            .zip(delta)
            .map(|(s, d)| {
                let a = 1.0 - (-s * d).exp();
                let w = trans * a;
                trans *= 1.0 - a;
                w
            })
            .collect()
    }

    /// dL/dsigma of a loss on the weights, through `composite_backward`.
    fn dsigma_through_composite(sigma: &[f32], delta: &[f32], dw: &[f32]) -> Vec<f32> {
        let n = sigma.len();
        let (rgb, t) = (vec![0.0; 3 * n], vec![0.0; n]);
        let s = RaySamples::new(sigma, &rgb, &t, delta).unwrap();
        let opts = CompositeOptions::default();
        let mut w = vec![0.0; n];
        let c = composite(s, &opts, &mut w).unwrap();
        let (mut ds, mut dc) = (vec![0.0; n], vec![0.0; 3 * n]);
        let up = Upstream { weights: Some(dw), ..Default::default() };
        composite_backward(s, &w, &opts, c.used, up, &mut ds, &mut dc).unwrap();
        ds
    }

    fn ray_densities() -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        // Edges in s (what the loss sees) and lengths in t (what the
        // compositor sees) need not be proportional.
        let s_edges = vec![0.0f32, 0.1, 0.25, 0.3, 0.5, 0.55, 0.8, 1.0];
        let delta = vec![0.2f32, 0.3, 0.1, 0.4, 0.1, 0.6, 0.9];
        let sigma = vec![0.4f32, 2.0, 0.1, 3.0, 0.7, 1.2, 0.3];
        (s_edges, delta, sigma)
    }

    #[test]
    fn distortion_density_gradient_matches_finite_differences_in_f64() {
        let (edges, delta, sigma) = ray_densities();
        let n = sigma.len();
        let (s64, d64, e64) = (f64v(&sigma), f64v(&delta), f64v(&edges));
        let w: Vec<f32> = weights_f64(&s64, &d64).iter().map(|&w| w as f32).collect();
        let mut dw = vec![0.0; n];
        distortion(Histogram::new(&edges, &w).unwrap(), 1.0, &mut dw).unwrap();
        let ds = dsigma_through_composite(&sigma, &delta, &dw);
        let loss = |s: &[f64]| distortion_reference(&e64, &weights_f64(s, &d64));
        for i in 0..n {
            let h = 1e-6;
            let (mut a, mut b) = (s64.clone(), s64.clone());
            a[i] += h;
            b[i] -= h;
            let num = (loss(&a) - loss(&b)) / (2.0 * h);
            assert!((num - ds[i] as f64).abs() < 1e-5 * (1.0 + num.abs()), "sigma {i}: {num} vs {}", ds[i]);
        }
    }

    /// A final histogram and a proposal over [0, 1] whose `outer` bounds
    /// are all at least 0.05 away from the final weights (off the kink of
    /// `max(0, .)`), with some intervals above their bound and some below.
    fn off_kink_case() -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let s = vec![0.0f32, 0.12, 0.3, 0.31, 0.5, 0.74, 0.9, 1.0];
        let w = vec![0.1f32, 0.4, 0.3, 0.0, 0.2, 0.6, 0.02];
        let p = vec![0.0f32, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0];
        let v = vec![0.02f32, 0.1, 0.15, 0.05, 0.3, 0.2];
        (s, w, p, v)
    }

    /// Every final interval with weight is at least 0.05 from its bound, so
    /// central differences of step 1e-6 do not straddle the kink.
    fn assert_off_kink(s: &[f64], w: &[f64], p: &[f64], v: &[f64]) {
        for i in 0..w.len() {
            let outer: f64 = (0..v.len()).filter(|&j| p[j] < s[i + 1] && p[j + 1] > s[i]).map(|j| v[j]).sum();
            assert!((w[i] - outer).abs() > 0.05 || w[i] == 0.0, "interval {i} is near the kink");
        }
    }

    #[test]
    fn interlevel_gradient_matches_finite_differences_in_f64() {
        let (s, w, p, v) = off_kink_case();
        let (s64, w64, p64, v64) = (f64v(&s), f64v(&w), f64v(&p), f64v(&v));
        assert_off_kink(&s64, &w64, &p64, &v64);
        let scale = 0.5f32;
        let mut d = vec![0.0; v.len()];
        let fine = Histogram::new(&s, &w).unwrap();
        Interlevel::default().loss(fine, Histogram::new(&p, &v).unwrap(), scale, &mut d).unwrap();
        assert!(d.iter().any(|&g| g < 0.0), "some final weight exceeds its bound: {d:?}");
        for j in 0..v.len() {
            let h = 1e-6;
            let (mut a, mut b) = (v64.clone(), v64.clone());
            a[j] += h;
            b[j] -= h;
            let num =
                (interlevel_reference(&s64, &w64, &p64, &a) - interlevel_reference(&s64, &w64, &p64, &b)) / (2.0 * h);
            let got = d[j] as f64 / scale as f64;
            assert!((num - got).abs() < 1e-5 * (1.0 + num.abs()), "v{j}: {num} vs {got}");
        }
    }

    #[test]
    fn interlevel_density_gradient_matches_finite_differences_in_f64() {
        // The proposal's weights come from its densities; the loss's gradient
        // reaches them through the compositor.
        let (s, w, p, _) = off_kink_case();
        let delta = vec![0.3f32, 0.2, 0.3, 0.2, 0.4, 0.5];
        let sigma = vec![0.1f32, 0.6, 0.5, 0.3, 1.5, 0.9];
        let (s64, w64, p64, d64, sig64) = (f64v(&s), f64v(&w), f64v(&p), f64v(&delta), f64v(&sigma));
        let v: Vec<f32> = weights_f64(&sig64, &d64).iter().map(|&x| x as f32).collect();
        assert_off_kink(&s64, &w64, &p64, &f64v(&v));
        let mut dv = vec![0.0; v.len()];
        let fine = Histogram::new(&s, &w).unwrap();
        let l = Interlevel::default().loss(fine, Histogram::new(&p, &v).unwrap(), 1.0, &mut dv).unwrap();
        assert!(l > 0.0);
        let ds = dsigma_through_composite(&sigma, &delta, &dv);
        let loss = |sig: &[f64]| interlevel_reference(&s64, &w64, &p64, &weights_f64(sig, &d64));
        for j in 0..sigma.len() {
            let h = 1e-6;
            let (mut a, mut b) = (sig64.clone(), sig64.clone());
            a[j] += h;
            b[j] -= h;
            let num = (loss(&a) - loss(&b)) / (2.0 * h);
            assert!((num - ds[j] as f64).abs() < 1e-5 * (1.0 + num.abs()), "sigma {j}: {num} vs {}", ds[j]);
        }
    }

    #[test]
    fn interlevel_edge_cases() {
        let mut il = Interlevel::default();
        let mut d = [0.0f32; 2];
        // A proposal that covers only [0, 0.5] of a final range [0, 1]: the
        // second final interval has no bound, so all its weight is penalty,
        // and nothing pulls on the proposal for it.
        let fine = Histogram::new(&[0.0, 0.5, 1.0], &[0.2, 0.3]).unwrap();
        let proposal = Histogram::new(&[0.0, 0.25, 0.5], &[0.1, 0.05]).unwrap();
        let l = il.loss(fine, proposal, 1.0, &mut d).unwrap();
        let eps = INTERLEVEL_EPS;
        let want = 0.05f64.powi(2) / (0.2 + eps) + 0.3f64.powi(2) / (0.3 + eps);
        assert!((l - want).abs() < 1e-7, "{l} vs {want}");
        let g0 = (-2.0 * 0.05 / (0.2 + eps)) as f32;
        assert!((d[0] - g0).abs() < 1e-6 && (d[1] - g0).abs() < 1e-6, "{d:?}");
        // A proposal beside the final range overlaps nothing.
        let mut d = [0.0f32; 1];
        let far = Histogram::new(&[2.0, 3.0], &[1.0]).unwrap();
        let l = il.loss(fine, far, 1.0, &mut d).unwrap();
        assert!((l - (0.2 + 0.3 - 2.0 * eps)).abs() < 1e-6 && d == [0.0], "{l} {d:?}");
        // Zero final weights cost nothing and pull on nothing.
        let zero = Histogram::new(&[0.0, 0.5, 1.0], &[0.0, 0.0]).unwrap();
        let mut d = [0.0f32; 2];
        assert_eq!(il.loss(zero, proposal, 1.0, &mut d).unwrap(), 0.0);
        assert_eq!(d, [0.0, 0.0]);
        // Zero proposal weights bound nothing: each final weight is penalty.
        let empty = Histogram::new(&[0.0, 0.25, 0.5], &[0.0, 0.0]).unwrap();
        let l = il.loss(fine, empty, 1.0, &mut d).unwrap();
        assert!((l - (0.2f64.powi(2) / (0.2 + eps) + 0.3f64.powi(2) / (0.3 + eps))).abs() < 1e-7);
        // One interval each: L = (w - v)^2 / (w + eps) when w > v, else 0.
        let mut d = [0.0f32; 1];
        let one = Histogram::new(&[0.0, 1.0], &[0.8]).unwrap();
        let l = il.loss(one, Histogram::new(&[0.0, 1.0], &[0.5]).unwrap(), 1.0, &mut d).unwrap();
        assert!((l - 0.09 / (0.8 + eps)).abs() < 1e-7 && (d[0] as f64 + 0.6 / (0.8 + eps)).abs() < 1e-6);
        let l = il.loss(one, Histogram::new(&[0.0, 1.0], &[0.9]).unwrap(), 1.0, &mut d).unwrap();
        assert_eq!(l, 0.0);
        // No intervals at all.
        let none = Histogram::new(&[0.5], &[]).unwrap();
        assert_eq!(il.loss(none, none, 1.0, &mut []).unwrap(), 0.0);
    }

    #[test]
    fn bad_histograms_are_errors() {
        assert_eq!(
            Histogram::new(&[0.0, 1.0], &[0.5, 0.5]).unwrap_err(),
            InputError::Length { what: "edges", expected: 3, got: 2 }
        );
        assert_eq!(
            Histogram::new(&[0.0, 0.7, 0.5], &[0.5, 0.5]).unwrap_err(),
            InputError::Unsorted { what: "edges", index: 2, value: 0.5 }
        );
        assert!(matches!(Histogram::new(&[0.0, f32::NAN], &[1.0]), Err(InputError::Unsorted { index: 1, .. })));
        let h = Histogram::new(&[0.0, 0.5, 1.0], &[0.5, 0.5]).unwrap();
        assert_eq!(
            distortion(h, 1.0, &mut [0.0; 3]).unwrap_err(),
            InputError::Length { what: "dw", expected: 2, got: 3 }
        );
        let err = Interlevel::default().loss(h, h, 1.0, &mut [0.0; 1]).unwrap_err();
        assert_eq!(err, InputError::Length { what: "d_proposal", expected: 2, got: 1 });
    }
}
