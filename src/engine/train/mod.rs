//! Training: the pass every model trains its fields with, the
//! optimisation loop, the session that resumes, saves and
//! reports around it, held-out estimates and the memory and disk estimate of
//! a run.

pub mod estimate;
pub mod heldout;
pub mod pass;
pub mod pixels;
pub mod session;
pub mod trainer;
