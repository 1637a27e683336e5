//! Positional (frequency) encoding of the original NeRF:
//! `gamma(p) = (p, sin(2^0 p), cos(2^0 p), ..., sin(2^(L-1) p), cos(2^(L-1) p))`
//! per coordinate, in the layout of the reference code (input first, then for
//! each frequency the sines of all coordinates, then the cosines).
//!
//! As in the reference implementation the frequencies are `2^k` without the
//! paper's factor pi; our coordinates are normalised to the scene box
//! (`[-1, 1]`), so the finest wavelength is about 1/80 of the box.

/// `sin_cos(x * f)`, finite for every finite `x`: when the phase overflows
/// f32 (huge coordinates, far outside the scene box) it is taken in f64.
#[inline]
fn phase(x: f32, f: f32) -> (f32, f32) {
    let a = x * f;
    if a.is_finite() || !x.is_finite() {
        a.sin_cos()
    } else {
        let (s, c) = (x as f64 * f as f64).sin_cos();
        (s as f32, c as f32)
    }
}

/// Output width for `dims` inputs and `freqs` frequencies.
pub const fn encoded_width(dims: usize, freqs: usize) -> usize {
    dims * (1 + 2 * freqs)
}

/// Encodes `n` points of `dims` coordinates (`x` is `[n x dims]`) into
/// `out` (`[n x encoded_width]`).
pub fn encode(x: &[f32], dims: usize, freqs: usize, out: &mut [f32]) {
    let w = encoded_width(dims, freqs);
    for (p, o) in x.chunks_exact(dims).zip(out.chunks_exact_mut(w)) {
        o[..dims].copy_from_slice(p);
        for k in 0..freqs {
            let f = (1u32 << k) as f32;
            let base = dims + 2 * dims * k;
            for d in 0..dims {
                let (s, c) = phase(p[d], f);
                o[base + d] = s;
                o[base + dims + d] = c;
            }
        }
    }
}

/// Backward of [`encode`] with respect to the input: `dx += J^T dout`.
pub fn encode_backward(x: &[f32], dims: usize, freqs: usize, dout: &[f32], dx: &mut [f32]) {
    let w = encoded_width(dims, freqs);
    for ((p, g), d) in x.chunks_exact(dims).zip(dout.chunks_exact(w)).zip(dx.chunks_exact_mut(dims)) {
        for i in 0..dims {
            d[i] += g[i];
        }
        for k in 0..freqs {
            let f = (1u32 << k) as f32;
            let base = dims + 2 * dims * k;
            for i in 0..dims {
                let (s, c) = phase(p[i], f);
                d[i] += f * (c * g[base + i] - s * g[base + dims + i]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_matches_reference() {
        let x = [0.5f32, -0.25, 1.0];
        let mut out = vec![0.0; encoded_width(3, 2)];
        encode(&x, 3, 2, &mut out);
        assert_eq!(&out[..3], &x);
        assert!((out[3] - 0.5f32.sin()).abs() < 1e-7);
        assert!((out[6] - 0.5f32.cos()).abs() < 1e-7);
        assert!((out[9 + 1] - (-0.5f32).sin()).abs() < 1e-7); // sin(2 * -0.25)
        assert!((out[12 + 2] - 2.0f32.cos()).abs() < 1e-7); // cos(2 * 1.0)
    }

    #[test]
    fn huge_coordinates_encode_to_finite_values() {
        let x = [f32::MAX, f32::MIN, 1e38];
        let mut out = vec![0.0; encoded_width(3, 10)];
        encode(&x, 3, 10, &mut out);
        assert!(out[3..].iter().all(|v| v.is_finite() && v.abs() <= 1.0), "{out:?}");
        let mut dx = [0.0; 3];
        encode_backward(&x, 3, 10, &vec![1.0; out.len()], &mut dx);
        assert!(dx.iter().all(|v| v.is_finite()), "{dx:?}");
    }

    #[test]
    fn backward_matches_finite_differences() {
        let x = [0.3f32, -0.7, 0.11, 0.9, 0.2, -0.4];
        let freqs = 4;
        let w = encoded_width(3, freqs);
        let g: Vec<f32> = (0..2 * w).map(|i| ((i * 37 % 11) as f32 - 5.0) / 5.0).collect();
        let mut dx = vec![0.0f32; 6];
        encode_backward(&x, 3, freqs, &g, &mut dx);
        // f64 reference objective sum(gamma(x) * g)
        let obj = |x: &[f64]| -> f64 {
            let mut t = 0.0;
            for (r, p) in x.chunks(3).enumerate() {
                let go = &g[r * w..(r + 1) * w];
                for i in 0..3 {
                    t += p[i] * go[i] as f64;
                    for k in 0..freqs {
                        let f = (1u32 << k) as f64;
                        t += (p[i] * f).sin() * go[3 + 6 * k + i] as f64;
                        t += (p[i] * f).cos() * go[3 + 6 * k + 3 + i] as f64;
                    }
                }
            }
            t
        };
        let x64: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        for i in 0..6 {
            let mut a = x64.clone();
            a[i] += 1e-6;
            let mut b = x64.clone();
            b[i] -= 1e-6;
            let num = (obj(&a) - obj(&b)) / 2e-6;
            assert!((num - dx[i] as f64).abs() < 1e-3, "{i}: {num} vs {}", dx[i]);
        }
    }
}
