//! The automatic model choice (design `real-captures.md` 2.10): `auto`, the
//! default of `radiance train --model`, `radiance bench --model` and of a
//! job's `model`, lets the dataset decide.
//!
//! - Training images with transparent pixels show an object on an empty
//!   background, as the NeRF synthetic scenes do: the fast model
//!   (`instant`), which was built and benchmarked for them.
//! - Masks composited as the images' alpha (`--masks composite`) make an
//!   object-only capture such a scene in effect (ethiopian_head: an object
//!   on white, where `instant` was benchmarked): `instant` too.
//! - Otherwise the images are opaque photographs of a real scene, with a
//!   background as far as the eye sees: the real-capture model (`capture`).
//!
//! The evidence is a [`SceneKind`], measured on the loaded dataset; the
//! service measures it when a scene is uploaded and keeps it in the scene's
//! record, so that a job's `auto` is resolved when it is posted (its memory
//! estimate needs the model) without loading the dataset again. The choice
//! comes with a sentence giving the evidence ([`ModelChoice::reason`]),
//! which `radiance train` prints and records keep.

use crate::engine::dataset::{Dataset, MaskUse};

/// The name that asks for the automatic choice.
pub const AUTO: &str = "auto";

/// The preset chosen for scenes of an object on an empty background.
pub const OBJECT_PRESET: &str = "instant";
/// The preset chosen for opaque photographs.
pub const PHOTO_PRESET: &str = "capture";
/// The preset chosen for opaque photographs taken all around the subject.
pub const ALL_AROUND_PRESET: &str = "capture-360";

/// What the automatic choice picked, and why.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ModelChoice {
    /// The preset (one of `config::presets()`).
    pub preset: String,
    /// The evidence, as a sentence: "37 of 100 training images have
    /// transparent pixels: an object on an empty background, the fast
    /// model".
    pub reason: String,
}

/// What the automatic choice looks at in a dataset.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SceneKind {
    /// Training images.
    pub train_images: usize,
    /// Training images with at least one pixel whose alpha is below 255.
    pub transparent_images: usize,
    /// The mask folder (`masks_8/`) whose masks are the images' alpha
    /// (`--masks composite`); `None` when no folder's masks are composited.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub composited_masks: Option<String>,
    /// Whether the training cameras all look the same way (the rig's
    /// `forward_facing`); `None` when the cameras give no rig.
    #[serde(default)]
    pub forward_facing: Option<bool>,
    /// The largest angle between a training camera's optical axis and
    /// their mean, degrees (the rig's `spread_deg`).
    #[serde(default)]
    pub spread_deg: Option<f32>,
    /// Whether the cameras saw the subject from one side, leaving a gap of
    /// more than `rig::ARC_GAP_DEG` around it (the rig's `arc_deg`); `None`
    /// when the cameras give no rig, and in records from before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub one_sided: Option<bool>,
}

impl SceneKind {
    /// Measures `ds` as it was loaded (with the masks in effect).
    pub fn of_dataset(ds: &Dataset) -> Self {
        let transparent_images = ds.train.iter().filter(|&&i| ds.frames[i].image.has_transparent_pixels()).count();
        let composited = ds.masks == MaskUse::Composite && ds.mask_folder.is_some();
        let rig = ds.rig();
        SceneKind {
            train_images: ds.train.len(),
            transparent_images,
            composited_masks: if composited { ds.mask_folder_name() } else { None },
            forward_facing: rig.as_ref().map(|r| r.forward_facing),
            spread_deg: rig.as_ref().map(|r| r.spread_deg),
            one_sided: rig.as_ref().map(|r| r.arc_deg.is_some()),
        }
    }

    /// The kind of a scene measured with its masks loaded as `auto` loads
    /// them (never composited), when a job asks for `masks`: composite
    /// makes the masks of `mask_folder` the images' alpha.
    pub fn with_masks(mut self, mask_folder: Option<&str>, masks: MaskUse) -> Self {
        if masks == MaskUse::Composite
            && let Some(folder) = mask_folder
        {
            self.composited_masks = Some(folder.to_string());
        }
        self
    }

    /// Whether the scene is an object on an empty background: transparent
    /// pixels, or masks composited as alpha.
    pub fn transparent(&self) -> bool {
        self.transparent_images > 0 || self.composited_masks.is_some()
    }

    /// The preset this scene calls for, with the evidence.
    pub fn choose(&self) -> ModelChoice {
        const OBJECT: &str = "an object on an empty background, the fast model";
        let (preset, reason) = if let Some(folder) = &self.composited_masks {
            (OBJECT_PRESET, format!("the masks in {folder} are the images' alpha (masks composite): {OBJECT}"))
        } else if self.transparent_images > 0 {
            let (n, m) = (self.transparent_images, self.train_images);
            let have = if n == 1 { "has" } else { "have" };
            (OBJECT_PRESET, format!("{n} of {m} training images {have} transparent pixels: {OBJECT}"))
        } else {
            match (self.forward_facing, self.spread_deg, self.one_sided) {
                (Some(true), Some(s), _) => (
                    PHOTO_PRESET,
                    format!(
                        "opaque photographs (forward-facing: axes within {s:.1} deg of their mean): the capture model"
                    ),
                ),
                (Some(false), Some(s), Some(false)) => (
                    ALL_AROUND_PRESET,
                    format!(
                        "opaque photographs (cameras all around their focus, axes up to {s:.0} deg from their mean): \
                         the capture model with a larger, finer hash grid and a stronger distortion loss"
                    ),
                ),
                (Some(false), Some(s), one_sided) => {
                    let side = if one_sided == Some(true) { " from one side" } else { "" };
                    (
                        PHOTO_PRESET,
                        format!(
                            "opaque photographs (cameras around their focus{side}, axes up to {s:.0} deg from their mean): \
                             the capture model"
                        ),
                    )
                }
                _ => (PHOTO_PRESET, "opaque photographs: the capture model".to_string()),
            }
        };
        ModelChoice { preset: preset.to_string(), reason }
    }
}

/// The choice for `ds` as loaded (`SceneKind::of_dataset(ds).choose()`).
pub fn choose(ds: &Dataset) -> ModelChoice {
    SceneKind::of_dataset(ds).choose()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;
    use crate::engine::dataset::textured::TexturedScene;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::math::Vec3;

    use crate::engine::models::config::ModelConfig;

    fn ball() -> Dataset {
        BallScene { size: 8, views: 6, ..Default::default() }.dataset()
    }

    fn photos() -> Dataset {
        TexturedScene { width: 8, height: 6, views: 8, fov: 0.9 }.dataset()
    }

    #[test]
    fn transparent_images_give_the_fast_model_with_their_count() {
        let ds = ball();
        let c = choose(&ds);
        let n = ds.train.len();
        assert_eq!(c.preset, "instant");
        assert_eq!(
            c.reason,
            format!(
                "{n} of {n} training images have transparent pixels: an object on an empty background, the fast model"
            )
        );
        // One image with one see-through pixel is enough, and is counted.
        let mut ds = photos();
        let f = &mut ds.frames[ds.train[2]].image;
        f.has_alpha = true;
        f.rgba[7] = 254;
        let c = choose(&ds);
        assert_eq!(
            (c.preset.as_str(), c.reason.starts_with("1 of 8 training images has transparent")),
            ("instant", true),
            "{c:?}"
        );
    }

    #[test]
    fn opaque_photographs_all_around_their_focus_give_the_larger_capture_model() {
        let ds = photos();
        let kind = SceneKind::of_dataset(&ds);
        assert_eq!((kind.transparent_images, kind.forward_facing, kind.one_sided), (0, Some(false), Some(false)));
        let spread = kind.spread_deg.unwrap();
        let c = kind.choose();
        assert_eq!(c.preset, "capture-360");
        assert_eq!(
            c.reason,
            format!(
                "opaque photographs (cameras all around their focus, axes up to {spread:.0} deg from their mean): \
                 the capture model with a larger, finer hash grid and a stronger distortion loss"
            )
        );
        // An alpha channel that is opaque everywhere is a photograph.
        let mut ds = photos();
        ds.frames.iter_mut().for_each(|f| f.image.has_alpha = true);
        assert_eq!(choose(&ds).preset, "capture-360");
        // The preset differs from `capture` in its table, finest level and
        // distortion weight alone.
        let (Some(ModelConfig::Capture(wide)), Some(ModelConfig::Capture(plain))) =
            (ModelConfig::preset("capture-360"), ModelConfig::preset("capture"))
        else {
            panic!("both are capture presets")
        };
        assert_eq!((wide.grid.log2_table, plain.grid.log2_table), (18, 16));
        assert_eq!((wide.grid.finest_resolution, plain.grid.finest_resolution), (4096, 2048));
        assert_eq!((wide.distortion, plain.distortion), (0.004, 0.002));
        let mut same = wide.clone();
        same.grid.log2_table = 16;
        same.grid.finest_resolution = 2048;
        same.distortion = 0.002;
        assert_eq!(same, plain);
    }

    #[test]
    fn photographs_from_one_side_give_the_capture_model() {
        let mut ds = photos();
        // Cameras on a quarter circle around the origin, looking at it.
        for (k, f) in ds.frames.iter_mut().enumerate() {
            let a = (k as f32 * 12.0 - 45.0).to_radians();
            let eye = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.5);
            f.camera = Camera::from_fov(8, 6, 0.9, look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap());
        }
        let kind = SceneKind::of_dataset(&ds);
        assert_eq!((kind.forward_facing, kind.one_sided), (Some(false), Some(true)), "{kind:?}");
        let spread = kind.spread_deg.unwrap();
        let c = kind.choose();
        assert_eq!(c.preset, "capture");
        assert_eq!(
            c.reason,
            format!(
                "opaque photographs (cameras around their focus from one side, axes up to {spread:.0} deg from their \
                 mean): the capture model"
            )
        );
        // A record from before `one_sided` existed: the plain capture model.
        assert_eq!(SceneKind { one_sided: None, ..kind }.choose().preset, "capture");
    }

    #[test]
    fn forward_facing_photographs_say_so() {
        let mut ds = photos();
        // Cameras on a small grid, all looking down -y.
        for (k, f) in ds.frames.iter_mut().enumerate() {
            let eye = Vec3::new(0.2 * (k % 3) as f32, 3.0, 0.2 * (k / 3) as f32);
            let pose =
                look_at(eye, eye + Vec3::new(0.05 * (k % 2) as f32, -1.0, 0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
            f.camera = Camera::from_fov(8, 6, 0.9, pose);
        }
        let kind = SceneKind::of_dataset(&ds);
        assert_eq!(kind.forward_facing, Some(true), "{kind:?}");
        let spread = kind.spread_deg.unwrap();
        assert!(spread < 5.0, "{spread}");
        let c = kind.choose();
        assert_eq!(c.preset, "capture");
        assert_eq!(
            c.reason,
            format!(
                "opaque photographs (forward-facing: axes within {spread:.1} deg of their mean): the capture model"
            )
        );
    }

    #[test]
    fn composited_masks_make_an_object_scene() {
        let kind = SceneKind::of_dataset(&photos());
        for masks in [MaskUse::Auto, MaskUse::Score, MaskUse::Ignore, MaskUse::Off] {
            assert_eq!(kind.clone().with_masks(Some("masks_8/"), masks).choose().preset, "capture-360", "{masks}");
        }
        // Without a mask folder there is nothing to composite.
        assert_eq!(kind.clone().with_masks(None, MaskUse::Composite).choose().preset, "capture-360");
        let c = kind.with_masks(Some("masks_8/"), MaskUse::Composite).choose();
        assert_eq!(c.preset, "instant");
        assert_eq!(
            c.reason,
            "the masks in masks_8/ are the images' alpha (masks composite): an object on an empty background, the fast model"
        );
    }

    /// The choice agrees with the scene's own flag, which decides how the
    /// fast model's occupancy grid treats the background.
    #[test]
    fn the_choice_follows_the_scenes_transparency() {
        let mut half = photos();
        half.frames[half.train[0]].image.has_alpha = true;
        half.frames[half.train[0]].image.rgba[3] = 0;
        let mut held_out_only = photos();
        let t = held_out_only.test[0];
        held_out_only.train.retain(|&i| i != t);
        held_out_only.frames[t].image.has_alpha = true;
        held_out_only.frames[t].image.rgba[3] = 0;
        for ds in [ball(), photos(), half, held_out_only] {
            let kind = SceneKind::of_dataset(&ds);
            let transparent = ds.scene().transparent;
            assert_eq!(kind.transparent(), transparent);
            assert_eq!(kind.choose().preset, if transparent { "instant" } else { "capture-360" });
            assert!(ModelConfig::preset(&kind.choose().preset).is_some());
        }
    }

    #[test]
    fn kinds_round_trip_and_old_forms_load() {
        let kind = SceneKind::of_dataset(&photos()).with_masks(Some("masks/"), MaskUse::Composite);
        let v = serde_json::to_value(&kind).unwrap();
        assert_eq!(serde_json::from_value::<SceneKind>(v).unwrap(), kind);
        let bare: SceneKind =
            serde_json::from_value(serde_json::json!({ "train_images": 3, "transparent_images": 0 })).unwrap();
        assert_eq!(
            bare.choose(),
            ModelChoice { preset: "capture".into(), reason: "opaque photographs: the capture model".into() }
        );
    }
}
