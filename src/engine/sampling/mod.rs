//! Where along a ray to evaluate a field: stratified and inverse-CDF samples
//! (the classic model) and the occupancy grid that lets the fast model march
//! through occupied cells only.

pub mod occupancy;
pub mod stratified;
