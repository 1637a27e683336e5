//! Real spherical harmonics up to degree 4 (16 coefficients) of a unit
//! direction, the direction encoding of Instant-NGP. The input is normalised
//! first; a zero or non-finite direction encodes as +z.

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
/// components (before normalisation: directions are inputs, this serves
/// gradient checks and any future pose refinement).
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
