//! The similarity transform (scale, rotation, translation) that best maps
//! one set of points onto another in the least-squares sense: Horn's
//! closed-form solution with unit quaternions (J. Opt. Soc. Am. A 4(4),
//! 1987). Used to compare camera poses estimated up to a similarity (by
//! structure from motion) with known ones.

/// `x -> scale * rotation * x + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    /// Row-major rotation matrix.
    pub rotation: [[f64; 3]; 3],
    pub translation: [f64; 3],
}

impl Similarity {
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let r = mat_vec(&self.rotation, p);
        [0, 1, 2].map(|i| self.scale * r[i] + self.translation[i])
    }
}

pub fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|i| m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2])
}

pub fn mat_mul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

/// The angle of the rotation `a * b^T`, in degrees: how far apart two
/// orientations are.
pub fn angle_between_deg(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> f64 {
    let trace: f64 = (0..3).map(|i| (0..3).map(|k| a[i][k] * b[i][k]).sum::<f64>()).sum();
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The similarity mapping `from[i]` closest to `to[i]`; `None` with fewer
/// than three points or when they are all (nearly) on one line.
pub fn similarity(from: &[[f64; 3]], to: &[[f64; 3]]) -> Option<Similarity> {
    if from.len() != to.len() || from.len() < 3 {
        return None;
    }
    let mean = |pts: &[[f64; 3]]| {
        let n = pts.len() as f64;
        [0, 1, 2].map(|k| pts.iter().map(|p| p[k]).sum::<f64>() / n)
    };
    let (ma, mb) = (mean(from), mean(to));
    let a: Vec<[f64; 3]> = from.iter().map(|p| [0, 1, 2].map(|k| p[k] - ma[k])).collect();
    let b: Vec<[f64; 3]> = to.iter().map(|p| [0, 1, 2].map(|k| p[k] - mb[k])).collect();
    // Cross-covariance S[x][y] = sum a_x b_y.
    let mut s = [[0.0; 3]; 3];
    for (p, q) in a.iter().zip(&b) {
        for x in 0..3 {
            for y in 0..3 {
                s[x][y] += p[x] * q[y];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = jacobi_eigen(n);
    let mut order = [0, 1, 2, 3];
    order.sort_by(|&i, &j| values[j].total_cmp(&values[i]));
    // Points on a line leave the rotation about it free: two equal top eigenvalues.
    let spread = values.iter().map(|v| v.abs()).fold(0.0, f64::max);
    if spread == 0.0 || (values[order[0]] - values[order[1]]).abs() < 1e-9 * spread {
        return None;
    }
    let q = [0, 1, 2, 3].map(|k| vectors[k][order[0]]);
    let rotation = quat_to_matrix(q);
    let (mut num, mut den) = (0.0, 0.0);
    for (p, q) in a.iter().zip(&b) {
        let rp = mat_vec(&rotation, *p);
        num += (0..3).map(|k| rp[k] * q[k]).sum::<f64>();
        den += (0..3).map(|k| p[k] * p[k]).sum::<f64>();
    }
    if den == 0.0 {
        return None;
    }
    let scale = num / den;
    let rm = mat_vec(&rotation, ma);
    let translation = [0, 1, 2].map(|k| mb[k] - scale * rm[k]);
    Some(Similarity { scale, rotation, translation })
}

/// A unit quaternion `w, x, y, z` (normalised here) as a rotation matrix.
pub fn quat_to_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let [w, x, y, z] = q.map(|v| v / n);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Eigenvalues and eigenvectors (the columns of the second result) of a
/// symmetric NxN matrix, by cyclic Jacobi rotations (unsorted).
pub fn jacobi_eigen<const N: usize>(mut a: [[f64; N]; N]) -> ([f64; N], [[f64; N]; N]) {
    let mut v = [[0.0; N]; N];
    for i in 0..N {
        v[i][i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..N)
            .flat_map(|i| (0..N).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        let total: f64 = a.iter().flatten().map(|x| x * x).sum();
        if off <= 1e-30 * total.max(1e-300) {
            break;
        }
        for p in 0..N {
            for q in p + 1..N {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..N {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..N {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for k in 0..N {
                    let (vkp, vkq) = (v[k][p], v[k][q]);
                    v[k][p] = c * vkp - s * vkq;
                    v[k][q] = s * vkp + c * vkq;
                }
            }
        }
    }
    (std::array::from_fn(|i| a[i][i]), v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points() -> Vec<[f64; 3]> {
        (0..12)
            .map(|i| {
                let t = i as f64;
                [(0.7 * t).cos() * 3.0, (0.7 * t).sin() * 2.0, 0.3 * t - 1.0 + (1.3 * t).sin()]
            })
            .collect()
    }

    #[test]
    fn a_known_similarity_is_recovered() {
        let truth =
            Similarity { scale: 2.5, rotation: quat_to_matrix([0.3, -0.5, 0.7, 0.2]), translation: [1.0, -4.0, 0.5] };
        let from = points();
        let to: Vec<_> = from.iter().map(|p| truth.apply(*p)).collect();
        let s = similarity(&from, &to).unwrap();
        assert!((s.scale - 2.5).abs() < 1e-9, "{}", s.scale);
        assert!(angle_between_deg(&s.rotation, &truth.rotation) < 1e-6);
        for k in 0..3 {
            assert!((s.translation[k] - truth.translation[k]).abs() < 1e-9);
        }
        // Rotations of any angle, including half turns (w = 0).
        for q in [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.6, 0.8], [1.0, 0.0, 0.0, 0.0]] {
            let r = quat_to_matrix(q);
            let to: Vec<_> = from.iter().map(|p| mat_vec(&r, *p)).collect();
            let s = similarity(&from, &to).unwrap();
            assert!(angle_between_deg(&s.rotation, &r) < 1e-6, "{q:?}");
        }
    }

    #[test]
    fn noise_moves_the_fit_a_little_and_degenerate_sets_are_refused() {
        let from = points();
        let to: Vec<_> = from.iter().enumerate().map(|(i, p)| [p[0] + 0.01 * (i as f64).sin(), p[1], p[2]]).collect();
        let s = similarity(&from, &to).unwrap();
        assert!(
            (s.scale - 1.0).abs() < 0.01 && angle_between_deg(&s.rotation, &quat_to_matrix([1.0, 0.0, 0.0, 0.0])) < 0.5
        );
        let line: Vec<_> = (0..5).map(|i| [i as f64, 2.0 * i as f64, 0.0]).collect();
        assert!(similarity(&line, &line).is_none());
        assert!(similarity(&from[..2], &to[..2]).is_none());
    }

    #[test]
    fn angles_between_rotations() {
        let r = quat_to_matrix([(0.25f64).cos(), 0.0, 0.0, (0.25f64).sin()]); // 0.5 rad about z
        assert!((angle_between_deg(&r, &quat_to_matrix([1.0, 0.0, 0.0, 0.0])) - 0.5f64.to_degrees()).abs() < 1e-9);
    }
}
