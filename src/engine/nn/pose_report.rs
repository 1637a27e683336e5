//! What pose refinement did (design `real-captures.md` 2.7, "Gauge and
//! report"): the common drift of all cameras, which the photographs cannot
//! see but which misplaces held-out cameras, and how far the cameras moved
//! with and without it.
//!
//! A drift of the whole rig by a small rotation `ω_g` about the origin and
//! a translation `t_g` moves camera `i` (centre `c_i`) by
//! `τ_i = ω_g × c_i + t_g` and turns it by `ω_i = ω_g`. With
//! `ω_i = ω_g + ε_i` and `τ_i = ω_g × c_i + t_g + η_i`, least squares gives
//! `ω_g = mean ω_i` and then `t_g = mean (τ_i - ω_g × c_i)`.

use crate::engine::geometry::so3;
use crate::engine::nn::pose::{Correction, PoseRefine};

/// The rig's common drift (model space).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Gauge {
    pub omega: [f64; 3],
    pub t: [f64; 3],
}

impl Gauge {
    /// The drift of the images `centres` lists (image, camera centre in
    /// model space) under `pose`'s corrections; zero for no images.
    pub fn fit(pose: &PoseRefine, params: &[f32], centres: &[(u32, [f64; 3])]) -> Self {
        let rows: Vec<(Correction, [f64; 3])> =
            centres.iter().filter_map(|&(i, c)| Some((pose.correction(params, i)?, c))).collect();
        if rows.is_empty() {
            return Self::default();
        }
        let n = rows.len() as f64;
        let mean = |f: &dyn Fn(&Correction, [f64; 3]) -> [f64; 3]| {
            rows.iter().fold([0.0; 3], |acc, (c, x)| {
                let v = f(c, *x);
                std::array::from_fn(|k| acc[k] + v[k] / n)
            })
        };
        let omega = mean(&|c, _| c.omega);
        let t = mean(&|c, x| {
            let turned = so3::cross(omega, x);
            std::array::from_fn(|k| c.tau[k] - turned[k])
        });
        Self { omega, t }
    }

    /// A camera at `centre` (model space) moved by the drift: its
    /// translation `ω_g × c + t_g`.
    pub fn translation_at(&self, centre: [f64; 3]) -> [f64; 3] {
        let turned = so3::cross(self.omega, centre);
        std::array::from_fn(|k| turned[k] + self.t[k])
    }
}

/// Mean and largest moves of the cameras.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PoseMoves {
    /// Translation, in percent of the cameras' distance from the focus.
    pub translation_mean_pct: f64,
    pub translation_max_pct: f64,
    /// Rotation, in degrees.
    pub rotation_mean_deg: f64,
    pub rotation_max_deg: f64,
}

/// How far refinement moved the training cameras: as they are (`raw`), and
/// with the common drift taken out (`relative`), and that drift (its
/// translation at the origin, where the cameras look, and its rotation).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PoseReport {
    /// Images the report covers (those trained on).
    pub images: usize,
    pub raw: PoseMoves,
    pub relative: PoseMoves,
    pub drift_translation_pct: f64,
    pub drift_rotation_deg: f64,
}

impl PoseReport {
    /// The report of `centres`' images (as [`Gauge::fit`] takes them), for
    /// cameras `radius` model units from the focus.
    pub fn new(pose: &PoseRefine, params: &[f32], centres: &[(u32, [f64; 3])], radius: f64) -> Self {
        let gauge = Gauge::fit(pose, params, centres);
        let pct = 100.0 / radius;
        let (mut raw, mut relative) = (Vec::new(), Vec::new());
        for &(i, c) in centres {
            let Some(k) = pose.correction(params, i) else { continue };
            raw.push((so3::norm(k.tau) * pct, so3::norm(k.omega).to_degrees()));
            let drift = gauge.translation_at(c);
            let eta: [f64; 3] = std::array::from_fn(|a| k.tau[a] - drift[a]);
            let eps: [f64; 3] = std::array::from_fn(|a| k.omega[a] - gauge.omega[a]);
            relative.push((so3::norm(eta) * pct, so3::norm(eps).to_degrees()));
        }
        Self {
            images: raw.len(),
            raw: moves(&raw),
            relative: moves(&relative),
            drift_translation_pct: so3::norm(gauge.t) * pct,
            drift_rotation_deg: so3::norm(gauge.omega).to_degrees(),
        }
    }
}

/// Means and maxima of (translation, rotation) pairs.
fn moves(v: &[(f64, f64)]) -> PoseMoves {
    let n = v.len().max(1) as f64;
    PoseMoves {
        translation_mean_pct: v.iter().map(|m| m.0).sum::<f64>() / n,
        translation_max_pct: v.iter().map(|m| m.0).fold(0.0, f64::max),
        rotation_mean_deg: v.iter().map(|m| m.1).sum::<f64>() / n,
        rotation_max_deg: v.iter().map(|m| m.1).fold(0.0, f64::max),
    }
}

impl std::fmt::Display for PoseReport {
    /// One line, e.g. "poses of 30 images moved: mean 0.40% of the camera
    /// distance (max 1.30%), 0.07 deg (max 0.31 deg); without the common
    /// drift (0.20%, 0.05 deg): mean 0.10% (max 0.50%), 0.02 deg (max
    /// 0.10 deg)".
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (r, q) = (&self.raw, &self.relative);
        write!(
            f,
            "poses of {} images moved: mean {:.2}% of the camera distance (max {:.2}%), {:.3} deg (max {:.3} deg); \
             without the common drift ({:.2}%, {:.3} deg): mean {:.2}% (max {:.2}%), {:.3} deg (max {:.3} deg)",
            self.images,
            r.translation_mean_pct,
            r.translation_max_pct,
            r.rotation_mean_deg,
            r.rotation_max_deg,
            self.drift_translation_pct,
            self.drift_rotation_deg,
            q.translation_mean_pct,
            q.translation_max_pct,
            q.rotation_mean_deg,
            q.rotation_max_deg
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::nn::linear::ParamLayout;
    use crate::engine::rng::Rng;

    /// The images trained on and their camera centres.
    type Centres = Vec<(u32, [f64; 3])>;

    /// Cameras on a ring of radius 2 with corrections made of a known drift
    /// plus each camera's own small move.
    fn drifted(own: f64) -> (PoseRefine, Vec<f32>, Centres, Gauge) {
        let mut layout = ParamLayout::default();
        let pose = PoseRefine::new(&mut layout, "pose", 10);
        let mut params = vec![0.0f32; layout.len];
        let gauge = Gauge { omega: [0.01, -0.02, 0.005], t: [0.03, 0.0, -0.01] };
        let mut rng = Rng::new(5);
        let mut centres = Vec::new();
        // Images 0-7 are trained; 8 and 9 are held out (their rows stay 0).
        for i in 0..8u32 {
            let a = f64::from(i) * 0.8;
            let c = [2.0 * a.cos(), 2.0 * a.sin(), 0.3];
            let drift = gauge.translation_at(c);
            let row: Vec<f32> = (0..6)
                .map(|k| {
                    let base = if k < 3 { drift[k] } else { gauge.omega[k - 3] };
                    (base + own * f64::from(rng.normal())) as f32
                })
                .collect();
            params[pose.row(i).unwrap()].copy_from_slice(&row);
            centres.push((i, c));
        }
        (pose, params, centres, gauge)
    }

    /// A pure drift is found exactly and leaves nothing relative.
    #[test]
    fn a_common_drift_is_recovered() {
        let (pose, params, centres, want) = drifted(0.0);
        let g = Gauge::fit(&pose, &params, &centres);
        for k in 0..3 {
            assert!((g.omega[k] - want.omega[k]).abs() < 1e-7 && (g.t[k] - want.t[k]).abs() < 1e-7, "{g:?}");
        }
        let r = PoseReport::new(&pose, &params, &centres, 2.0);
        assert_eq!(r.images, 8);
        assert!(r.relative.translation_max_pct < 1e-4 && r.relative.rotation_max_deg < 1e-5, "{r:?}");
        assert!(r.raw.rotation_mean_deg > 1.0 && r.raw.translation_mean_pct > 1.0, "{r:?}");
        assert!((r.drift_rotation_deg - so3::norm(want.omega).to_degrees()).abs() < 1e-5);
        assert!((r.drift_translation_pct - 50.0 * so3::norm(want.t)).abs() < 1e-4);
    }

    /// With each camera's own moves on top, the relative moves are theirs:
    /// smaller than the raw ones, and of their size.
    #[test]
    fn own_moves_remain_relative() {
        let (pose, params, centres, _) = drifted(1e-3);
        let r = PoseReport::new(&pose, &params, &centres, 2.0);
        assert!(r.relative.rotation_mean_deg < r.raw.rotation_mean_deg, "{r:?}");
        // |N(0, 1e-3)^3| is about 1.6e-3 rad (0.09 deg), 0.08% of 2 units.
        assert!((0.02..0.3).contains(&r.relative.rotation_mean_deg), "{r:?}");
        assert!((0.01..0.3).contains(&r.relative.translation_mean_pct), "{r:?}");
        let line = r.to_string();
        assert!(line.starts_with("poses of 8 images moved: mean "), "{line}");
    }

    #[test]
    fn no_images_give_zeros() {
        let (pose, params, _, _) = drifted(0.0);
        assert_eq!(Gauge::fit(&pose, &params, &[]), Gauge::default());
        assert_eq!(PoseReport::new(&pose, &params, &[], 1.0), PoseReport::default());
    }
}
