//! Neural-network building blocks over one flat parameter buffer with named
//! ranges: linear layers and their GEMM, encodings (frequency, spherical
//! harmonics, multiresolution hash grid), the classic NeRF MLP, Adam (with learning-rate
//! scales for ranges), per-image appearance embeddings folded into a layer's
//! bias, and per-image camera pose corrections (`pose`, `pose_report`).

pub mod adam;
pub mod appearance;
pub mod encoding;
pub mod gemm;
pub mod hashgrid;
pub mod linear;
pub mod nerf_net;
pub mod pose;
pub mod pose_report;
pub mod sh;
