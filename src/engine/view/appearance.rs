//! Which appearance a new view takes (design `real-captures.md` 2.6): a
//! model with per-image appearance (the capture model) learned one
//! embedding per training photo, so a view no photo was taken from needs
//! one chosen for it. [`Appearance`] is the user's choice (`--appearance`,
//! the API's `appearance`); [`Appearance::resolve`] checks it against the
//! model and turns it into the [`RenderOptions`] a model renders with.
//!
//! - `Mean`: the mean embedding of the images trained on (nerfacto's new
//!   views).
//! - `Image(i)`: training image `i`'s (a dataset frame index), which must
//!   have been trained on: otherwise an error naming the ones that were.
//! - `Nearest`: per camera, the training camera nearest it
//!   ([`CameraRig::nearest_frame`](crate::engine::geometry::rig::CameraRig::nearest_frame)).
//!   Held-out views are scored with it ([`held_out_options`]): every 8th
//!   photo of a capture is held out, its neighbours were trained on, and
//!   auto-exposure drifts slowly along a capture, so the nearest one
//!   predicts the held-out photo's exposure at no cost.
//!
//! Models without per-image appearance accept every choice and ignore it.

use std::fmt;
use std::str::FromStr;

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Vec3;
use crate::engine::models::{Model, RenderOptions};

/// The appearance a user asks a view to have.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(into = "String", try_from = "String")]
pub enum Appearance {
    /// The mean embedding of the images trained on.
    #[default]
    Mean,
    /// One training image's embedding, by dataset frame index.
    Image(u32),
    /// The embedding of the training camera nearest the view's camera.
    Nearest,
}

/// Why an appearance cannot be rendered with this model.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AppearanceError {
    #[error(
        "appearance: image {image} was not trained on, so it has no appearance of its own (training images: {valid})"
    )]
    NotTrained { image: u32, valid: String },
    #[error(
        "appearance 'nearest': this model stores no training cameras (it was trained before checkpoints kept them); \
         ask for 'mean' or a training image's index"
    )]
    NoCameras,
}

impl Appearance {
    /// Whether it is the default, [`Appearance::Mean`].
    pub fn is_mean(&self) -> bool {
        *self == Appearance::Mean
    }

    /// The options a view from `camera` renders with under this choice, for
    /// `model`: an index must be one of [`Appearance::images`](crate::engine::models::Appearance::images);
    /// `Nearest` picks among them (the mean when there are none yet, as an
    /// untrained model has).
    pub fn resolve(self, model: &dyn Model, camera: &Camera) -> Result<RenderOptions, AppearanceError> {
        let Some(images) = model.appearance().map(|a| a.images()) else {
            return Ok(RenderOptions::default());
        };
        match self {
            Appearance::Mean => Ok(RenderOptions::default()),
            Appearance::Image(image) => match images.binary_search(&image) {
                Ok(_) => Ok(RenderOptions { image: Some(image) }),
                Err(_) => Err(AppearanceError::NotTrained { image, valid: index_ranges(&images) }),
            },
            Appearance::Nearest => {
                let rig = model.scene().rig.as_ref().filter(|r| !r.frames.is_empty());
                let rig = rig.ok_or(AppearanceError::NoCameras)?;
                let axis = camera.rotate(Vec3::new(0.0, 0.0, -1.0)).normalized().unwrap_or(Vec3::new(0.0, 0.0, -1.0));
                let image = rig.nearest_frame(camera.origin(), axis, |i| images.binary_search(&i).is_ok());
                Ok(RenderOptions { image })
            }
        }
    }

    /// Checks the choice against `model` where no camera is known yet (a
    /// request, before its views): `Nearest` is checked for the training
    /// cameras it needs, an index as [`Appearance::resolve`] does.
    pub fn check(self, model: &dyn Model) -> Result<(), AppearanceError> {
        let Some(images) = model.appearance().map(|a| a.images()) else { return Ok(()) };
        match self {
            Appearance::Mean => Ok(()),
            Appearance::Image(image) => match images.binary_search(&image) {
                Ok(_) => Ok(()),
                Err(_) => Err(AppearanceError::NotTrained { image, valid: index_ranges(&images) }),
            },
            Appearance::Nearest => match model.scene().rig.as_ref().is_some_and(|r| !r.frames.is_empty()) {
                true => Ok(()),
                false => Err(AppearanceError::NoCameras),
            },
        }
    }
}

/// The options held-out views are scored with, by `eval`, `bench`, the
/// training job's final number and its held-out chart alike: the nearest
/// training camera's appearance, or the mean for a model that stores no
/// training cameras (trained before checkpoints kept them).
pub fn held_out_options(model: &dyn Model, camera: &Camera) -> RenderOptions {
    Appearance::Nearest.resolve(model, camera).unwrap_or_default()
}

/// Sorted indices as ranges: `[0, 1, 2, 4, 6, 7]` -> `0-2, 4, 6-7`;
/// `none` for no index.
pub fn index_ranges(images: &[u32]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut k = 0;
    while k < images.len() {
        let start = images[k];
        let mut end = start;
        while k + 1 < images.len() && images[k + 1] == end.wrapping_add(1) {
            k += 1;
            end = images[k];
        }
        parts.push(if start == end { start.to_string() } else { format!("{start}-{end}") });
        k += 1;
    }
    if parts.is_empty() { "none".to_string() } else { parts.join(", ") }
}

impl fmt::Display for Appearance {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Appearance::Mean => f.write_str("mean"),
            Appearance::Image(i) => write!(f, "{i}"),
            Appearance::Nearest => f.write_str("nearest"),
        }
    }
}

impl FromStr for Appearance {
    type Err = String;

    /// `mean`, `nearest` or a training image's index.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "mean" => Ok(Appearance::Mean),
            "nearest" => Ok(Appearance::Nearest),
            _ if !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()) => s
                .parse()
                .map(Appearance::Image)
                .map_err(|_| format!("appearance '{s}': an image index must be below {}", u32::MAX as u64 + 1)),
            _ => Err(format!("appearance '{s}': expected mean, nearest or a training image's index")),
        }
    }
}

impl From<Appearance> for String {
    fn from(a: Appearance) -> String {
        a.to_string()
    }
}

impl TryFrom<String> for Appearance {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

#[cfg(test)]
#[path = "appearance_tests.rs"]
mod tests;
