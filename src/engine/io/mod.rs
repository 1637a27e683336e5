//! Files: the checkpoint container and atomic writes. Saving a model with
//! its optimiser in a checkpoint is `train::persist`'s.

pub mod checkpoint;
pub mod fsio;
