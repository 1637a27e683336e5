//! How the commands that train (`train`, `bench`) build a fresh model, its
//! optimiser and the training settings: through the engine's
//! [`ModelConfig`], as the service's jobs do.

// `presets()`: the names `--model` accepts besides `auto` (each model kind
// is one, and `auto` may choose `capture-360`).
use crate::engine::front::{
    AUTO, Adam, Dataset, Model, ModelChoice, ModelConfig, ModelError, Scene, choose_model, trainable_presets as presets,
};

pub use crate::engine::front::DEFAULT_BATCH_RAYS;

/// Refuses a `--model` that is neither `auto` nor a preset.
pub fn check_model_name(name: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        name == AUTO || presets().contains(&name),
        "unknown model '{name}' (available: {AUTO}, {})",
        presets().join(", ")
    );
    Ok(())
}

/// The model kind `--model name` trains on `ds`: `auto` lets the dataset
/// (as loaded, masks included) decide, and the choice comes back with its
/// reason; a kind is taken as it is.
pub fn resolve_model(name: &str, ds: &Dataset) -> anyhow::Result<(String, Option<ModelChoice>)> {
    check_model_name(name)?;
    if name != AUTO {
        return Ok((name.to_string(), None));
    }
    let choice = choose_model(ds);
    Ok((choice.preset.clone(), Some(choice)))
}

/// The configuration of `kind`. `skip: false` samples the whole clipped ray,
/// without the occupancy grid (nerf only). `sets` are `--set KEY=VALUE`
/// overrides of the preset (see [`apply_sets`]).
pub fn model_config(kind: &str, skip: bool, sets: &[String]) -> anyhow::Result<ModelConfig> {
    check_model_name(kind)?;
    anyhow::ensure!(kind != AUTO, "the model 'auto' must be resolved for a dataset first (resolve_model)");
    let mut cfg = apply_sets(ModelConfig::preset(kind).expect("every model kind is a preset"), sets)?;
    if !skip {
        match &mut cfg {
            ModelConfig::Nerf(c) => c.occupancy = None,
            _ => anyhow::bail!("--no-skip applies to the nerf model only"),
        }
    }
    Ok(cfg)
}

/// Overrides fields of `cfg`: each of `sets` is `KEY=VALUE`, where `KEY` is
/// a dotted path into the configuration as JSON (`occupancy.sweep`,
/// `grid.log2_table`) and `VALUE` is JSON (a bare word counts as a string).
/// Unknown keys, values of the wrong type and out-of-range results are
/// errors that name the key.
pub fn apply_sets(cfg: ModelConfig, sets: &[String]) -> anyhow::Result<ModelConfig> {
    if sets.is_empty() {
        return Ok(cfg);
    }
    let mut json = serde_json::to_value(&cfg)?;
    for set in sets {
        let (key, value) = set
            .split_once('=')
            .ok_or_else(|| anyhow::anyhow!("--set {set}: expected KEY=VALUE, e.g. grid.log2_table=17"))?;
        anyhow::ensure!(key != "kind", "--set {set}: the model kind is chosen with --model");
        let value: serde_json::Value =
            serde_json::from_str(value).unwrap_or_else(|_| serde_json::Value::String(value.to_string()));
        let mut node = &mut json;
        for part in key.split('.') {
            node = node
                .as_object_mut()
                .and_then(|o| o.get_mut(part))
                .ok_or_else(|| anyhow::anyhow!("--set {set}: the {} config has no field '{key}'", cfg.kind()))?;
        }
        anyhow::ensure!(
            !node.is_object() && !node.is_array(),
            "--set {set}: '{key}' is a group of settings; set one of its fields"
        );
        *node = value;
    }
    let out: ModelConfig = serde_json::from_value(json).map_err(|e| anyhow::anyhow!("--set: {e}"))?;
    out.check().map_err(|e| anyhow::anyhow!("--set: {e}"))?;
    Ok(out)
}

/// A fresh model of `kind` and its optimiser.
pub fn new_model_and_adam(
    kind: &str,
    scene: Scene,
    seed: u64,
    skip: bool,
    lr: Option<f32>,
    sets: &[String],
) -> anyhow::Result<(ModelConfig, Box<dyn Model>, Adam)> {
    let cfg = model_config(kind, skip, sets)?;
    let (model, adam) = cfg.build_with_adam(scene, seed, lr).map_err(|e| match e {
        ModelError::LearningRate(_) => anyhow::anyhow!("--lr: {e}"),
        // The configuration does not suit the dataset (e.g. space=ndc).
        _ => anyhow::anyhow!("{e}"),
    })?;
    Ok((cfg, model, adam))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_resolves_by_the_dataset_and_names_are_checked() {
        use crate::engine::dataset::synthetic::BallScene;
        use crate::engine::dataset::textured::TexturedScene;
        let ball = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
        let photos = TexturedScene { width: 8, height: 6, views: 6, fov: 0.9 }.dataset();
        let (kind, choice) = resolve_model("auto", &ball).unwrap();
        assert_eq!((kind.as_str(), choice.map(|c| c.preset)), ("instant", Some("instant".to_string())));
        let (kind, choice) = resolve_model("auto", &photos).unwrap();
        assert_eq!(kind, "capture-360", "the test scene's cameras go all around");
        assert!(choice.unwrap().reason.starts_with("opaque photographs"));
        // A named model is taken as it is, whatever the dataset.
        assert_eq!(resolve_model("nerf", &photos).unwrap(), ("nerf".to_string(), None));
        let e = resolve_model("fast", &photos).unwrap_err().to_string();
        assert_eq!(
            e,
            "unknown model 'fast' (available: auto, instant, instant-tiny, nerf, nerf-tiny, capture, capture-360, \
             capture-tiny)"
        );
        assert!(model_config("auto", true, &[]).unwrap_err().to_string().contains("resolved"));
    }

    #[test]
    fn sets_override_nested_fields_and_name_bad_keys() {
        let cfg = model_config("instant", true, &["grid.log2_table=17".into(), "occupancy.sweep=4".into()]).unwrap();
        let ModelConfig::Instant(c) = &cfg else { panic!("instant expected") };
        assert_eq!((c.grid.log2_table, c.occupancy.sweep), (17, 4));
        let err = |s: &str| model_config("instant", true, &[s.to_string()]).unwrap_err().to_string();
        assert!(err("grid.nope=1").contains("no field 'grid.nope'"), "{}", err("grid.nope=1"));
        assert!(err("grid=3").contains("group of settings"));
        assert!(err("hidden=wide").contains("--set"));
        assert!(err("grid.log2_table=40").contains("--set: instant config: grid.log2_table is 40, allowed 8..=24"));
        assert!(err("hidden").contains("KEY=VALUE"));
        assert!(err("kind=nerf").contains("--model"));
    }

    /// `space` is a setting of the capture model; the NDC camera it uses is
    /// derived from the cameras, so it is not one.
    #[test]
    fn sets_choose_the_capture_models_space() {
        use crate::engine::models::capture::Space;
        let space = |sets: &[&str]| {
            let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
            model_config("capture", true, &sets).map(|c| match c {
                ModelConfig::Capture(c) => (c.space, c.ndc_camera),
                _ => panic!("capture expected"),
            })
        };
        assert_eq!(space(&[]).unwrap(), (Space::Contract, None));
        assert_eq!(space(&["space=ndc"]).unwrap(), (Space::Ndc, None));
        assert_eq!(space(&["space=ndc", "space=contract"]).unwrap(), (Space::Contract, None));
        let err = space(&["space=sphere"]).unwrap_err().to_string();
        assert!(err.contains("--set") && err.contains("sphere"), "{err}");
        let err = space(&["ndc_camera.near=2"]).unwrap_err().to_string();
        assert!(err.contains("no field 'ndc_camera.near'"), "{err}");
    }
}
