//! Files: the checkpoint container, saving and loading models in it, and
//! atomic writes.

pub mod checkpoint;
pub mod fsio;
pub mod persist;
