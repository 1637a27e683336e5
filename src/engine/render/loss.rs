//! The photometric loss: squared error of a ray's colour, value and
//! gradient side by side.

/// The mean over the three channels of the squared error of `rgb` against
/// `target` (accumulated in f64), and its gradient with respect to `rgb`
/// times `scale` (a batch's mean takes `scale = 1 / (3 * rays)`).
#[inline]
pub fn l2(rgb: [f32; 3], target: [f32; 3], scale: f32) -> (f64, [f32; 3]) {
    let err = [rgb[0] - target[0], rgb[1] - target[1], rgb[2] - target[2]];
    let value = err.iter().map(|e| (*e as f64) * (*e as f64)).sum::<f64>() / 3.0;
    (value, [2.0 * scale * err[0], 2.0 * scale * err[1], 2.0 * scale * err[2]])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_and_gradient_by_hand_and_by_finite_differences() {
        // err = (0.5, -0.25, 0): value (0.25 + 0.0625) / 3.
        let (v, g) = l2([1.0, 0.25, 0.3], [0.5, 0.5, 0.3], 0.5);
        assert!((v - 0.3125 / 3.0).abs() < 1e-12);
        assert_eq!(g, [0.5, -0.25, 0.0]);
        // d value / d rgb_k = 2 err_k / 3: the gradient with scale 1/3.
        let rgb = [0.7f32, 0.1, 0.45];
        let target = [0.2f32, 0.6, 0.4];
        let (_, g) = l2(rgb, target, 1.0 / 3.0);
        for k in 0..3 {
            let h = 1e-3f32;
            let (mut a, mut b) = (rgb, rgb);
            a[k] += h;
            b[k] -= h;
            let num = (l2(a, target, 1.0).0 - l2(b, target, 1.0).0) / (2.0 * h as f64);
            assert!((num - g[k] as f64).abs() < 1e-4, "{k}: {num} vs {}", g[k]);
        }
    }
}
