//! The CPU NeRF engine: cameras and rays, datasets, samplers, encodings,
//! networks, volume rendering, optimisation, training and checkpoints.
//!
//! No async, no HTTP, no global state: progress is reported through callbacks
//! and long work stops when a cancel flag is set.

pub mod adam;
pub mod camera;
pub mod checkpoint;
pub mod dataset;
pub mod encoding;
pub mod estimate;
pub mod fsio;
pub mod gemm;
pub mod hashgrid;
pub mod heldout;
pub mod instant;
pub mod linear;
pub mod math;
pub mod metrics;
pub mod model;
pub mod model_config;
pub mod nerf;
pub mod nerf_net;
pub mod occupancy;
pub mod persist;
pub mod render;
pub mod rng;
pub mod sampler;
pub mod scene;
pub mod sh;
pub mod synthetic;
pub mod trainer;
pub mod volume;
