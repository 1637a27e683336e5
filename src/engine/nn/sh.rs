//! Real spherical harmonics up to degree 4 (16 coefficients) of a unit
//! direction, the direction encoding of Instant-NGP. The input is normalised
//! first; a zero or non-finite direction encodes as +z. `encode_backward`
//! is its derivative with respect to the direction (for gradients that
//! reach camera rotations).

pub const WIDTH: usize = 16;

/// Normalises `d`, falling back to +z.
pub fn unit(d: [f32; 3]) -> [f32; 3] {
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if n.is_finite() && n > 0.0 { [d[0] / n, d[1] / n, d[2] / n] } else { [0.0, 0.0, 1.0] }
}

/// Encodes one direction.
pub fn encode_one(d: [f32; 3], o: &mut [f32]) {
    let [x, y, z] = unit(d);
    let (xy, yz, xz) = (x * y, y * z, x * z);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    o[0] = 0.282_094_8;
    o[1] = -0.488_602_5 * y;
    o[2] = 0.488_602_5 * z;
    o[3] = -0.488_602_5 * x;
    o[4] = 1.092_548_4 * xy;
    o[5] = -1.092_548_4 * yz;
    o[6] = 0.946_174_7 * z2 - 0.315_391_57;
    o[7] = -1.092_548_4 * xz;
    o[8] = 0.546_274_2 * (x2 - y2);
    o[9] = 0.590_043_6 * y * (-3.0 * x2 + y2);
    o[10] = 2.890_611_4 * xy * z;
    o[11] = 0.457_045_8 * y * (1.0 - 5.0 * z2);
    o[12] = 0.373_176_33 * z * (5.0 * z2 - 3.0);
    o[13] = 0.457_045_8 * x * (1.0 - 5.0 * z2);
    o[14] = 1.445_305_7 * z * (x2 - y2);
    o[15] = 0.590_043_6 * x * (-x2 + 3.0 * y2);
}

/// Encodes `n` directions (`[n x 3]`) into `out` (`[n x 16]`).
pub fn encode(dirs: &[f32], out: &mut [f32]) {
    for (d, o) in dirs.chunks_exact(3).zip(out.chunks_exact_mut(WIDTH)) {
        encode_one([d[0], d[1], d[2]], o);
    }
}

/// Gradient of `sum(encode(d) * g)` with respect to the unit direction's
/// components, as if they were free: the gradient of the polynomials at
/// `unit(d)`, not projected onto the sphere ([`encode_backward_one`] is the
/// derivative of the encoding itself).
pub fn backward_one(d: [f32; 3], g: &[f32]) -> [f32; 3] {
    let [x, y, z] = unit(d);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    let mut dx = 0.0;
    let mut dy = 0.0;
    let mut dz = 0.0;
    dy += -0.488_602_5 * g[1];
    dz += 0.488_602_5 * g[2];
    dx += -0.488_602_5 * g[3];
    dx += 1.092_548_4 * y * g[4];
    dy += 1.092_548_4 * x * g[4];
    dy += -1.092_548_4 * z * g[5];
    dz += -1.092_548_4 * y * g[5];
    dz += 2.0 * 0.946_174_7 * z * g[6];
    dx += -1.092_548_4 * z * g[7];
    dz += -1.092_548_4 * x * g[7];
    dx += 0.546_274_2 * 2.0 * x * g[8];
    dy += -0.546_274_2 * 2.0 * y * g[8];
    dx += 0.590_043_6 * y * (-6.0 * x) * g[9];
    dy += 0.590_043_6 * (-3.0 * x2 + 3.0 * y2) * g[9];
    dx += 2.890_611_4 * y * z * g[10];
    dy += 2.890_611_4 * x * z * g[10];
    dz += 2.890_611_4 * x * y * g[10];
    dy += 0.457_045_8 * (1.0 - 5.0 * z2) * g[11];
    dz += 0.457_045_8 * y * (-10.0 * z) * g[11];
    dz += 0.373_176_33 * (15.0 * z2 - 3.0) * g[12];
    dx += 0.457_045_8 * (1.0 - 5.0 * z2) * g[13];
    dz += 0.457_045_8 * x * (-10.0 * z) * g[13];
    dx += 1.445_305_7 * z * 2.0 * x * g[14];
    dy += -1.445_305_7 * z * 2.0 * y * g[14];
    dz += 1.445_305_7 * (x2 - y2) * g[14];
    dx += 0.590_043_6 * (-3.0 * x2 + 3.0 * y2) * g[15];
    dy += 0.590_043_6 * x * 6.0 * y * g[15];
    [dx, dy, dz]
}

/// The derivative of [`encode_one`] at `d`: the gradient of
/// `sum(encode_one(d) * g)` (`g` is `[16]`) with respect to `d`.
///
/// The encoding normalises its input, `u = d / |d|`, so the gradient is the
/// polynomials' gradient at `u` ([`backward_one`]) projected onto the
/// sphere's tangent plane at `u` and divided by `|d|`:
/// `(I - u u^T) ∇p(u) / |d|`. For a unit direction it is the tangential
/// part alone (moving `d` along itself changes nothing). Zero where the
/// encoding falls back to +z (zero, non-finite, or overflowing `d`): it is
/// constant there.
pub fn encode_backward_one(d: [f32; 3], g: &[f32]) -> [f32; 3] {
    // The same norm as `unit`, so the fallback cases agree.
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if !(n.is_finite() && n > 0.0) {
        return [0.0; 3];
    }
    let u = [d[0] / n, d[1] / n, d[2] / n];
    let p = backward_one(u, g);
    let along = u[0] * p[0] + u[1] * p[1] + u[2] * p[2];
    [(p[0] - along * u[0]) / n, (p[1] - along * u[1]) / n, (p[2] - along * u[2]) / n]
}

/// Backward of [`encode`] with respect to the directions: adds
/// [`encode_backward_one`] of each row of `dirs` (`[n x 3]`) and `dout`
/// (`[n x 16]`) to `ddirs` (`[n x 3]`), as `encoding::encode_backward`
/// accumulates into its `dx`.
pub fn encode_backward(dirs: &[f32], dout: &[f32], ddirs: &mut [f32]) {
    for ((d, g), dd) in dirs.chunks_exact(3).zip(dout.chunks_exact(WIDTH)).zip(ddirs.chunks_exact_mut(3)) {
        let v = encode_backward_one([d[0], d[1], d[2]], g);
        for k in 0..3 {
            dd[k] += v[k];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orthonormal_on_the_sphere() {
        // Monte-Carlo check that the basis is orthonormal: E[Y_i Y_j] 4 pi = delta_ij.
        let mut rng = crate::engine::rng::Rng::new(3);
        let n = 200_000;
        let mut gram = [[0.0f64; WIDTH]; WIDTH];
        let mut o = [0.0f32; WIDTH];
        for _ in 0..n {
            encode_one([rng.normal(), rng.normal(), rng.normal()], &mut o);
            for i in 0..WIDTH {
                for j in 0..WIDTH {
                    gram[i][j] += (o[i] * o[j]) as f64;
                }
            }
        }
        let s = 4.0 * std::f64::consts::PI / n as f64;
        for i in 0..WIDTH {
            for j in 0..WIDTH {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((gram[i][j] * s - want).abs() < 0.03, "({i},{j}) = {}", gram[i][j] * s);
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let g: Vec<f32> = (0..WIDTH).map(|i| ((i * 5 % 7) as f32 - 3.0) / 3.0).collect();
        let d = [0.3f32, -0.5, 0.81];
        let u = unit(d);
        let grad = backward_one(u, &g);
        // f64 objective on the unnormalised components around the unit vector:
        // differentiate the polynomial directly (no renormalisation).
        let poly = |v: [f64; 3]| -> f64 {
            let [x, y, z] = v;
            let c: [f64; 16] = [
                0.2820948,
                -0.4886025 * y,
                0.4886025 * z,
                -0.4886025 * x,
                1.0925484 * x * y,
                -1.0925484 * y * z,
                0.9461747 * z * z - 0.31539157,
                -1.0925484 * x * z,
                0.5462742 * (x * x - y * y),
                0.5900436 * y * (-3.0 * x * x + y * y),
                2.8906114 * x * y * z,
                0.4570458 * y * (1.0 - 5.0 * z * z),
                0.37317633 * z * (5.0 * z * z - 3.0),
                0.4570458 * x * (1.0 - 5.0 * z * z),
                1.4453057 * z * (x * x - y * y),
                0.5900436 * x * (-x * x + 3.0 * y * y),
            ];
            c.iter().zip(&g).map(|(a, b)| a * *b as f64).sum()
        };
        let u64 = [u[0] as f64, u[1] as f64, u[2] as f64];
        for k in 0..3 {
            let mut a = u64;
            a[k] += 1e-6;
            let mut b = u64;
            b[k] -= 1e-6;
            let num = (poly(a) - poly(b)) / 2e-6;
            assert!((num - grad[k] as f64).abs() < 1e-4, "{k}: {num} vs {}", grad[k]);
        }
    }

    /// The encoding in f64, normalising as `encode_one` does.
    fn encode64(d: [f64; 3]) -> [f64; WIDTH] {
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let [x, y, z] = d.map(|v| v / n);
        [
            0.282_094_791_773_878_14,
            -0.488_602_511_902_919_9 * y,
            0.488_602_511_902_919_9 * z,
            -0.488_602_511_902_919_9 * x,
            1.092_548_430_592_079_2 * x * y,
            -1.092_548_430_592_079_2 * y * z,
            0.946_174_695_757_560_1 * z * z - 0.315_391_565_252_520_05,
            -1.092_548_430_592_079_2 * x * z,
            0.546_274_215_296_039_6 * (x * x - y * y),
            0.590_043_589_926_643_5 * y * (-3.0 * x * x + y * y),
            2.890_611_442_640_554 * x * y * z,
            0.457_045_799_464_465_8 * y * (1.0 - 5.0 * z * z),
            0.373_176_332_590_115_4 * z * (5.0 * z * z - 3.0),
            0.457_045_799_464_465_8 * x * (1.0 - 5.0 * z * z),
            1.445_305_721_320_277 * z * (x * x - y * y),
            0.590_043_589_926_643_5 * x * (-x * x + 3.0 * y * y),
        ]
    }

    /// `encode_backward` against central differences of the f64 encoding
    /// (checked against `encode_one`), degree by degree (0 to 4, the
    /// coefficients `l^2 .. (l+1)^2`) and all together, on random unit
    /// directions and on directions of other lengths.
    #[test]
    fn encode_backward_matches_finite_differences_for_every_degree() {
        let mut rng = crate::engine::rng::Rng::new(31);
        let mut o = [0.0f32; WIDTH];
        let bands = [0..1, 1..4, 4..9, 9..16, 0..16];
        for band in bands {
            let mut largest = 0.0f64;
            for trial in 0..200 {
                let g: Vec<f32> = (0..WIDTH).map(|i| if band.contains(&i) { rng.normal() } else { 0.0 }).collect();
                let raw = [rng.normal(), rng.normal(), rng.normal()];
                let len = if trial % 2 == 0 { 1.0 } else { 0.2 + 5.0 * rng.f32() };
                let u = unit(raw);
                let d = u.map(|v| v * len);
                let d64 = d.map(|v| v as f64);
                encode_one(d, &mut o);
                let e = encode64(d64);
                assert!(o.iter().zip(&e).all(|(a, b)| (*a as f64 - b).abs() < 1e-6), "{o:?} vs {e:?}");
                let mut got = [0.0f32; 3];
                encode_backward(&d, &g, &mut got);
                let f = |v: [f64; 3]| -> f64 { encode64(v).iter().zip(&g).map(|(a, b)| a * *b as f64).sum() };
                for k in 0..3 {
                    let (mut a, mut b) = (d64, d64);
                    a[k] += 1e-6;
                    b[k] -= 1e-6;
                    let num = (f(a) - f(b)) / 2e-6;
                    largest = largest.max(num.abs());
                    assert!(
                        (num - got[k] as f64).abs() < 1e-4 * (1.0 + num.abs()),
                        "band {band:?}, d {d:?}, axis {k}: {num} vs {}",
                        got[k]
                    );
                }
                let along: f32 = (0..3).map(|k| got[k] * u[k]).sum();
                assert!(along.abs() < 1e-5, "the gradient is tangent to the sphere: {got:?} . {u:?} = {along}");
                if band.start == 0 && band.end == 1 {
                    assert_eq!(got, [0.0; 3], "the constant term has no gradient");
                }
            }
            if band.start > 0 || band.end > 1 {
                assert!(largest > 0.5, "band {band:?}: gradients are not all small ({largest})");
            }
        }
    }

    #[test]
    fn encode_backward_accumulates_and_is_zero_where_the_encoding_is_constant() {
        let g: Vec<f32> = (0..WIDTH).map(|i| i as f32 * 0.1 - 0.7).collect();
        let dirs = [0.3f32, -0.5, 0.81, 0.0, 0.0, 0.0, f32::NAN, 1.0, 0.0, 1e30, 1e30, 0.0];
        let dout: Vec<f32> = g.repeat(4);
        let mut dd = vec![1.0f32; 12];
        encode_backward(&dirs, &dout, &mut dd);
        let first = encode_backward_one([0.3, -0.5, 0.81], &g);
        assert_eq!(&dd[..3], &first.map(|v| v + 1.0), "adds to what is there");
        assert!(first.iter().any(|v| v.abs() > 0.1));
        assert_eq!(&dd[3..], &[1.0; 9], "zero, NaN and overflowing directions encode as +z: no gradient");
    }

    #[test]
    fn degenerate_directions_never_give_nan() {
        let mut o = [0.0f32; WIDTH];
        for d in [[0.0, 0.0, 0.0], [f32::NAN, 1.0, 0.0], [1e30, 1e30, 0.0], [3.0, 4.0, 0.0]] {
            encode_one(d, &mut o);
            assert!(o.iter().all(|v| v.is_finite()), "{d:?}");
        }
        encode_one([3.0, 4.0, 0.0], &mut o);
        let mut p = [0.0f32; WIDTH];
        encode_one([0.6, 0.8, 0.0], &mut p);
        assert_eq!(o, p, "non-unit directions are normalised");
    }
}
