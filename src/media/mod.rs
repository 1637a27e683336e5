//! Encoding rendered views for people: PNG images and orbit videos (GIF, MP4).

pub mod png;
pub mod video;
