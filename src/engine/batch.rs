//! What passes between the trainer, the models and the render loop: a
//! training ray, a step's context, and what a batch or a ray gives. A leaf
//! of the engine (it uses only `geometry`), so that every layer can name them.

use crate::engine::geometry::math::Ray;

/// A training ray in model space with its target colour.
#[derive(Clone, Copy, Debug)]
pub struct TrainRay {
    pub ray: Ray,
    pub target: [f32; 3],
    pub background: [f32; 3],
    /// Position in the batch: seeds this ray's random stream.
    pub index: u64,
    /// The dataset frame the ray comes from (fields with per-image
    /// appearance read it).
    pub image: u32,
    /// The weight of the ray's colour loss: 1, or 0 where training found a
    /// transient occluder (`engine::transient`).
    pub weight: f32,
}

/// Per-step context for a batch.
#[derive(Clone, Copy, Debug)]
pub struct StepCtx {
    pub seed: u64,
    pub step: u64,
    /// Rays in the whole batch (losses are means over it).
    pub batch_rays: usize,
}

/// Sums over a part of a batch.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BatchStats {
    /// Sum over rays of the mean squared colour error of the final pass.
    pub sq_err: f64,
    /// The loss summed over passes (coarse + fine for NeRF).
    pub loss: f64,
    /// Network evaluations (of the main field, for a model with proposal
    /// networks).
    pub samples: u64,
    /// Evaluations of the proposal networks, which only place the main
    /// field's samples (the capture model's; 0 for the others).
    pub proposal_samples: u64,
    /// Samples a dense marcher would have taken but that were skipped.
    pub skipped: u64,
    pub rays: u64,
}

impl BatchStats {
    pub fn add(&mut self, o: &BatchStats) {
        self.sq_err += o.sq_err;
        self.loss += o.loss;
        self.samples += o.samples;
        self.proposal_samples += o.proposal_samples;
        self.skipped += o.skipped;
        self.rays += o.rays;
    }
}

/// What rendering one ray gives.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayOutput {
    pub rgb: [f32; 3],
    /// Expected distance along the ray in model units.
    pub depth: f32,
    pub opacity: f32,
    /// Where along the ray its opacity reaches one half, in model units
    /// (`Composite::median`); 0 when it never does.
    pub median: f32,
}
