//! The background of a capture taken all around: what lies farther from
//! the cameras' focus than the cameras themselves (the room of a
//! walk-around) keeps a colour of degree 0.
//!
//! Each part of that room is seen by few photos, from one side, so the
//! view-dependent terms of its Gaussians fit those photos and extrapolate
//! to a new view as saturated blotches (blue, green, pink on a grey wall);
//! the field, smooth by construction, draws a plain wall there. Low-order
//! colour for far content is what Hierarchical 3DGS's sky box and
//! WildGaussians' sphere give it. A forward-facing capture has no such
//! outside (every camera looks the same way), and keeps every term.

use crate::engine::dataset::Dataset;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::splats::gaussians::Layout;

/// The ball around the focus beyond which Gaussians are background (model
/// units).
pub(super) struct Background {
    focus: [f32; 3],
    radius: f32,
}

impl Background {
    /// The ball of `ds`'s training cameras (their focus, their median
    /// distance from it) in `scene`'s model units; `None` for a capture
    /// with no rig or a forward-facing one.
    pub fn of(ds: &Dataset, scene: &Scene) -> Option<Self> {
        let rig = ds.rig().filter(|r| !r.forward_facing)?;
        Some(Self { focus: scene.point_to_model(rig.focus), radius: rig.radius * scene.scale })
    }

    /// Whether model-space point `at` is background.
    pub fn holds(&self, at: [f32; 3]) -> bool {
        let d2: f32 = (0..3).map(|c| (at[c] - self.focus[c]).powi(2)).sum();
        d2 > self.radius * self.radius
    }

    /// The Gaussians of `params` (laid out by `l`) that are background.
    pub fn members(&self, l: &Layout, params: &[f32]) -> Vec<usize> {
        (0..l.n).filter(|&i| self.holds([params[3 * i], params[3 * i + 1], params[3 * i + 2]])).collect()
    }
}

/// Zeroes the spherical-harmonic terms above degree 0 of Gaussians `which`
/// in `values` (parameters or their gradients, laid out by `l`).
pub(super) fn zero_rest(l: &Layout, values: &mut [f32], which: &[usize]) {
    let rest = l.sh_rest();
    let width = rest.len() / l.n.max(1);
    for &i in which {
        values[rest.start + width * i..rest.start + width * (i + 1)].fill(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussians_beyond_the_cameras_lose_their_higher_terms_and_no_other() {
        let bg = Background { focus: [1.0, 0.0, 0.0], radius: 2.0 };
        assert!(!bg.holds([1.0, 1.9, 0.0]));
        assert!(bg.holds([1.0, 0.0, -2.1]));
        // Three Gaussians of degree 1: the middle one 3 units out.
        let l = Layout::new(3, 1);
        let mut p: Vec<f32> = (0..l.len()).map(|k| k as f32 + 1.0).collect();
        p[..9].copy_from_slice(&[1.0, 0.5, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 1.0]);
        let which = bg.members(&l, &p);
        assert_eq!(which, vec![1]);
        let before = p.clone();
        zero_rest(&l, &mut p, &which);
        let rest = l.sh_rest();
        let w = rest.len() / 3;
        for k in 0..p.len() {
            let of_middle = rest.contains(&k) && (k - rest.start) / w == 1;
            assert_eq!(p[k], if of_middle { 0.0 } else { before[k] }, "value {k}");
        }
    }
}
