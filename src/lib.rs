//! radiance: train Neural Radiance Fields on CPUs and render novel views.

pub mod engine;
