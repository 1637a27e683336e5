//! The CPU NeRF engine: cameras and rays, datasets, samplers, encodings,
//! networks, volume rendering, optimisation, training and checkpoints.
//!
//! No async, no HTTP, no global state: progress is reported through callbacks
//! and long work stops when a cancel flag is set.

pub mod bake;
pub mod batch;
pub mod dataset;
pub mod fields;
pub mod front;
pub mod geometry;
pub mod io;
pub mod mesh;
pub mod metrics;
pub mod models;
pub mod nn;
pub mod render;
pub mod rng;
pub mod sampling;
pub mod train;
pub mod transient;
pub mod view;
