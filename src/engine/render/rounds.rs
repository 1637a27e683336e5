//! The one render loop every model uses: the rays of a chunk are marched
//! together in rounds of a few samples per ray. Each round evaluates the
//! densities of the new samples, composites them in order, and retires rays
//! whose transmittance falls below `min_transmittance` (early termination).
//! Samples whose weights, summed along their ray, stay below
//! `max_dropped_weight` are never coloured (the dropped-colour rule: a pixel
//! changes by at most that much); the rest are coloured in one pass at the
//! end.

use super::composite::{Transmittance, mark_median};
use crate::engine::batch::{BatchStats, RayOutput};
use crate::engine::fields::{Field, Points};
use crate::engine::sampling::{RaySampler, Samples};

/// How the loop runs.
#[derive(Clone, Copy, Debug)]
pub struct RoundSettings {
    /// Samples per ray and round.
    pub round: usize,
    /// Transmittance below which a ray stops.
    pub min_transmittance: f32,
    /// Weight per ray that may go uncoloured (0: colour every sample with a
    /// weight).
    pub max_dropped_weight: f32,
}

/// Where each ray is.
#[derive(Clone, Copy)]
struct RayState {
    /// Transmittance so far.
    along: Transmittance,
    /// Weight of the samples left uncoloured.
    dropped: f32,
    /// Where the opacity reached one half (`Composite::median`); 0 until then.
    median: f32,
    live: bool,
}

/// The samples that get a colour: their ray, weight and distance, the rows
/// the field saved for them and their directions.
#[derive(Default)]
struct Kept {
    ray: Vec<usize>,
    w: Vec<f32>,
    t: Vec<f32>,
    rows: Vec<f32>,
    dirs: Vec<f32>,
}

/// Renders the `out.len()` rays whose samples `sampler` hands out, composited
/// on `background`. `samples` and `ctx` are scratch.
#[allow(clippy::too_many_arguments)]
pub fn render_in_rounds<F: Field>(
    field: &F,
    params: &[f32],
    sampler: &mut impl RaySampler,
    settings: RoundSettings,
    background: [f32; 3],
    ctx: &mut F::Ctx,
    samples: &mut Samples,
    out: &mut [RayOutput],
) -> BatchStats {
    let mut stats = BatchStats { rays: out.len() as u64, ..Default::default() };
    let mut state: Vec<RayState> = (0..out.len())
        .map(|r| RayState { along: Transmittance::default(), dropped: 0.0, median: 0.0, live: sampler.has_samples(r) })
        .collect();
    let mut kept = Kept::default();
    let mut owners = Vec::new();
    loop {
        next_samples(sampler, settings.round, &mut state, samples, &mut owners);
        stats.skipped += std::mem::take(&mut samples.skipped);
        if samples.is_empty() {
            break;
        }
        stats.samples += samples.len() as u64;
        field.density(params, Points { pos: &samples.pos, dirs: &samples.dirs, image: &[] }, ctx);
        stats.skipped += composite_round(field, ctx, samples, &owners, settings, &mut state, &mut kept);
    }
    finish(field, params, ctx, kept, &state, background, out);
    stats
}

/// The next round's samples of every live ray, one span each; `owners`
/// gets the ray of each span.
fn next_samples(
    sampler: &mut impl RaySampler,
    round: usize,
    state: &mut [RayState],
    samples: &mut Samples,
    owners: &mut Vec<usize>,
) {
    samples.clear();
    owners.clear();
    for (r, st) in state.iter_mut().enumerate() {
        if !st.live {
            continue;
        }
        let start = samples.len();
        st.live = sampler.next(r, round, samples);
        if samples.len() > start {
            samples.end_span(start);
            owners.push(r);
        }
    }
}

/// Composites one round's densities in order along each ray, retiring rays
/// that became opaque and keeping the samples that need a colour; returns
/// the samples left behind by retired rays.
fn composite_round<F: Field>(
    field: &F,
    ctx: &F::Ctx,
    samples: &Samples,
    owners: &[usize],
    settings: RoundSettings,
    state: &mut [RayState],
    kept: &mut Kept,
) -> u64 {
    let sigma = field.sigma(ctx);
    let mut skipped = 0;
    for (&r, &(o, n)) in owners.iter().zip(&samples.spans) {
        let st = &mut state[r];
        for i in o..o + n {
            if st.along.value() < settings.min_transmittance {
                st.live = false;
                skipped += (o + n - i) as u64;
                break;
            }
            let w = st.along.step(sigma[i], samples.delta[i], false);
            mark_median(&mut st.median, st.along.value(), samples.t[i]);
            if st.dropped + w <= settings.max_dropped_weight {
                // Nearly empty space: its colour cannot matter.
                st.dropped += w;
                continue;
            }
            kept.ray.push(r);
            kept.w.push(w);
            kept.t.push(samples.t[i]);
            field.save_row(ctx, i, &mut kept.rows);
            kept.dirs.extend_from_slice(&samples.dirs[3 * i..3 * i + 3]);
        }
        if st.along.value() < settings.min_transmittance {
            st.live = false;
        }
    }
    skipped
}

/// Colours the kept samples in one pass and writes each ray's colour,
/// depth and opacity, over the background.
fn finish<F: Field>(
    field: &F,
    params: &[f32],
    ctx: &mut F::Ctx,
    kept: Kept,
    state: &[RayState],
    background: [f32; 3],
    out: &mut [RayOutput],
) {
    out.fill(RayOutput::default());
    if !kept.ray.is_empty() {
        field.color_rows(params, kept.rows, &kept.dirs, ctx);
        let rgb = field.rgb(ctx);
        for (i, &r) in kept.ray.iter().enumerate() {
            let o = &mut out[r];
            for ch in 0..3 {
                o.rgb[ch] += kept.w[i] * rgb[3 * i + ch];
            }
            o.depth += kept.w[i] * kept.t[i];
        }
    }
    for (o, st) in out.iter_mut().zip(state) {
        let trans = st.along.value();
        o.opacity = 1.0 - trans;
        o.median = st.median;
        for ch in 0..3 {
            o.rgb[ch] += trans * background[ch];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::fields::toy::{Toy, ToyCtx};
    use crate::engine::geometry::math::{Ray, Vec3};
    use crate::engine::render::composite::{CompositeOptions, RaySamples, composite};

    const W: [f32; 8] = [1.5, -0.5, 0.8, 0.4, -1.0, 0.7, 0.3, -0.2];
    const BG: [f32; 3] = [0.9, 0.2, 0.6];

    /// Fixed samples per ray, `delta` apart.
    struct Fixed {
        rays: Vec<Ray>,
        t: Vec<Vec<f32>>,
        next: Vec<usize>,
    }

    impl RaySampler for Fixed {
        fn has_samples(&self, r: usize) -> bool {
            !self.t[r].is_empty()
        }
        fn next(&mut self, r: usize, limit: usize, out: &mut Samples) -> bool {
            let end = (self.next[r] + limit).min(self.t[r].len());
            for &t in &self.t[r][self.next[r]..end] {
                out.push(&self.rays[r], t, 0.05);
            }
            self.next[r] = end;
            end < self.t[r].len()
        }
    }

    /// Five rays through the toy field: 40, 7, 0 (background), 1 and 90
    /// samples.
    fn sampler() -> Fixed {
        let counts = [40usize, 7, 0, 1, 90];
        let rays = (0..counts.len())
            .map(|k| Ray { origin: Vec3::new(-1.0, 0.1 * k as f32, 0.2), dir: Vec3::new(0.8, 0.0, 0.6) })
            .collect();
        let t = counts.iter().map(|&n| (0..n).map(|i| 0.5 + 0.05 * i as f32).collect()).collect();
        Fixed { rays, t, next: vec![0; counts.len()] }
    }

    /// Each ray composited whole by the compositor.
    fn reference() -> Vec<RayOutput> {
        let s = sampler();
        (0..s.rays.len())
            .map(|r| {
                let mut m = Samples::default();
                for &t in &s.t[r] {
                    m.push(&s.rays[r], t, 0.05);
                }
                let mut ctx = ToyCtx::default();
                Toy.density(&W, Points { pos: &m.pos, dirs: &m.dirs, image: &[] }, &mut ctx);
                Toy.color(&W, &m.dirs, &mut ctx);
                let mut w = vec![0.0; m.len()];
                let s = RaySamples::new(Toy.sigma(&ctx), Toy.rgb(&ctx), &m.t, &m.delta).unwrap();
                let opts = CompositeOptions { background: BG, ..Default::default() };
                let c = composite(s, &opts, &mut w).unwrap();
                RayOutput { rgb: c.rgb, depth: c.depth, opacity: c.opacity, median: c.median }
            })
            .collect()
    }

    fn render(round: usize, min_transmittance: f32, max_dropped_weight: f32) -> (Vec<RayOutput>, BatchStats) {
        let settings = RoundSettings { round, min_transmittance, max_dropped_weight };
        let mut out = vec![RayOutput::default(); 5];
        let (mut ctx, mut m) = (ToyCtx::default(), Samples::default());
        let stats = render_in_rounds(&Toy, &W, &mut sampler(), settings, BG, &mut ctx, &mut m, &mut out);
        (out, stats)
    }

    #[test]
    fn without_termination_or_dropping_it_is_the_compositor_bit_for_bit_in_any_rounds() {
        let want = reference();
        assert_eq!(want[2], RayOutput { rgb: BG, depth: 0.0, opacity: 0.0, median: 0.0 });
        assert!(want[4].opacity > 0.9, "the long ray becomes opaque: {:?}", want[4]);
        for round in [1, 3, 16, 1000] {
            let (got, stats) = render(round, 0.0, 0.0);
            assert_eq!(got, want, "round {round}");
            assert_eq!((stats.rays, stats.samples), (5, 138));
        }
    }

    #[test]
    fn termination_and_dropping_change_a_pixel_by_at_most_their_thresholds() {
        let want = reference();
        for (min_t, drop) in [(1e-2f32, 0.0f32), (0.0, 0.05), (1e-2, 0.05)] {
            let (got, stats) = render(4, min_t, drop);
            for (g, w) in got.iter().zip(&want) {
                for k in 0..3 {
                    // Both cut weights from the sum; colours and the
                    // background are in [0, 1].
                    assert!((g.rgb[k] - w.rgb[k]).abs() <= min_t + drop + 1e-6, "{min_t} {drop}: {g:?} {w:?}");
                }
            }
            if min_t > 0.0 {
                // The long ray stops before its end.
                assert!(stats.samples < 138, "{stats:?}");
            }
        }
    }
}
