//! Floater cleanup: the Gaussians a viewer should not be given, removed
//! before export.
//!
//! - **Transparent**: opacity under `min_opacity` (1/255 by default: the
//!   rasteriser, ours and Spark's alike, skips any pixel's alpha under
//!   1/255, and a Gaussian's alpha never exceeds its opacity, so these draw
//!   nothing at all).
//! - **Isolated**: specks in empty space. A Gaussian is isolated when its
//!   `neighbours`-th nearest centre is farther than `isolation` times the
//!   reach (three standard deviations of the largest axis) of the two
//!   together: it and the Gaussians about it overlap nothing. Measured
//!   against its own size, not the cloud's average spacing, so a sparse but
//!   large background (a far wall drawn by big Gaussians) is kept.
//! - **Oversized far from the rest**: a Gaussian whose reach is over
//!   `max_reach` times the radius holding 99% of the centres (about the
//!   whole scene's), centred outside the radius holding 90%: the haze a
//!   bake leaves where the photos see little. A background wall of big
//!   Gaussians is within the 99%, and each is smaller than all of it.
//!
//! Each rule is a setting; a setting of zero turns its rule off.

use rstar::{RTree, primitives::GeomWithData};

use super::SplatsModel;
use super::gaussians::sigmoid;
use crate::engine::geometry::math::Vec3;
use crate::engine::models::{Model, ModelError};

/// The thresholds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CleanupSettings {
    /// Opacity under which a Gaussian is removed (0 to 1).
    pub min_opacity: f32,
    /// The neighbour counted for isolation (1 or more; 0 turns it off).
    pub neighbours: usize,
    /// How many reaches away that neighbour makes a Gaussian isolated.
    pub isolation: f32,
    /// The reach, in radii of the central 99% of centres, over which a
    /// Gaussian outside the central 90% is removed (0 turns it off).
    pub max_reach: f32,
}

impl Default for CleanupSettings {
    fn default() -> Self {
        Self { min_opacity: 1.0 / 255.0, neighbours: 4, isolation: 4.0, max_reach: 1.0 }
    }
}

impl CleanupSettings {
    /// No rule at all.
    pub const OFF: Self = Self { min_opacity: 0.0, neighbours: 0, isolation: 0.0, max_reach: 0.0 };

    /// The settings' errors, each naming its field.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(0.0..=1.0).contains(&self.min_opacity) {
            return Err(("min_opacity", format!("{} is not between 0 and 1", self.min_opacity)));
        }
        if self.neighbours > 64 {
            return Err(("neighbours", format!("{} is over 64", self.neighbours)));
        }
        if !(self.isolation.is_finite() && self.isolation >= 0.0) {
            return Err(("isolation", format!("{} is not a number of reaches of 0 or more", self.isolation)));
        }
        if !(self.max_reach.is_finite() && self.max_reach >= 0.0) {
            return Err(("max_reach", format!("{} is not a number of radii of 0 or more", self.max_reach)));
        }
        Ok(())
    }
}

/// What a cleanup removed, by rule (a Gaussian counts under the first
/// rule, in the order above, that removes it).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Removed {
    pub transparent: usize,
    pub isolated: usize,
    pub oversized: usize,
}

impl Removed {
    pub fn total(&self) -> usize {
        self.transparent + self.isolated + self.oversized
    }
}

impl std::fmt::Display for Removed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} Gaussians removed ({} transparent, {} isolated, {} oversized far out)",
            self.total(),
            self.transparent,
            self.isolated,
            self.oversized
        )
    }
}

/// Why each Gaussian of `model` goes: `None` where it stays.
pub fn judge(model: &SplatsModel, s: &CleanupSettings) -> Vec<Option<Rule>> {
    let l = model.layout();
    let p = model.params();
    let centres: Vec<[f32; 3]> = (0..l.n).map(|i| l.get(p, i).mean).collect();
    let reach: Vec<f32> =
        (0..l.n).map(|i| 3.0 * l.get(p, i).log_scale.into_iter().fold(f32::MIN, f32::max).exp()).collect();
    let mut out: Vec<Option<Rule>> =
        (0..l.n).map(|i| (sigmoid(l.get(p, i).opacity_logit) < s.min_opacity).then_some(Rule::Transparent)).collect();
    if s.neighbours > 0 && s.isolation > 0.0 && l.n > s.neighbours {
        let tree = RTree::bulk_load(centres.iter().enumerate().map(|(i, c)| GeomWithData::new(*c, i)).collect());
        for i in 0..l.n {
            if out[i].is_some() {
                continue;
            }
            // The first is the Gaussian itself (or one at its very place).
            let Some(nb) = tree.nearest_neighbor_iter(centres[i]).nth(s.neighbours) else { continue };
            let d = dist(&centres[i], nb.geom());
            if d > s.isolation * (reach[i] + reach[nb.data]) {
                out[i] = Some(Rule::Isolated);
            }
        }
    }
    if s.max_reach > 0.0 && l.n > 0 {
        let mut mid = [0.0; 3];
        for (c, m) in mid.iter_mut().enumerate() {
            let mut v: Vec<f32> = centres.iter().map(|p| p[c]).collect();
            *m = *v.select_nth_unstable_by(l.n / 2, f32::total_cmp).1;
        }
        let far: Vec<f32> = centres.iter().map(|c| dist(c, &mid)).collect();
        let mut sorted = far.clone();
        sorted.sort_unstable_by(f32::total_cmp);
        let (r90, r99) = (sorted[(l.n * 9) / 10], sorted[((l.n * 99) / 100).min(l.n - 1)]);
        for i in 0..l.n {
            if out[i].is_none() && far[i] > r90 && reach[i] > s.max_reach * r99 {
                out[i] = Some(Rule::Oversized);
            }
        }
    }
    out
}

/// The rule that removes a Gaussian.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rule {
    Transparent,
    Isolated,
    Oversized,
}

fn dist(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    (Vec3::from_array(*a) - Vec3::from_array(*b)).norm()
}

/// `model` without the Gaussians `s` removes, and what went.
pub fn cleanup(model: &SplatsModel, s: &CleanupSettings) -> Result<(SplatsModel, Removed), ModelError> {
    let verdict = judge(model, s);
    let mut removed = Removed::default();
    let mut keep = Vec::with_capacity(verdict.len());
    for (i, v) in verdict.iter().enumerate() {
        match v {
            None => keep.push(i),
            Some(Rule::Transparent) => removed.transparent += 1,
            Some(Rule::Isolated) => removed.isolated += 1,
            Some(Rule::Oversized) => removed.oversized += 1,
        }
    }
    Ok((model.keeping(&keep)?, removed))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::math::{Aabb, Vec3};
    use crate::engine::models::splats::SplatsConfig;
    use crate::engine::models::splats::gaussians::Layout;

    /// Gaussians given as (centre, standard deviation, opacity), isotropic.
    fn model(g: &[([f32; 3], f32, f32)]) -> SplatsModel {
        let scene = crate::engine::geometry::scene::Scene::from_bounds(
            Aabb { min: Vec3::new(-1.0, -1.0, -1.0), max: Vec3::new(1.0, 1.0, 1.0) },
            0.0,
            10.0,
        );
        let l = Layout::new(g.len(), 0);
        let mut p = vec![0.0; l.len()];
        for (i, &(c, s, o)) in g.iter().enumerate() {
            p[3 * i..3 * i + 3].copy_from_slice(&c);
            p[3 * l.n + 3 * i..3 * l.n + 3 * i + 3].fill(s.ln());
            p[6 * l.n + 4 * i] = 1.0;
            p[10 * l.n + i] = (o / (1.0 - o)).ln();
        }
        SplatsModel::from_parts(SplatsConfig { sh_degree: 0, ..Default::default() }, scene, p).unwrap()
    }

    /// A surface: a 30x30 grid of overlapping Gaussians on z = 0 (spacing
    /// 0.02, deviation 0.01), and far behind it a sparse wall of big ones
    /// (spacing 0.5, deviation 0.2).
    fn scene() -> Vec<([f32; 3], f32, f32)> {
        let mut g = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                g.push(([i as f32 * 0.02 - 0.3, j as f32 * 0.02 - 0.3, 0.0], 0.01, 0.8));
            }
        }
        for i in 0..6 {
            for j in 0..6 {
                g.push(([i as f32 * 0.5 - 1.25, j as f32 * 0.5 - 1.25, 3.0], 0.2, 0.9));
            }
        }
        g
    }

    #[test]
    fn floaters_go_and_the_scene_stays() {
        let mut g = scene();
        let clean = g.len();
        g.push(([0.0, 0.0, 0.01], 0.01, 0.002)); // transparent, on the surface
        g.push(([0.1, 0.2, 1.2], 0.01, 0.9)); // a speck in the empty space between
        g.push(([-0.2, 0.1, 0.8], 0.005, 0.5)); // another
        g.push(([0.0, 0.0, -4.0], 3.0, 0.3)); // a huge blob far out
        let (m, removed) = cleanup(&model(&g), &CleanupSettings::default()).unwrap();
        assert_eq!(removed, Removed { transparent: 1, isolated: 2, oversized: 1 });
        assert_eq!(m.layout().n, clean);
        // What stays is the surface and the wall, in order, unchanged.
        let (a, b) = (model(&g[..clean]), m);
        assert_eq!(a.params(), b.params());
    }

    #[test]
    fn a_clean_scene_loses_nothing_and_off_removes_nothing() {
        let (m, removed) = cleanup(&model(&scene()), &CleanupSettings::default()).unwrap();
        assert_eq!((removed.total(), m.layout().n), (0, scene().len()));
        let mut g = scene();
        g.push(([0.1, 0.2, 1.2], 0.01, 0.0001));
        let (m, removed) = cleanup(&model(&g), &CleanupSettings::OFF).unwrap();
        assert_eq!((removed.total(), m.layout().n), (0, g.len()));
    }

    #[test]
    fn settings_are_checked_by_field() {
        assert_eq!(CleanupSettings::default().check(), Ok(()));
        let bad = |s: CleanupSettings| s.check().unwrap_err().0;
        assert_eq!(bad(CleanupSettings { min_opacity: 1.5, ..Default::default() }), "min_opacity");
        assert_eq!(bad(CleanupSettings { isolation: f32::NAN, ..Default::default() }), "isolation");
        assert_eq!(bad(CleanupSettings { max_reach: -1.0, ..Default::default() }), "max_reach");
        assert_eq!(bad(CleanupSettings { neighbours: 1000, ..Default::default() }), "neighbours");
    }
}
