//! The fast model's sampler: constant steps of `dt` along each ray, clipped
//! to the scene box, through the cells the occupancy grid marks occupied
//! (empty cells are stepped over and counted as skipped).

use super::occupancy::OccupancyGrid;
use super::{RaySampler, Samples};
use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::rng::Rng;

/// Marches model-space rays through an occupancy grid.
#[derive(Clone, Copy)]
pub struct GridMarcher<'a> {
    pub scene: &'a Scene,
    pub grid: &'a OccupancyGrid,
    /// The step between samples.
    pub dt: f32,
    /// Samples per ray at most.
    pub max_samples: usize,
}

impl<'a> GridMarcher<'a> {
    /// All samples of each ray, one span per ray (empty for rays that miss
    /// the box), offset by a random fraction of a step with `rng` (training)
    /// or by half a step without.
    pub fn march(&self, rays: &[Ray], mut rng: Option<&mut Rng>, out: &mut Samples) {
        out.clear();
        for ray in rays {
            let start = out.len();
            if let Some((t0, t1)) = self.scene.clip(ray) {
                let jitter = rng.as_deref_mut().map_or(0.5, |r| r.f32());
                let mut t = t0 + jitter * self.dt;
                self.segment(ray, &mut t, t1, self.max_samples, out);
            }
            out.end_span(start);
        }
    }

    /// Appends up to `limit` samples of `ray` from `t` on (stepping over
    /// empty cells) and advances `t` past them; returns how many.
    fn segment(&self, ray: &Ray, t: &mut f32, t1: f32, limit: usize, out: &mut Samples) -> usize {
        let dt = self.dt;
        let gr = self.grid.grid_ray(ray);
        let (count, skipped) = self.grid.march(&gr, t, t1, dt, limit, |t| out.push(ray, t, dt));
        out.skipped += skipped;
        count
    }

    /// Hands out the samples of `rays` a few at a time (for rendering).
    pub fn rounds(self, rays: &'a [Ray]) -> MarchRounds<'a> {
        let state = rays
            .iter()
            .map(|r| match self.scene.clip(r) {
                Some((t0, t1)) => RayMarch { t: t0 + 0.5 * self.dt, end: t1, taken: 0, live: true },
                None => RayMarch { t: 0.0, end: 0.0, taken: 0, live: false },
            })
            .collect();
        MarchRounds { marcher: self, rays, state }
    }
}

/// Where each ray's march is.
struct RayMarch {
    t: f32,
    end: f32,
    taken: usize,
    live: bool,
}

/// [`GridMarcher`] as a [`RaySampler`].
pub struct MarchRounds<'a> {
    marcher: GridMarcher<'a>,
    rays: &'a [Ray],
    state: Vec<RayMarch>,
}

impl RaySampler for MarchRounds<'_> {
    fn has_samples(&self, r: usize) -> bool {
        self.state[r].live
    }

    fn next(&mut self, r: usize, limit: usize, out: &mut Samples) -> bool {
        let m = &self.marcher;
        let st = &mut self.state[r];
        let limit = limit.min(m.max_samples - st.taken);
        let n = m.segment(&self.rays[r], &mut st.t, st.end, limit, out);
        st.taken += n;
        st.live = n > 0 && st.t < st.end && st.taken < m.max_samples;
        st.live
    }
}
