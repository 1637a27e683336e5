//! Numerical stability: tests that try hard to break the engine.
//!
//! Volume rendering, inverse-CDF sampling, encodings and cameras under
//! extreme inputs (property tests), f32 against an f64 reference, scale
//! invariance, degenerate datasets, a long run, the trainer's divergence
//! guard, bit-identical checkpoints and fuzzed dataset parsers; one module
//! per part, in one test binary (one link instead of five).
//!
//! Proptest keeps the regressions of `stability/NAME.rs` in
//! `tests/proptest-regressions/NAME.txt` (next to the folder holding this
//! `main.rs`) and replays them first.

#[path = "../common/mod.rs"]
mod common;

mod encodings;
mod models;
mod parsers;
mod rendering;
mod sampling;
