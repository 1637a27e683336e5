//! Where along a ray to sample: stratified samples for the coarse pass and
//! inverse-transform sampling of a piecewise-constant PDF for the fine pass.
//!
//! Samples are positions `t` sorted along the ray; each represents the
//! interval between the midpoints to its neighbours (the first starts at the
//! ray's near end, the last ends at its far end), so the intervals tile
//! `[near, far]` exactly.

use crate::engine::rng::Rng;

/// `n` stratified samples in `[near, far]`: one per equal bin, jittered
/// uniformly inside it when `rng` is given, at the bin centre otherwise.
pub fn stratified(near: f32, far: f32, n: usize, rng: Option<&mut Rng>, t: &mut Vec<f32>) {
    t.clear();
    let step = (far - near) / n as f32;
    match rng {
        Some(rng) => t.extend((0..n).map(|i| near + (i as f32 + rng.f32()) * step)),
        None => t.extend((0..n).map(|i| near + (i as f32 + 0.5) * step)),
    }
}

/// Interval lengths of sorted samples `t` in `[near, far]`: from the midpoint
/// to the previous sample (or `near`) to the midpoint to the next (or `far`).
pub fn deltas(t: &[f32], near: f32, far: f32, delta: &mut Vec<f32>) {
    delta.clear();
    let n = t.len();
    for i in 0..n {
        let lo = if i == 0 { near } else { 0.5 * (t[i - 1] + t[i]) };
        let hi = if i + 1 == n { far } else { 0.5 * (t[i] + t[i + 1]) };
        delta.push((hi - lo).max(0.0));
    }
}

/// Draws `n` samples from the piecewise-constant density whose bins have
/// `edges` (`weights.len() + 1` sorted values) and non-negative `weights`,
/// by inverting its CDF; appends them to `out` in increasing order.
/// Stratified `u` (jittered with `rng`, or at bin centres without it).
/// All-zero, tiny or non-finite weights fall back to a uniform density, so
/// the samples are always sorted, finite and inside `[edges[0], edges[last]]`.
pub fn sample_pdf(edges: &[f32], weights: &[f32], n: usize, rng: Option<&mut Rng>, out: &mut Vec<f32>) {
    let bins = weights.len();
    debug_assert_eq!(edges.len(), bins + 1);
    if bins == 0 || n == 0 {
        return;
    }
    // Padding as in the reference code keeps every bin reachable.
    const EPS: f32 = 1e-5;
    let mut cdf = Vec::with_capacity(bins + 1);
    pdf_cdf(weights, 1.0, EPS, &mut cdf);
    let mut rng = rng;
    let u = (0..n).map(|i| {
        let jitter = rng.as_deref_mut().map_or(0.5, |r| r.f32());
        (i as f32 + jitter) / n as f32
    });
    invert_cdf(edges, &cdf, u, out);
}

/// Writes into `cdf` the CDF (`[bins + 1]`, from 0 to exactly 1) of the
/// piecewise-constant density whose bin `j` has mass
/// `max(w_j, 0)^exponent + padding` (non-finite weights count as 0, and
/// `0^0 = 1`), summed in f64 so weights near `f32::MAX` cannot overflow.
/// When every mass is 0 (zero weights and no padding) the bins get equal
/// masses. `padding` must be finite and non-negative.
pub(super) fn pdf_cdf(weights: &[f32], exponent: f32, padding: f32, cdf: &mut Vec<f32>) {
    let bins = weights.len();
    cdf.clear();
    cdf.push(0.0);
    // First the masses and their total, then the running sums divided by it.
    let mut total = 0.0f64;
    for &w in weights {
        let w = if w.is_finite() && w > 0.0 { w } else { 0.0 };
        let mass = if exponent == 1.0 { w } else { w.powf(exponent) };
        total += mass as f64 + padding as f64;
        cdf.push(mass);
    }
    if total > 0.0 {
        let mut sum = 0.0f64;
        for c in &mut cdf[1..] {
            sum += *c as f64 + padding as f64;
            *c = (sum / total) as f32;
        }
    } else {
        for (k, c) in cdf.iter_mut().enumerate() {
            *c = k as f32 / bins as f32;
        }
    }
    cdf[bins] = 1.0;
}

/// Appends, for each of the non-decreasing `u` in `[0, 1]`, the point where
/// the CDF `cdf` of the bins `edges` (both `[bins + 1]`, sorted, `bins >= 1`)
/// reaches it, linear inside a bin. The points are clamped to be
/// non-decreasing and inside `[edges[0], edges[bins]]`.
pub(super) fn invert_cdf(edges: &[f32], cdf: &[f32], u: impl Iterator<Item = f32>, out: &mut Vec<f32>) {
    let bins = cdf.len() - 1;
    let mut j = 0usize;
    let lo = edges[0];
    let hi = edges[bins];
    for (i, u) in u.enumerate() {
        while j + 1 < bins && cdf[j + 1] <= u {
            j += 1;
        }
        let span = cdf[j + 1] - cdf[j];
        let frac = if span > 0.0 { ((u - cdf[j]) / span).clamp(0.0, 1.0) } else { 0.5 };
        let s = edges[j] + frac * (edges[j + 1] - edges[j]);
        let prev = out.last().copied().filter(|_| i > 0).unwrap_or(lo);
        out.push(s.clamp(prev, hi));
    }
}

/// Merges two sorted sample lists into `out` (sorted).
pub fn merge_sorted(a: &[f32], b: &[f32], out: &mut Vec<f32>) {
    out.clear();
    out.reserve(a.len() + b.len());
    let (mut i, mut j) = (0, 0);
    while i < a.len() && j < b.len() {
        if a[i] <= b[j] {
            out.push(a[i]);
            i += 1;
        } else {
            out.push(b[j]);
            j += 1;
        }
    }
    out.extend_from_slice(&a[i..]);
    out.extend_from_slice(&b[j..]);
}

/// The interval edges of sorted samples `t` in `[near, far]` (see [`deltas`]).
pub fn edges(t: &[f32], near: f32, far: f32, out: &mut Vec<f32>) {
    out.clear();
    out.push(near);
    for w in t.windows(2) {
        out.push(0.5 * (w[0] + w[1]));
    }
    out.push(far);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stratified_is_sorted_and_in_bins() {
        let mut rng = Rng::new(1);
        let mut t = Vec::new();
        stratified(2.0, 6.0, 64, Some(&mut rng), &mut t);
        for (i, &v) in t.iter().enumerate() {
            let lo = 2.0 + i as f32 / 16.0;
            assert!(v >= lo && v <= lo + 1.0 / 16.0);
        }
        let mut d = Vec::new();
        deltas(&t, 2.0, 6.0, &mut d);
        assert!((d.iter().sum::<f32>() - 4.0).abs() < 1e-5, "intervals tile [near, far]");
    }

    #[test]
    fn pdf_samples_follow_the_weights() {
        let edges = [0.0, 1.0, 2.0, 3.0, 4.0];
        let weights = [0.0, 1.0, 0.0, 3.0];
        let mut out = Vec::new();
        sample_pdf(&edges, &weights, 1000, None, &mut out);
        let in_bin = |a: f32, b: f32| out.iter().filter(|&&s| s >= a && s < b).count();
        assert!((in_bin(1.0, 2.0) as i32 - 250).abs() < 5);
        assert!((in_bin(3.0, 4.0) as i32 - 750).abs() < 5);
        assert!(out.windows(2).all(|w| w[0] <= w[1]));
    }

    #[test]
    fn degenerate_weights_give_sorted_finite_samples() {
        let edges = [2.0, 3.0, 4.0, 5.0];
        let mut rng = Rng::new(4);
        for w in [[0.0f32; 3], [1e-30; 3], [0.0, 1.0, 0.0], [f32::NAN, f32::INFINITY, -1.0], [f32::MAX; 3]] {
            let mut out = Vec::new();
            sample_pdf(&edges, &w, 17, Some(&mut rng), &mut out);
            assert_eq!(out.len(), 17);
            assert!(out.iter().all(|s| s.is_finite() && (2.0..=5.0).contains(s)), "{w:?}: {out:?}");
            assert!(out.windows(2).all(|p| p[0] <= p[1]));
        }
    }

    #[test]
    fn huge_equal_weights_give_the_uniform_density() {
        // The f32 total of these weights overflows; the samples must not collapse.
        let edges = [0.0, 1.0, 2.0, 3.0, 4.0];
        let mut out = Vec::new();
        sample_pdf(&edges, &[1e38; 4], 8, None, &mut out);
        let want: Vec<f32> = (0..8).map(|k| (k as f32 + 0.5) / 2.0).collect();
        assert!(out.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-4), "{out:?}");
    }

    #[test]
    fn merge_keeps_order() {
        let mut out = Vec::new();
        merge_sorted(&[1.0, 3.0, 5.0], &[2.0, 2.5, 6.0], &mut out);
        assert_eq!(out, vec![1.0, 2.0, 2.5, 3.0, 5.0, 6.0]);
    }

    /// `sample_pdf` as it was before its CDF and inversion became
    /// `pdf_cdf` and `invert_cdf` (commit d1bff93), kept to show the nerf
    /// model's samples did not move.
    fn sample_pdf_before(edges: &[f32], weights: &[f32], n: usize, rng: Option<&mut Rng>, out: &mut Vec<f32>) {
        let bins = weights.len();
        if bins == 0 || n == 0 {
            return;
        }
        const EPS: f32 = 1e-5;
        let mut total = 0.0f64;
        let mut sums = Vec::with_capacity(bins + 1);
        sums.push(0.0f64);
        for &w in weights {
            let w = if w.is_finite() && w > 0.0 { w as f64 } else { 0.0 };
            total += w + EPS as f64;
            sums.push(total);
        }
        let mut cdf: Vec<f32> = sums.iter().map(|&c| (c / total) as f32).collect();
        cdf[bins] = 1.0;
        let mut rng = rng;
        let mut j = 0usize;
        let lo = edges[0];
        let hi = edges[bins];
        for i in 0..n {
            let jitter = rng.as_deref_mut().map_or(0.5, |r| r.f32());
            let u = (i as f32 + jitter) / n as f32;
            while j + 1 < bins && cdf[j + 1] <= u {
                j += 1;
            }
            let span = cdf[j + 1] - cdf[j];
            let frac = if span > 0.0 { ((u - cdf[j]) / span).clamp(0.0, 1.0) } else { 0.5 };
            let s = edges[j] + frac * (edges[j + 1] - edges[j]);
            let prev = out.last().copied().filter(|_| i > 0).unwrap_or(lo);
            out.push(s.clamp(prev, hi));
        }
    }

    #[test]
    fn sample_pdf_draws_the_same_bits_as_before_it_was_split() {
        let mut draw = Rng::new(99);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for case in 0..400 {
            let bins = 1 + draw.below(64) as usize;
            let mut edges: Vec<f32> = (0..=bins).map(|_| 6.0 * draw.f32()).collect();
            edges.sort_by(f32::total_cmp);
            let weights: Vec<f32> = (0..bins)
                .map(|_| match draw.below(8) {
                    0 => 0.0,
                    1 => f32::NAN,
                    2 => 1e30,
                    _ => draw.f32() * draw.f32(),
                })
                .collect();
            let n = draw.below(200) as usize;
            // Both append after what `out` already holds.
            let (mut a, mut b) = (vec![0.5f32], vec![0.5f32]);
            if case % 2 == 0 {
                sample_pdf(&edges, &weights, n, Some(&mut Rng::stream(3, case as u64, 1)), &mut a);
                sample_pdf_before(&edges, &weights, n, Some(&mut Rng::stream(3, case as u64, 1)), &mut b);
            } else {
                sample_pdf(&edges, &weights, n, None, &mut a);
                sample_pdf_before(&edges, &weights, n, None, &mut b);
            }
            assert_eq!(bits(&a), bits(&b), "case {case}");
        }
    }
}
