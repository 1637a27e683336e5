//! The CPU NeRF engine: cameras and rays, datasets, samplers, encodings,
//! networks, volume rendering, optimisation, training and checkpoints.
//!
//! No async, no HTTP, no global state: progress is reported through callbacks
//! and long work stops when a cancel flag is set.

pub mod camera;
pub mod dataset;
pub mod math;
pub mod fsio;
pub mod metrics;
pub mod checkpoint;
