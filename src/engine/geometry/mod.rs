//! Points, rays and boxes; pinhole cameras with lens distortion; the scene's
//! bounds and the map from world to model space.

pub mod align;
pub mod camera;
pub mod math;
pub mod path;
pub mod quat;
pub mod rig;
pub mod scene;
pub mod so3;
