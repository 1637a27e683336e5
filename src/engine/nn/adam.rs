//! Adam over a flat parameter buffer, with an exponential learning-rate
//! schedule, and ranges of the buffer whose learning rate is scaled
//! ([`LrGroup`]: the camera poses learn at a tenth of the networks' rate).
//! Its state is saved with the checkpoint; the groups come from the model.

use std::ops::Range;

/// A range of the parameter buffer that learns at `scale` times the
/// schedule's rate (the range outside every group at 1).
#[derive(Clone, Debug, PartialEq)]
pub struct LrGroup {
    pub range: Range<usize>,
    pub scale: f32,
}

/// Adam's hyper-parameters. `Default` gives the NeRF paper's values.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AdamConfig {
    /// Initial learning rate (5e-4).
    pub lr: f32,
    /// Learning rate at the end of the schedule (5e-5).
    pub lr_end: f32,
    pub beta1: f32,
    pub beta2: f32,
    /// 1e-7 as in the paper's TensorFlow code.
    pub eps: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { lr: 5e-4, lr_end: 5e-5, beta1: 0.9, beta2: 0.999, eps: 1e-7 }
    }
}

impl AdamConfig {
    /// Exponential decay from `lr` at progress 0 to `lr_end` at progress 1.
    pub fn lr_at(&self, progress: f64) -> f32 {
        let p = progress.clamp(0.0, 1.0);
        (self.lr as f64 * (self.lr_end as f64 / self.lr as f64).powf(p)) as f32
    }
}

/// First and second moments and the step count.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    pub config: AdamConfig,
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub t: u64,
}

impl Adam {
    pub fn new(config: AdamConfig, len: usize) -> Self {
        Self { config, m: vec![0.0; len], v: vec![0.0; len], t: 0 }
    }

    /// One update of `params` with gradient `grads` at learning rate `lr`.
    /// The gradient is consumed: `grads` is left zeroed, ready to accumulate
    /// the next step's (in the same pass over memory).
    pub fn step(&mut self, params: &mut [f32], grads: &mut [f32], lr: f32) {
        self.step_groups(params, grads, lr, &[]);
    }

    /// [`Adam::step`] with the learning rate of each of `groups` (ranges in
    /// increasing order that do not overlap; cut at the buffer's end) scaled. Outside the groups, and inside a group of
    /// scale 1, the update is bit for bit [`Adam::step`]'s.
    pub fn step_groups(&mut self, params: &mut [f32], grads: &mut [f32], lr: f32, groups: &[LrGroup]) {
        use rayon::prelude::*;
        self.t += 1;
        let (b1, b2, eps) = (self.config.beta1, self.config.beta2, self.config.eps);
        let bc1 = 1.0 - (b1 as f64).powi(self.t as i32);
        let bc2 = 1.0 - (b2 as f64).powi(self.t as i32);
        let step = (lr as f64 * bc2.sqrt() / bc1) as f32;
        let eps_hat = eps * bc2.sqrt() as f32;
        const CHUNK: usize = 1 << 14;
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks_mut(CHUNK))
            .zip(self.m.par_chunks_mut(CHUNK))
            .zip(self.v.par_chunks_mut(CHUNK))
            .enumerate()
            .for_each(|(c, (((p, g), m), v))| {
                let start = c * CHUNK;
                let chunk = start..start + p.len();
                let mut update = |r: Range<usize>, step: f32| {
                    for i in r {
                        let gi = g[i];
                        g[i] = 0.0;
                        m[i] = b1 * m[i] + (1.0 - b1) * gi;
                        v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                        p[i] -= step * m[i] / (v[i].sqrt() + eps_hat);
                    }
                };
                // The chunk in pieces: before each group, the group's part.
                let mut at = chunk.start;
                for grp in groups {
                    let (lo, hi) = (grp.range.start.max(at), grp.range.end.min(chunk.end));
                    if lo < hi {
                        update(at - start..lo - start, step);
                        update(lo - start..hi - start, step * grp.scale);
                        at = hi;
                    }
                }
                update(at - start..chunk.end - start, step);
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_decays_exponentially() {
        let c = AdamConfig::default();
        assert!((c.lr_at(0.0) - 5e-4).abs() < 1e-10);
        assert!((c.lr_at(1.0) - 5e-5).abs() < 1e-10);
        assert!((c.lr_at(0.5) - 5e-4 * 0.1f32.sqrt()).abs() < 1e-9);
        assert_eq!(c.lr_at(2.0), c.lr_at(1.0));
    }

    #[test]
    fn first_step_moves_by_lr_against_the_gradient_sign() {
        let mut a = Adam::new(AdamConfig::default(), 3);
        let mut p = vec![1.0f32, 1.0, 1.0];
        let mut g = [2.0, -0.001, 0.0];
        a.step(&mut p, &mut g, 0.1);
        assert_eq!(g, [0.0; 3], "the gradient is consumed");
        // With bias correction the first step is lr * g / |g|.
        assert!((p[0] - 0.9).abs() < 1e-5);
        assert!((p[1] - 1.1).abs() < 1e-3);
        assert_eq!(p[2], 1.0);
    }

    /// A group's parameters move by `scale` times as much on the first
    /// step (where the move is `lr` times the gradient's sign); the others
    /// exactly as without groups, across chunk boundaries.
    #[test]
    fn groups_scale_their_range_only() {
        let n = 40_000;
        let grads: Vec<f32> = (0..n).map(|i| ((i * 7919) % 13) as f32 - 6.0).collect();
        let (mut plain, mut grouped) = (Adam::new(AdamConfig::default(), n), Adam::new(AdamConfig::default(), n));
        let (mut p0, mut p1) = (vec![0.0f32; n], vec![0.0f32; n]);
        // The last one runs past the buffer's end: cut there.
        let groups = [
            LrGroup { range: 100..200, scale: 0.1 },
            LrGroup { range: 16_000..17_000, scale: 1.0 },
            LrGroup { range: 30_000..n + 10, scale: 0.5 },
        ];
        for _ in 0..3 {
            plain.step(&mut p0, &mut grads.clone(), 0.01);
            grouped.step_groups(&mut p1, &mut grads.clone(), 0.01, &groups);
        }
        for i in 0..n {
            let scale = if (100..200).contains(&i) {
                0.1
            } else if i >= 30_000 {
                0.5
            } else {
                assert_eq!(p0[i].to_bits(), p1[i].to_bits(), "parameter {i} outside a scaled group");
                continue;
            };
            let (a, b) = (p0[i], p1[i]);
            assert!((b - scale * a).abs() <= 1e-5 * a.abs(), "{i}: {b} vs {scale} x {a}");
        }
        assert!(plain.m == grouped.m && plain.v == grouped.v, "the moments do not depend on the rate");
    }

    #[test]
    fn minimises_a_quadratic() {
        let mut a = Adam::new(AdamConfig { lr: 0.05, ..Default::default() }, 2);
        let mut p = vec![3.0f32, -2.0];
        for _ in 0..2000 {
            let mut g = vec![2.0 * (p[0] - 1.0), 8.0 * (p[1] + 0.5)];
            a.step(&mut p, &mut g, 0.05);
        }
        assert!((p[0] - 1.0).abs() < 1e-2 && (p[1] + 0.5).abs() < 1e-2, "{p:?}");
    }
}
