//! Training: the pass every model trains its fields with (and the
//! real-capture model's own: `capture_levels` places its samples by
//! proposal networks, `capture_pass` trains them and its field), the
//! optimisation loop, the session that resumes, saves and reports around
//! it, held-out estimates and the memory and disk estimate of a run.

pub mod appearance_fit;
pub mod estimate;
pub mod heldout;
pub mod persist;
pub mod pixels;
pub mod session;
pub mod trainer;
