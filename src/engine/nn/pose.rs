//! Per-image camera pose corrections in the flat parameter buffer (design
//! `real-captures.md` 2.7): six numbers per image, `δ_i = (τ_i, ω_i)`,
//! zero at first, so Adam, checkpoints, resuming and the divergence guard
//! treat them as any other parameter.
//!
//! The parametrisation is nerfstudio's `SO3xR3`: a model-space training ray
//! of image `i` becomes `o' = o + τ_i`, `d' = R(ω_i) d` (a rotation about
//! the camera centre in model axes, and a translation). Gradients come back
//! per ray as `∂L/∂o'` and `∂L/∂d'` ([`Correction::backward`]):
//! `∂L/∂τ = ∂L/∂o'` and `∂L/∂ω = J_l(ω)ᵀ (d' × ∂L/∂d')`, since a change
//! `δω` turns `d'` by `(J_l δω) × d'`.

use std::ops::Range;

use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::geometry::so3::{self, Mat3};
use crate::engine::nn::linear::ParamLayout;

/// Parameters per image: the translation `τ` then the rotation vector `ω`.
pub const PER_IMAGE: usize = 6;

/// The block of pose corrections: one row of [`PER_IMAGE`] values per
/// image, for `images` images.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseRefine {
    pub range: Range<usize>,
    pub images: usize,
}

/// One image's correction, read from the parameters, with its rotation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correction {
    /// The image's row (its parameters are `range.start + 6 image ..`).
    pub image: u32,
    pub tau: [f64; 3],
    pub omega: [f64; 3],
    pub rotation: Mat3,
}

impl PoseRefine {
    /// Lays out `images` rows named `name` (zero-initialised: the buffer
    /// starts at 0 and nothing else writes them before training).
    pub fn new(layout: &mut ParamLayout, name: &str, images: usize) -> Self {
        Self { range: layout.add(name, images * PER_IMAGE), images }
    }

    /// Image `image`'s correction; `None` for an image without a row (it is
    /// trained uncorrected) or a parameter buffer too short.
    pub fn correction(&self, params: &[f32], image: u32) -> Option<Correction> {
        let row = self.row(image)?;
        let p = params.get(row)?;
        let tau = [p[0], p[1], p[2]].map(f64::from);
        let omega = [p[3], p[4], p[5]].map(f64::from);
        Some(Correction { image, tau, omega, rotation: so3::exp(omega) })
    }

    /// The range of image `image`'s parameters.
    pub fn row(&self, image: u32) -> Option<Range<usize>> {
        let i = image as usize;
        (i < self.images).then(|| self.range.start + PER_IMAGE * i..self.range.start + PER_IMAGE * (i + 1))
    }
}

impl Correction {
    /// The corrected ray: `o + τ`, `R(ω) d`.
    pub fn apply(&self, ray: &Ray) -> Ray {
        let o = [ray.origin.x, ray.origin.y, ray.origin.z].map(f64::from);
        let d = so3::apply(&self.rotation, [ray.dir.x, ray.dir.y, ray.dir.z].map(f64::from));
        let v = |a: [f64; 3]| Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32);
        Ray { origin: v(std::array::from_fn(|k| o[k] + self.tau[k])), dir: v(d) }
    }

    /// Adds to `grads` (the whole parameter buffer) the gradient of the
    /// corrections given a corrected ray's direction `dir` and the loss's
    /// gradients with respect to its origin and direction. Skips a
    /// non-finite gradient (the trainer's guard sees the loss instead).
    pub fn backward(&self, pose: &PoseRefine, dir: [f64; 3], d_origin: [f64; 3], d_dir: [f64; 3], grads: &mut [f32]) {
        let Some(row) = pose.row(self.image) else { return };
        let d_omega = so3::apply_transposed(&so3::left_jacobian(self.omega), so3::cross(dir, d_dir));
        let all = d_origin.into_iter().chain(d_omega);
        if all.clone().all(f64::is_finite)
            && let Some(g) = grads.get_mut(row)
        {
            for (g, v) in g.iter_mut().zip(all) {
                *g += v as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn block() -> (PoseRefine, Vec<f32>) {
        let mut layout = ParamLayout::default();
        layout.add("before", 5);
        let pose = PoseRefine::new(&mut layout, "pose", 3);
        let mut params = vec![0.0f32; layout.len];
        params[pose.row(1).unwrap()].copy_from_slice(&[0.1, -0.2, 0.3, 0.02, -0.01, 0.03]);
        (pose, params)
    }

    /// Rows sit after what was laid out before, six per image; images
    /// beyond the block have none.
    #[test]
    fn rows_are_laid_out_in_order() {
        let (pose, params) = block();
        assert_eq!((pose.range.clone(), pose.row(0), pose.row(2)), (5..23, Some(5..11), Some(17..23)));
        assert!(pose.row(3).is_none() && pose.correction(&params, 3).is_none());
        assert!(pose.correction(&params[..10], 1).is_none(), "a short buffer gives no correction");
    }

    /// A zero row leaves rays as they are, bit for bit; a row moves the
    /// origin by `τ` and turns the direction by `exp(ω)`.
    #[test]
    fn corrections_move_origins_and_turn_directions() {
        let (pose, params) = block();
        let ray = Ray { origin: Vec3::new(0.5, -1.0, 2.0), dir: Vec3::new(0.6, 0.0, -0.8) };
        assert_eq!(pose.correction(&params, 0).unwrap().apply(&ray), ray);
        let c = pose.correction(&params, 1).unwrap();
        let moved = c.apply(&ray);
        assert!((moved.origin - Vec3::new(0.6, -1.2, 2.3)).norm() < 1e-6, "{moved:?}");
        assert!((moved.dir.norm() - 1.0).abs() < 1e-6, "rotations keep lengths");
        let want = so3::apply(&so3::exp([0.02, -0.01, 0.03]), [0.6, 0.0, -0.8]);
        assert!((0..3).all(|k| (f64::from([moved.dir.x, moved.dir.y, moved.dir.z][k]) - want[k]).abs() < 1e-7));
    }

    /// The gradient of `L = a · o' + b · d'` by central differences in f64
    /// over the six parameters of a row.
    #[test]
    fn backward_matches_finite_differences() {
        let (pose, params) = block();
        let (a, b) = ([0.3, -0.7, 1.1], [-0.4, 0.9, 0.25]);
        let d = [0.48, 0.6, -0.64];
        let loss = |row: [f64; 6]| {
            let o = [row[0], row[1], row[2]];
            let dd = so3::apply(&so3::exp([row[3], row[4], row[5]]), d);
            (0..3).map(|k| a[k] * o[k] + b[k] * dd[k]).sum::<f64>()
        };
        let c = pose.correction(&params, 1).unwrap();
        let mut grads = vec![0.0f32; params.len()];
        let d_prime = so3::apply(&c.rotation, d);
        c.backward(&pose, d_prime, a, b, &mut grads);
        let row: [f64; 6] = std::array::from_fn(|k| f64::from(params[pose.row(1).unwrap()][k]));
        for k in 0..6 {
            let h = 1e-6;
            let (mut up, mut down) = (row, row);
            up[k] += h;
            down[k] -= h;
            let num = (loss(up) - loss(down)) / (2.0 * h);
            let ana = f64::from(grads[pose.row(1).unwrap()][k]);
            assert!((num - ana).abs() < 1e-6 * (1.0 + num.abs()), "parameter {k}: FD {num}, analytic {ana}");
        }
        assert!(grads[..11].iter().chain(&grads[17..]).all(|&g| g == 0.0), "only image 1's row");
    }
}
