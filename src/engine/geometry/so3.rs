//! The rotation group's exponential map and its left Jacobian, for camera
//! pose refinement (design `real-captures.md` 2.7): a rotation vector `ω`
//! (axis times angle, radians) to a rotation matrix, and the matrix that
//! turns a small change of `ω` into the rotation vector of the change it
//! makes on the left, `exp(ω + δ) ≈ exp(J_l(ω) δ) exp(ω)`.
//!
//! In f64: the corrections are few (one per image), and the gradient check
//! differentiates them numerically.

/// A 3x3 matrix, rows.
pub type Mat3 = [[f64; 3]; 3];

/// Below this angle the coefficients come from their series (as
/// nerfstudio's `exp_map_SE3` `near_zero` branch): `sin θ / θ` and its
/// siblings lose all precision near 0.
const SMALL: f64 = 1e-4;

/// The three coefficients of `I`, `K` and `K²` that both maps use, for
/// `θ = |ω|`: `(sin θ / θ, (1 - cos θ) / θ², (θ - sin θ) / θ³)`.
fn coefficients(theta: f64) -> (f64, f64, f64) {
    if theta < SMALL {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0, 0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        let (s, c) = theta.sin_cos();
        (s / theta, (1.0 - c) / (theta * theta), (theta - s) / (theta * theta * theta))
    }
}

/// `a I + b K + c K²` with `K = [ω]×`.
fn combine(w: [f64; 3], a: f64, b: f64, c: f64) -> Mat3 {
    let k = hat(w);
    let k2 = mul(&k, &k);
    std::array::from_fn(|i| std::array::from_fn(|j| a * f64::from(u8::from(i == j)) + b * k[i][j] + c * k2[i][j]))
}

/// The cross-product matrix: `hat(w) v = w × v`.
pub fn hat(w: [f64; 3]) -> Mat3 {
    [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
}

/// The rotation `exp([ω]×) = I + (sin θ/θ) K + ((1 - cos θ)/θ²) K²`
/// (Rodrigues). A non-finite `ω` gives a non-finite matrix.
pub fn exp(w: [f64; 3]) -> Mat3 {
    let (a, b, _) = coefficients(norm(w));
    combine(w, 1.0, a, b)
}

/// The left Jacobian `J_l = I + ((1 - cos θ)/θ²) K + ((θ - sin θ)/θ³) K²`:
/// `exp(ω + δ) = exp([J_l(ω) δ]×) exp(ω) + O(|δ|²)`.
pub fn left_jacobian(w: [f64; 3]) -> Mat3 {
    let (_, b, c) = coefficients(norm(w));
    combine(w, 1.0, b, c)
}

/// `m v`.
pub fn apply(m: &Mat3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

/// `mᵀ v`.
pub fn apply_transposed(m: &Mat3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| m[0][i] * v[0] + m[1][i] * v[1] + m[2][i] * v[2])
}

/// `a b`.
pub fn mul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// `a × b`.
pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// The Euclidean norm.
pub fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    fn transpose(m: &Mat3) -> Mat3 {
        std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
    }

    /// The rotation vector of a rotation near the identity: the
    /// antisymmetric part `(R - Rᵀ)/2 = [sin θ a]×`, enough for the small
    /// differences the Jacobian test takes.
    fn vee_small(r: &Mat3) -> [f64; 3] {
        [0.5 * (r[2][1] - r[1][2]), 0.5 * (r[0][2] - r[2][0]), 0.5 * (r[1][0] - r[0][1])]
    }

    fn random_vectors(seed: u64) -> Vec<[f64; 3]> {
        let mut rng = Rng::new(seed);
        let mut v: Vec<[f64; 3]> = (0..20)
            .map(|k| {
                let scale = [1e-7, 1e-5, 0.03, 0.5, 2.0][k % 5];
                std::array::from_fn(|_| scale * f64::from(rng.normal()))
            })
            .collect();
        v.push([0.0; 3]);
        v.push([SMALL, 0.0, 0.0]);
        v.push([0.0, 0.999_999 * SMALL, 0.0]);
        v
    }

    /// Every exp is a rotation: orthonormal with determinant 1; it
    /// rotates about `ω` by `|ω|` (`exp(ω) ω = ω`, and a quarter turn about
    /// z maps x to y).
    #[test]
    fn exp_gives_rotations_about_the_vector() {
        for w in random_vectors(1) {
            let r = exp(w);
            let rrt = mul(&r, &transpose(&r));
            for (i, row) in rrt.iter().enumerate() {
                for (j, &v) in row.iter().enumerate() {
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((v - want).abs() < 1e-12, "{w:?}: R Rt [{i}][{j}] = {v}");
                }
            }
            let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
                - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
                + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
            assert!((det - 1.0).abs() < 1e-12, "{w:?}: det {det}");
            let rw = apply(&r, w);
            assert!((0..3).all(|k| (rw[k] - w[k]).abs() < 1e-12 * (1.0 + norm(w))), "{w:?} {rw:?}");
        }
        let q = exp([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let y = apply(&q, [1.0, 0.0, 0.0]);
        assert!((y[0]).abs() < 1e-15 && (y[1] - 1.0).abs() < 1e-15 && y[2].abs() < 1e-15, "{y:?}");
    }

    /// Either side of the series' threshold the coefficients agree.
    #[test]
    fn series_and_closed_form_meet() {
        let (below, above) = (coefficients(SMALL * (1.0 - 1e-9)), coefficients(SMALL * (1.0 + 1e-9)));
        // The closed forms lose about 1e-16 / θ² ~ 1e-8 (second) and
        // 1e-16 / θ³ ~ 1e-4 (third) to cancellation at the threshold: why
        // the series is used below it.
        assert!((below.0 - above.0).abs() < 1e-12, "{below:?} {above:?}");
        assert!((below.1 - above.1).abs() < 1e-7, "{below:?} {above:?}");
        assert!((below.2 - above.2).abs() < 1e-3, "{below:?} {above:?}");
        let at_two = coefficients(2.0);
        assert!((at_two.0 - 2f64.sin() / 2.0).abs() < 1e-15);
    }

    /// `J_l(ω) δ` is the rotation vector of `exp(ω + δ) exp(ω)ᵀ`, by
    /// central differences in each axis.
    #[test]
    fn left_jacobian_matches_finite_differences() {
        let h = 1e-6;
        for w in random_vectors(2) {
            let j = left_jacobian(w);
            let rt = transpose(&exp(w));
            for a in 0..3 {
                let mut up = w;
                up[a] += h;
                let mut down = w;
                down[a] -= h;
                let vu = vee_small(&mul(&exp(up), &rt));
                let vd = vee_small(&mul(&exp(down), &rt));
                for i in 0..3 {
                    let num = (vu[i] - vd[i]) / (2.0 * h);
                    assert!((num - j[i][a]).abs() < 1e-7, "{w:?}: J[{i}][{a}] = {} but FD {num}", j[i][a]);
                }
            }
        }
    }

    #[test]
    fn hat_is_the_cross_product() {
        let (a, b) = ([0.3, -1.2, 2.0], [1.5, 0.25, -0.7]);
        let c = apply(&hat(a), b);
        let want = cross(a, b);
        assert!((0..3).all(|k| (c[k] - want[k]).abs() < 1e-15));
        assert_eq!(apply_transposed(&hat(a), b), apply(&hat(a.map(|v| -v)), b));
    }
}
