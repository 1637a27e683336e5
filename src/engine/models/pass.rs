//! One training pass of a field over packed samples, shared by every model:
//! densities, optional culling of what early termination would not see,
//! colours, compositing, the L2 loss and the backward pass.

use crate::engine::batch::TrainRay;
use crate::engine::fields::{Field, Points};
use crate::engine::render::composite::{
    CompositeOptions, RaySamples, Upstream, composite, composite_backward, optical_depth,
};
use crate::engine::render::loss::l2;
use crate::engine::sampling::Samples;

/// Buffers of a pass, reused across passes by one thread.
#[derive(Default)]
pub struct PassBuffers {
    /// Compositing weight of each sample of the last pass (after culling),
    /// `[n]`: hierarchical samplers draw from these.
    pub weights: Vec<f32>,
    dsigma: Vec<f32>,
    drgb: Vec<f32>,
    keep: Vec<usize>,
    image: Vec<u32>,
}

/// What a pass measured.
#[derive(Clone, Copy, Debug, Default)]
pub struct PassStats {
    /// Sum over rays of the mean squared colour error.
    pub sq_err: f64,
    /// Samples the field evaluated.
    pub samples: u64,
    /// Samples culled behind the termination point.
    pub culled: u64,
}

/// Trains `field` on `rays` whose samples are `samples` (one span per ray,
/// in order; a ray without samples shows its background). With `cull`, the
/// samples behind the point where a ray's transmittance falls below it are
/// dropped after the density pass: they would change its colour by less
/// than `cull`, and their colour pass and backward are skipped. Gradients of
/// the loss times `scale` accumulate into `grads`.
#[allow(clippy::too_many_arguments)]
pub fn train_pass<F: Field>(
    field: &F,
    params: &[f32],
    rays: &[TrainRay],
    samples: &mut Samples,
    cull: Option<f32>,
    scale: f32,
    ctx: &mut F::Ctx,
    buf: &mut PassBuffers,
    grads: &mut [f32],
) -> PassStats {
    let mut stats = PassStats { samples: samples.len() as u64, ..Default::default() };
    if !samples.is_empty() {
        buf.image.clear();
        for (r, &(_, k)) in rays.iter().zip(&samples.spans) {
            buf.image.extend(std::iter::repeat_n(r.image, k));
        }
        field.density(params, Points { pos: &samples.pos, dirs: &samples.dirs, image: &buf.image }, ctx);
        if let Some(min_t) = cull {
            visible(&samples.spans, field.sigma(ctx), &samples.delta, min_t, &mut buf.keep);
            if buf.keep.len() < samples.len() {
                stats.culled = (samples.len() - buf.keep.len()) as u64;
                field.compact(ctx, &buf.keep);
                samples.compact(&buf.keep);
            }
        }
        field.color(params, &samples.dirs, ctx);
    }
    let n = samples.len();
    for v in [&mut buf.weights, &mut buf.dsigma, &mut buf.drgb] {
        v.clear();
    }
    buf.weights.resize(n, 0.0);
    buf.dsigma.resize(n, 0.0);
    buf.drgb.resize(3 * n, 0.0);
    let (sigma, rgb) = if n > 0 { (field.sigma(ctx), field.rgb(ctx)) } else { (&[][..], &[][..]) };
    for (r, &(o, k)) in rays.iter().zip(&samples.spans) {
        let (sig, col) = (&sigma[o..o + k], &rgb[3 * o..3 * (o + k)]);
        let (t, d) = (&samples.t[o..o + k], &samples.delta[o..o + k]);
        let s = RaySamples::new(sig, col, t, d).expect("one span of packed samples");
        let opts = CompositeOptions { background: r.background, ..Default::default() };
        let comp = composite(s, &opts, &mut buf.weights[o..o + k]).expect("one weight per sample");
        let (sq, g) = l2(comp.rgb, r.target, scale);
        stats.sq_err += sq;
        if k > 0 {
            let (ds, dc) = (&mut buf.dsigma[o..o + k], &mut buf.drgb[3 * o..3 * (o + k)]);
            let up = Upstream { rgb: g, depth: 0.0, weights: None };
            composite_backward(s, &buf.weights[o..o + k], &opts, comp.used, up, ds, dc)
                .expect("one gradient per sample");
        }
    }
    if n > 0 {
        field.backward(params, ctx, &buf.dsigma, &buf.drgb, grads);
    }
    stats
}

/// Indices of the samples in front of the point where each ray's
/// transmittance falls below `min_t` (from the densities alone).
pub(super) fn visible(spans: &[(usize, usize)], sigma: &[f32], delta: &[f32], min_t: f32, keep: &mut Vec<usize>) {
    keep.clear();
    for &(o, k) in spans {
        let mut tau = 0.0f32;
        for i in o..o + k {
            if (-tau).exp() < min_t {
                break;
            }
            keep.push(i);
            tau += optical_depth(sigma[i], delta[i]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::fields::toy::{Toy, ToyCtx};
    use crate::engine::geometry::math::{Ray, Vec3};

    const W: [f32; 8] = [1.5, -0.5, 0.8, 0.4, -1.0, 0.7, 0.3, -0.2];

    fn rays() -> Vec<TrainRay> {
        (0..4)
            .map(|k| TrainRay {
                ray: Ray { origin: Vec3::new(-1.0, 0.2 * k as f32, 0.1), dir: Vec3::new(0.6, 0.0, 0.8) },
                target: [0.1 * k as f32, 0.7, 0.3],
                background: [1.0, 0.5 * k as f32 / 3.0, 0.0],
                index: k,
                image: 0,
                weight: 1.0,
            })
            .collect()
    }

    fn samples(rays: &[TrainRay]) -> Samples {
        let mut m = Samples::default();
        for (k, r) in rays.iter().enumerate() {
            let start = m.len();
            for i in 0..[12, 0, 30, 5][k] {
                m.push(&r.ray, 0.3 + 0.07 * i as f32, 0.07);
            }
            m.end_span(start);
        }
        m
    }

    /// The mean over rays of the loss, and its gradient.
    fn run(w: &[f32], cull: Option<f32>) -> (f64, Vec<f32>) {
        let rays = rays();
        let mut m = samples(&rays);
        let (mut ctx, mut buf) = (ToyCtx::default(), PassBuffers::default());
        let mut grads = vec![0.0; 8];
        let scale = 1.0 / (3.0 * rays.len() as f32);
        let s = train_pass(&Toy, w, &rays, &mut m, cull, scale, &mut ctx, &mut buf, &mut grads);
        (s.sq_err / rays.len() as f64, grads)
    }

    #[test]
    fn gradients_match_finite_differences_in_f64() {
        let (_, grads) = run(&W, None);
        for i in 0..8 {
            let h = 1e-2f32;
            let (mut a, mut b) = (W, W);
            a[i] += h;
            b[i] -= h;
            let num = (run(&a, None).0 - run(&b, None).0) / (2.0 * h as f64);
            assert!((num - grads[i] as f64).abs() < 1e-3 * (1.0 + num.abs()), "w{i}: {num} vs {}", grads[i]);
        }
    }

    #[test]
    fn culling_drops_samples_but_not_the_loss_or_gradient() {
        let (loss, grads) = run(&W, None);
        let mut w = W;
        w[3] = 8.0; // dense: rays become opaque early, so there is something to cull
        let (dense_loss, dense_grads) = run(&w, None);
        let rays = rays();
        let mut m = samples(&rays);
        let (mut ctx, mut buf) = (ToyCtx::default(), PassBuffers::default());
        let s = train_pass(&Toy, &w, &rays, &mut m, Some(1e-4), 1.0, &mut ctx, &mut buf, &mut [0.0; 8]);
        assert!(s.culled > 0 && s.samples == 47, "{s:?}");
        let (culled_loss, culled_grads) = run(&w, Some(1e-4));
        assert!((culled_loss - dense_loss).abs() < 1e-4, "{culled_loss} {dense_loss}");
        for (a, b) in culled_grads.iter().zip(&dense_grads) {
            assert!((a - b).abs() < 1e-3 * (1.0 + b.abs()), "{culled_grads:?} {dense_grads:?}");
        }
        // Nothing to cull at the first weights' transmittance: the same numbers.
        assert_eq!(run(&W, Some(1e-9)), (loss, grads));
    }
}
