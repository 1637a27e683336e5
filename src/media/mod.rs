//! Encoding rendered views for people: PNG images (videos come later).

pub mod png;
pub mod video;
