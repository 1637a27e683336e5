//! The splats' parameters: where each Gaussian's values lie in the model's
//! flat parameter vector, and the values a renderer derives from them
//! (scales, rotation, opacity, colour).
//!
//! The parameters are six blocks, one value kind each, Gaussian by
//! Gaussian (so a block is a slice an optimiser or a densifier can treat
//! alike, at its own learning rate): positions `[n x 3]` (model units), log
//! scales `[n x 3]`, rotations `[n x 4]` (quaternions `w x y z`, not
//! necessarily of unit length: they are normalised where used), opacity
//! logits `[n]`, and the spherical-harmonic colour coefficients: the DC
//! terms `[n x 3]` and the rest `[n x (k-1) x 3]` (`k = (degree+1)^2`
//! coefficients, each an RGB triple; the colour is `0.5 + sum_k c_k Y_k(d)`
//! with `d` the unit direction from the camera to the Gaussian, as in the
//! 3DGS paper's code).

use crate::engine::nn::sh;

/// Coefficients per colour channel at SH degree `degree` (0 to 3).
pub const fn sh_coeffs(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// The zeroth SH basis function's value: an SH DC coefficient `c` gives the
/// colour `0.5 + SH_C0 * c` in every direction.
pub const SH_C0: f32 = 0.282_094_8;

/// Where each block of `n` Gaussians' parameters lies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    pub n: usize,
    /// SH coefficients per channel.
    pub k: usize,
}

impl Layout {
    pub fn new(n: usize, degree: u32) -> Self {
        Self { n, k: sh_coeffs(degree) }
    }

    /// Parameters per Gaussian.
    pub fn stride(k: usize) -> usize {
        3 + 3 + 4 + 1 + 3 * k
    }

    /// The layout of `len` parameters at `degree`; `None` when `len` is not
    /// a whole number of Gaussians.
    pub fn of_len(len: usize, degree: u32) -> Option<Self> {
        let k = sh_coeffs(degree);
        len.is_multiple_of(Self::stride(k)).then(|| Self { n: len / Self::stride(k), k })
    }

    pub fn len(&self) -> usize {
        self.n * Self::stride(self.k)
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    pub fn means(&self) -> std::ops::Range<usize> {
        0..3 * self.n
    }
    pub fn log_scales(&self) -> std::ops::Range<usize> {
        3 * self.n..6 * self.n
    }
    pub fn rotations(&self) -> std::ops::Range<usize> {
        6 * self.n..10 * self.n
    }
    pub fn opacities(&self) -> std::ops::Range<usize> {
        10 * self.n..11 * self.n
    }
    pub fn sh_dc(&self) -> std::ops::Range<usize> {
        11 * self.n..14 * self.n
    }
    pub fn sh_rest(&self) -> std::ops::Range<usize> {
        14 * self.n..self.len()
    }

    /// Gaussian `i`'s parameters in `params`.
    pub fn get<'a>(&self, params: &'a [f32], i: usize) -> Gaussian<'a> {
        let n = self.n;
        let r3 = 3 * (self.k - 1);
        Gaussian {
            mean: three(&params[3 * i..]),
            log_scale: three(&params[3 * n + 3 * i..]),
            rotation: [
                params[6 * n + 4 * i],
                params[6 * n + 4 * i + 1],
                params[6 * n + 4 * i + 2],
                params[6 * n + 4 * i + 3],
            ],
            opacity_logit: params[10 * n + i],
            sh_dc: three(&params[11 * n + 3 * i..]),
            sh_rest: &params[14 * n + r3 * i..14 * n + r3 * (i + 1)],
        }
    }

    /// The parameters of the Gaussians `keep` (in that order) of
    /// `params`, laid out for `keep.len()` Gaussians.
    pub fn select(&self, params: &[f32], keep: &[usize]) -> Vec<f32> {
        let to = Layout { n: keep.len(), k: self.k };
        let mut out = vec![0.0; to.len()];
        for (block, width) in [(0, 3), (3, 3), (6, 4), (10, 1), (11, 3), (14, 3 * (self.k - 1))] {
            let (src, dst) = (&params[block * self.n..], &mut out[block * to.n..]);
            for (j, &i) in keep.iter().enumerate() {
                dst[width * j..width * (j + 1)].copy_from_slice(&src[width * i..width * (i + 1)]);
            }
        }
        out
    }
}

fn three(s: &[f32]) -> [f32; 3] {
    [s[0], s[1], s[2]]
}

/// One Gaussian's parameters.
#[derive(Clone, Copy, Debug)]
pub struct Gaussian<'a> {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    pub rotation: [f32; 4],
    pub opacity_logit: f32,
    /// The SH DC term of each channel.
    pub sh_dc: [f32; 3],
    /// The other coefficients, `[(k-1) x 3]`.
    pub sh_rest: &'a [f32],
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `q / |q|`, or the identity for a zero or non-finite quaternion.
pub fn unit_quat(q: [f32; 4]) -> [f32; 4] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n.is_finite() && n > 0.0 { [q[0] / n, q[1] / n, q[2] / n, q[3] / n] } else { [1.0, 0.0, 0.0, 0.0] }
}

/// The rotation matrix of a unit quaternion `w x y z` (rows).
pub fn rotation_matrix(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// The backward of [`rotation_matrix`] then [`unit_quat`]: the gradient
/// with respect to the raw quaternion `q` of a loss whose gradient with
/// respect to the matrix is `g`.
pub fn rotation_backward(q: [f32; 4], g: [[f32; 3]; 3]) -> [f32; 4] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(n.is_finite() && n > 0.0) {
        return [0.0; 4];
    }
    let [w, x, y, z] = [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
    // d R / d(w, x, y, z), entry by entry.
    let dw = 2.0 * (-z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1]);
    let dx = 2.0
        * (y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2] + z * g[2][0] + w * g[2][1]
            - 2.0 * x * g[2][2]);
    let dy = 2.0
        * (-2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2] - w * g[2][0] + z * g[2][1]
            - 2.0 * y * g[2][2]);
    let dz = 2.0
        * (-2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
            + y * g[1][2]
            + x * g[2][0]
            + y * g[2][1]);
    let u = [w, x, y, z];
    let d = [dw, dx, dy, dz];
    let along = u[0] * d[0] + u[1] * d[1] + u[2] * d[2] + u[3] * d[3];
    [(d[0] - along * u[0]) / n, (d[1] - along * u[1]) / n, (d[2] - along * u[2]) / n, (d[3] - along * u[3]) / n]
}

/// The 3D covariance `R S S^T R^T` (symmetric: `xx xy xz yy yz zz`) and
/// `M = R S`, of a Gaussian.
pub fn covariance(log_scale: [f32; 3], rotation: [f32; 4]) -> ([f32; 6], [[f32; 3]; 3]) {
    let r = rotation_matrix(unit_quat(rotation));
    let s = [log_scale[0].exp(), log_scale[1].exp(), log_scale[2].exp()];
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = r[i][j] * s[j];
        }
    }
    let dot = |a: usize, b: usize| m[a][0] * m[b][0] + m[a][1] * m[b][1] + m[a][2] * m[b][2];
    ([dot(0, 0), dot(0, 1), dot(0, 2), dot(1, 1), dot(1, 2), dot(2, 2)], m)
}

/// The colour of Gaussian `g`'s SH coefficients (`k` per channel) seen
/// along `dir` (from the camera to the Gaussian; any length), before
/// clamping: `0.5 + sum_k c_k Y_k`.
pub fn sh_colour(g: &Gaussian<'_>, k: usize, dir: [f32; 3], basis: &mut [f32; sh::WIDTH]) -> [f32; 3] {
    let dc = g.sh_dc;
    let mut rgb = [0.5 + SH_C0 * dc[0], 0.5 + SH_C0 * dc[1], 0.5 + SH_C0 * dc[2]];
    if k > 1 {
        sh::encode_one(dir, basis);
        for j in 1..k {
            for c in 0..3 {
                rgb[c] += basis[j] * g.sh_rest[3 * (j - 1) + c];
            }
        }
    }
    rgb
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_blocks_tile_the_parameters() {
        for degree in 0..=3 {
            let l = Layout::new(5, degree);
            assert_eq!(l.len(), 5 * (11 + 3 * sh_coeffs(degree)));
            assert_eq!(l.means().end, l.log_scales().start);
            assert_eq!(l.log_scales().end, l.rotations().start);
            assert_eq!(l.rotations().end, l.opacities().start);
            assert_eq!(l.opacities().end, l.sh_dc().start);
            assert_eq!(l.sh_dc().end, l.sh_rest().start);
            assert_eq!(l.sh_rest().len(), 5 * 3 * (l.k - 1));
            assert_eq!(Layout::of_len(l.len(), degree), Some(l));
            assert_eq!(Layout::of_len(l.len() + 1, degree), None);
        }
    }

    #[test]
    fn select_keeps_each_gaussians_values() {
        let l = Layout::new(4, 1);
        let params: Vec<f32> = (0..l.len()).map(|i| i as f32).collect();
        let kept = l.select(&params, &[2, 0]);
        let to = Layout::new(2, 1);
        for (j, i) in [(0, 2), (1, 0)] {
            let (a, b) = (to.get(&kept, j), l.get(&params, i));
            assert_eq!(
                (a.mean, a.log_scale, a.rotation, a.opacity_logit),
                (b.mean, b.log_scale, b.rotation, b.opacity_logit)
            );
            assert_eq!((a.sh_dc, a.sh_rest), (b.sh_dc, b.sh_rest));
        }
    }

    #[test]
    fn rotation_matrix_is_orthonormal_and_its_backward_matches_differences() {
        let q = [0.7f32, -0.3, 0.5, 0.2];
        let r = rotation_matrix(unit_quat(q));
        for i in 0..3 {
            for j in 0..3 {
                let d: f32 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-6);
            }
        }
        let g = [[0.3, -1.0, 0.5], [0.2, 0.7, -0.4], [1.1, -0.6, 0.9]];
        let loss = |q: [f64; 4]| {
            let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
            let [w, x, y, z] = [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
            let r = [
                [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
                [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
                [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
            ];
            (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).map(|(i, j)| r[i][j] * g[i][j] as f64).sum::<f64>()
        };
        let analytic = rotation_backward(q, g);
        for c in 0..4 {
            let h = 1e-6;
            let (mut a, mut b) = (q.map(f64::from), q.map(f64::from));
            a[c] += h;
            b[c] -= h;
            let fd = (loss(a) - loss(b)) / (2.0 * h);
            assert!((analytic[c] as f64 - fd).abs() < 1e-4, "{c}: {} vs {fd}", analytic[c]);
        }
    }
}
