//! Training: the optimisation loop, held-out estimates and the memory and
//! disk estimate of a run.

pub mod estimate;
pub mod heldout;
pub mod pass;
pub mod trainer;
