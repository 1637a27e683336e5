//! The one render loop every model uses: the rays of a chunk are marched
//! together in rounds of a few samples per ray. Each round evaluates the
//! densities of the new samples, composites them in order, and retires rays
//! whose transmittance falls below `min_transmittance` (early termination).
//! Samples whose weights, summed along their ray, stay below
//! `max_dropped_weight` are never coloured (the dropped-colour rule: a pixel
//! changes by at most that much); the rest are coloured in one pass at the
//! end.

use super::composite::optical_depth;
use crate::engine::fields::{Field, Points};
use crate::engine::models::{BatchStats, RayOutput};
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
    /// Optical depth so far.
    tau: f32,
    /// Weight of the samples left uncoloured.
    dropped: f32,
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
    let mut state: Vec<RayState> =
        (0..out.len()).map(|r| RayState { tau: 0.0, dropped: 0.0, live: sampler.has_samples(r) }).collect();
    let mut kept = Kept::default();
    let mut owners = Vec::new();
    loop {
        samples.clear();
        owners.clear();
        for (r, st) in state.iter_mut().enumerate() {
            if !st.live {
                continue;
            }
            let start = samples.len();
            st.live = sampler.next(r, settings.round, samples);
            if samples.len() > start {
                samples.end_span(start);
                owners.push(r);
            }
        }
        stats.skipped += std::mem::take(&mut samples.skipped);
        if samples.is_empty() {
            break;
        }
        stats.samples += samples.len() as u64;
        let pts = Points { pos: &samples.pos, dirs: &samples.dirs, image: &[] };
        field.density(params, pts, ctx);
        let sigma = field.sigma(ctx);
        for (&r, &(o, n)) in owners.iter().zip(&samples.spans) {
            let st = &mut state[r];
            for i in o..o + n {
                let trans = (-st.tau).exp();
                if trans < settings.min_transmittance {
                    st.live = false;
                    stats.skipped += (o + n - i) as u64;
                    break;
                }
                st.tau += optical_depth(sigma[i], samples.delta[i]);
                let w = trans - (-st.tau).exp();
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
            if (-st.tau).exp() < settings.min_transmittance {
                st.live = false;
            }
        }
    }
    out.fill(RayOutput::default());
    if !kept.ray.is_empty() {
        field.color_rows(params, std::mem::take(&mut kept.rows), &kept.dirs, ctx);
        let rgb = field.rgb(ctx);
        for (i, &r) in kept.ray.iter().enumerate() {
            let o = &mut out[r];
            for ch in 0..3 {
                o.rgb[ch] += kept.w[i] * rgb[3 * i + ch];
            }
            o.depth += kept.w[i] * kept.t[i];
        }
    }
    for (o, st) in out.iter_mut().zip(&state) {
        let trans = (-st.tau).exp();
        o.opacity = 1.0 - trans;
        for ch in 0..3 {
            o.rgb[ch] += trans * background[ch];
        }
    }
    stats
}
