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
        let update = self.begin(lr);
        self.apply(&update, params, grads, groups, None);
    }

    /// Starts a step at learning rate `lr`: counts it and returns its
    /// constants, for [`Adam::apply`] and [`AdamUpdate::update`]. Every
    /// parameter must then be updated once with them.
    pub fn begin(&mut self, lr: f32) -> AdamUpdate {
        self.t += 1;
        let (b1, b2, eps) = (self.config.beta1, self.config.beta2, self.config.eps);
        let bc1 = 1.0 - (b1 as f64).powi(self.t as i32);
        let bc2 = 1.0 - (b2 as f64).powi(self.t as i32);
        let step = (lr as f64 * bc2.sqrt() / bc1) as f32;
        let eps_hat = eps * bc2.sqrt() as f32;
        AdamUpdate { b1, b2, step, eps_hat }
    }

    /// The update of a step begun with [`Adam::begin`], over the whole
    /// buffer except `skip` (left to the caller, who updates it with
    /// [`AdamUpdate::update`] and its own gradient; `groups` must not
    /// overlap it).
    pub fn apply(
        &mut self,
        update: &AdamUpdate,
        params: &mut [f32],
        grads: &mut [f32],
        groups: &[LrGroup],
        skip: Option<Range<usize>>,
    ) {
        use rayon::prelude::*;
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
                let mut run = |r: Range<usize>, scale: f32| {
                    // The chunk's part of `r` without `skip`'s.
                    let (lo, hi) = match &skip {
                        Some(s) => (s.start.clamp(r.start, r.end), s.end.clamp(r.start, r.end)),
                        None => (r.end, r.end),
                    };
                    for r in [r.start..lo, hi.max(lo)..r.end] {
                        let r = r.start - start..r.end - start;
                        update.update(&mut p[r.clone()], &mut g[r.clone()], &mut m[r.clone()], &mut v[r], scale);
                    }
                };
                // The chunk in pieces: before each group, the group's part.
                let mut at = chunk.start;
                for grp in groups {
                    let (lo, hi) = (grp.range.start.max(at), grp.range.end.min(chunk.end));
                    if lo < hi {
                        run(at..lo, 1.0);
                        run(lo..hi, grp.scale);
                        at = hi;
                    }
                }
                run(at..chunk.end, 1.0);
            });
    }
}

/// The constants of one Adam step ([`Adam::begin`]).
#[derive(Clone, Copy, Debug)]
pub struct AdamUpdate {
    b1: f32,
    b2: f32,
    step: f32,
    eps_hat: f32,
}

impl AdamUpdate {
    /// Updates `p` with gradient `g` and moments `m`, `v` (equal lengths),
    /// at `scale` times the step's rate; leaves `g` zeroed.
    #[inline]
    pub fn update(&self, p: &mut [f32], g: &mut [f32], m: &mut [f32], v: &mut [f32], scale: f32) {
        let Self { b1, b2, eps_hat, .. } = *self;
        let step = if scale == 1.0 { self.step } else { self.step * scale };
        let n = p.len();
        let (g, m, v) = (&mut g[..n], &mut m[..n], &mut v[..n]);
        for i in 0..n {
            let gi = g[i];
            g[i] = 0.0;
            m[i] = b1 * m[i] + (1.0 - b1) * gi;
            v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
            p[i] -= step * m[i] / (v[i].sqrt() + eps_hat);
        }
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

    /// A step begun with `begin`, applied outside a skipped range and by
    /// the caller inside it, is `step_groups`' bit for bit; `apply` leaves
    /// the skipped range (parameters, gradient, moments) alone.
    #[test]
    fn apply_leaves_the_skipped_range_to_the_caller() {
        let n = 40_000;
        let skip = 9_000..35_000;
        let groups = [LrGroup { range: 100..200, scale: 0.1 }, LrGroup { range: 36_000..37_000, scale: 0.5 }];
        let grads: Vec<f32> = (0..n).map(|i| ((i * 7919) % 13) as f32 - 6.0).collect();
        let (mut whole, mut split) = (Adam::new(AdamConfig::default(), n), Adam::new(AdamConfig::default(), n));
        let (mut p0, mut p1) = (vec![0.25f32; n], vec![0.25f32; n]);
        for s in 0..3 {
            let lr = 0.01 / (s + 1) as f32;
            whole.step_groups(&mut p0, &mut grads.clone(), lr, &groups);
            let update = split.begin(lr);
            let mut g = grads.clone();
            let before = (p1[skip.clone()].to_vec(), split.m[skip.clone()].to_vec(), split.v[skip.clone()].to_vec());
            split.apply(&update, &mut p1, &mut g, &groups, Some(skip.clone()));
            assert_eq!(g[skip.clone()], grads[skip.clone()], "the skipped gradient is not read");
            assert!(g[..skip.start].iter().chain(&g[skip.end..]).all(|v| *v == 0.0), "the rest is consumed");
            assert_eq!(
                before,
                (p1[skip.clone()].to_vec(), split.m[skip.clone()].to_vec(), split.v[skip.clone()].to_vec())
            );
            let r = skip.clone();
            update.update(&mut p1[r.clone()], &mut g[r.clone()], &mut split.m[r.clone()], &mut split.v[r], 1.0);
        }
        assert_eq!(whole.t, split.t);
        for i in 0..n {
            assert_eq!(p0[i].to_bits(), p1[i].to_bits(), "parameter {i}");
            assert_eq!(whole.m[i].to_bits(), split.m[i].to_bits(), "m {i}");
            assert_eq!(whole.v[i].to_bits(), split.v[i].to_bits(), "v {i}");
        }
    }
}
