//! Adam over a flat parameter buffer, with an exponential learning-rate
//! schedule. Its state is saved with the checkpoint.

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
            .for_each(|(((p, g), m), v)| {
                for i in 0..p.len() {
                    let gi = g[i];
                    g[i] = 0.0;
                    m[i] = b1 * m[i] + (1.0 - b1) * gi;
                    v[i] = b2 * v[i] + (1.0 - b2) * gi * gi;
                    p[i] -= step * m[i] / (v[i].sqrt() + eps_hat);
                }
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
