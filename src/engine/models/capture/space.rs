//! The space map of the real-capture model (`models::capture`): a scene
//! contraction, or NDC of the training cameras' mean pose for
//! forward-facing captures (design `real-captures.md`, section 2.3).
//!
//! NDC needs a reference camera, which only the training cameras can give:
//! [`resolve`] derives it from the scene's rig when a model is built and
//! stores it in the configuration (`CaptureConfig::ndc_camera`), which the
//! checkpoint saves; a reloaded model maps space with the stored camera,
//! since a checkpoint's scene is already normalised and has lost the
//! dataset's near bound.

use super::config::{CaptureConfig, Space};
use super::{KIND, capture_scene};
use crate::engine::fields::space::{NdcCamera, NdcFrame, SpaceMap};
use crate::engine::geometry::rig::FORWARD_FACING_SPREAD_DEG;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::ModelError;

/// The map `config` describes. A configuration whose NDC camera is not
/// known yet (the memory estimate lays out parameters without a scene) is
/// laid out as a contraction: the two maps have the same parameters.
pub fn space_map(config: &CaptureConfig) -> SpaceMap {
    match (config.space, &config.ndc_camera) {
        (Space::Ndc, Some(frame)) => SpaceMap::Ndc(frame.clone()),
        _ => SpaceMap::Contract { norm: config.contraction },
    }
}

/// `config` ready to build a model for `scene` (as a dataset gives it):
/// with `space: ndc`, its NDC camera derived by [`ndc_frame`] (replacing
/// any it had: the scene is the truth at build time); with `contract`, no
/// camera, and with `near_from_data` a `near` raised to the dataset's near
/// bound ([`data_near`]) when that is further (and before `far`). Applying
/// it to a model's own normalised scene changes nothing.
pub fn resolve(mut config: CaptureConfig, scene: &Scene) -> Result<CaptureConfig, ModelError> {
    config.ndc_camera = match config.space {
        Space::Ndc => Some(ndc_frame(scene, &config)?),
        Space::Contract => None,
    };
    if config.space == Space::Contract
        && config.near_from_data
        && let Some(near) = data_near(scene, &config)
        && near > config.near
        && near < config.far
    {
        config.near = near;
    }
    Ok(config)
}

/// The dataset's near bound in the model's units (`None` when it has none:
/// 0, as transforms.json's, or not finite). The scene holds it in its box
/// normalisation; a scene the model has normalised holds the model's `near`.
pub fn data_near(scene: &Scene, config: &CaptureConfig) -> Option<f32> {
    let near = near_in_model_units(scene, &capture_scene(scene, config));
    (near.is_finite() && near > 0.0).then_some(near)
}

/// `scene`'s near bound (in its box normalisation) in the units of `model`,
/// the model's normalisation of it ([`capture_scene`]).
fn near_in_model_units(scene: &Scene, model: &Scene) -> f32 {
    scene.near / scene.scale * model.scale
}

/// Refuses a configuration a saved model cannot be rebuilt from: `space:
/// ndc` without its camera (a checkpoint always stores it).
pub fn check_resolved(config: &CaptureConfig) -> Result<(), ModelError> {
    match (config.space, &config.ndc_camera) {
        (Space::Ndc, None) => Err(config_error(
            "space is ndc but the configuration has no ndc_camera (a model trained with NDC stores it)".into(),
        )),
        _ => Ok(()),
    }
}

fn config_error(message: String) -> ModelError {
    ModelError::Config { kind: KIND, message }
}

/// The NDC reference camera of `scene`'s training cameras, in the units of
/// the model's normalisation ([`capture_scene`]: their focus at the origin,
/// their median distance at `camera_radius`):
/// - pose: the cameras' mean centre and mean axes, re-orthonormalised (the
///   rig's spiral frame: right, up, and backward = right x up);
/// - image: the first training camera's size and horizontal field of view,
///   with square pixels (`fy = fx`: the rig keeps one field of view);
/// - near plane: the dataset's near bound (LLFF's 0.9 x the nearest depth
///   bound), converted from the scene's units to the model's.
///
/// Errors (`ModelError::Config`) for a scene without a rig, a rig that is
/// not forward-facing (NDC's frustum would leave out what cameras looking
/// other ways see), or without the cameras' image size, and for a camera
/// `NdcFrame` refuses.
pub fn ndc_frame(scene: &Scene, config: &CaptureConfig) -> Result<NdcFrame, ModelError> {
    let rig = scene.rig.as_ref().ok_or_else(|| {
        config_error("space=ndc needs the training cameras, and this scene has none (made from bounds alone)".into())
    })?;
    if !rig.forward_facing {
        return Err(config_error(format!(
            "space=ndc is for forward-facing captures (every optical axis within {FORWARD_FACING_SPREAD_DEG} deg \
             of their mean); this one's axes spread {:.1} deg: use space=contract",
            rig.spread_deg
        )));
    }
    let half_fov = (0.5 * rig.fov_deg).to_radians();
    let [width, height] = rig.image;
    if width == 0 || height == 0 || !(half_fov > 0.0 && half_fov < std::f32::consts::FRAC_PI_2) {
        return Err(config_error(format!(
            "space=ndc needs the training cameras' image size and field of view; the scene's rig has \
             {width}x{height} and {} deg",
            rig.fov_deg
        )));
    }
    let focal = 0.5 * width as f32 / half_fov.tan();
    let model = capture_scene(scene, config);
    if model.centre != rig.focus {
        return Err(config_error(format!(
            "space=ndc needs the cameras' focus and distance, and the rig has focus {:?} at distance {}",
            rig.focus, rig.radius
        )));
    }
    let s = &rig.spiral;
    let back = cross(s.right, s.up);
    let camera = NdcCamera {
        rotation: std::array::from_fn(|i| [s.right[i], s.up[i], back[i]]),
        centre: std::array::from_fn(|i| (s.centre[i] - model.centre[i]) * model.scale),
        near: near_in_model_units(scene, &model),
        fx: focal,
        fy: focal,
        width,
        height,
    };
    NdcFrame::new(camera).map_err(|e| config_error(format!("space=ndc: {e}")))
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[cfg(test)]
#[path = "space_tests.rs"]
mod tests;
