//! Which model to train and how: the configuration of either model kind,
//! the named presets, and everything that differs between the kinds when a
//! fresh model is built (its optimiser settings, its training settings).
//! The CLI and the job runner both build models through this, so they train
//! the same way.

pub use super::spec::{Checks, ConfigError, FieldError, FieldValue, Footprint, ModelSpec, check_occupancy};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::capture::CaptureConfig;
use crate::engine::models::instant::InstantConfig;
use crate::engine::models::nerf::NerfConfig;
use crate::engine::models::splats::SplatsConfig;
use crate::engine::models::training::{Budget, TrainConfig};
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::{Adam, AdamConfig};

/// The model kinds: one line each, `Variant(ConfigType) = module`. The
/// module (`models/<module>/`) provides `KIND`, its config type with
/// `impl ModelSpec`, and `config::PRESETS` / `config::preset` (its named
/// configurations, the default first). From this list come the tagged
/// [`ModelConfig`] enum, [`ModelConfig::spec`], [`KINDS`], [`presets`] and
/// [`ModelConfig::preset`].
macro_rules! registry {
    ($($(#[$doc:meta])* $variant:ident($config:ty) = $module:ident,)+) => {
        /// A model configuration of any kind, tagged by `kind` in JSON.
        #[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
        #[serde(tag = "kind", rename_all = "lowercase")]
        pub enum ModelConfig {
            $($(#[$doc])* $variant($config),)+
        }

        /// The kinds, as [`ModelConfig`] tags them.
        pub const KINDS: &[&str] = &[$(super::$module::KIND,)+];

        /// The names [`ModelConfig::preset`] knows, kind by kind, each
        /// kind's default first (the first is the default of all).
        pub fn presets() -> Vec<&'static str> {
            let mut all = Vec::new();
            $(all.extend_from_slice(super::$module::config::PRESETS);)+
            all
        }

        impl ModelConfig {
            /// The kind's own configuration.
            pub fn spec(&self) -> &dyn ModelSpec {
                match self {
                    $(ModelConfig::$variant(c) => c,)+
                }
            }

            /// A named configuration (one of [`presets`]); `None` for an
            /// unknown name. Each kind's presets are documented in its
            /// `config::preset`.
            pub fn preset(name: &str) -> Option<Self> {
                $(if let Some(c) = super::$module::config::preset(name) {
                    return Some(ModelConfig::$variant(c));
                })+
                None
            }
        }
    };
}

registry! {
    /// The fast model: hash grid, tiny MLPs, occupancy-grid marching.
    Instant(InstantConfig) = instant,
    /// The classic NeRF of the paper.
    Nerf(NerfConfig) = nerf,
    /// Real captures: contracted unbounded space, proposal sampling,
    /// per-image appearance.
    Capture(CaptureConfig) = capture,
    /// 3D Gaussian splats baked from a trained model, rasterised.
    Splats(SplatsConfig) = splats,
}

/// The presets a training run can start from ([`presets`] of the kinds
/// that train on rays; splats are baked from one of them instead).
pub fn trainable_presets() -> Vec<&'static str> {
    presets().into_iter().filter(|p| ModelConfig::preset(p).is_some_and(|c| c.spec().trains_on_rays())).collect()
}

/// Rays per optimisation step for `nerf` (the fast model adapts its number of
/// rays to a constant sample budget and ignores this).
pub const DEFAULT_BATCH_RAYS: usize = 1024;

impl ModelConfig {
    /// The configuration a built model runs with (as its checkpoint stores it).
    pub fn of_model(model: &dyn Model) -> Option<Self> {
        Self::from_kind_json(model.kind(), model.config_json())
    }

    /// A configuration from a model kind and its untagged JSON (as
    /// `Model::config_json` writes it).
    pub fn from_kind_json(kind: &str, json: serde_json::Value) -> Option<Self> {
        Self::parse(kind, json).ok()
    }

    /// Like [`ModelConfig::from_kind_json`], saying what was wrong.
    pub fn parse(kind: &str, mut json: serde_json::Value) -> Result<Self, ModelError> {
        let Some(kind) = KINDS.iter().copied().find(|k| *k == kind) else {
            return Err(ModelError::UnknownKind(kind.to_string()));
        };
        let Some(fields) = json.as_object_mut() else {
            return Err(ModelError::Config { kind, message: format!("expected a JSON object, found {json}") });
        };
        fields.insert("kind".into(), kind.into());
        serde_json::from_value(json).map_err(|e| ModelError::Config { kind, message: e.to_string() })
    }

    /// `instant`, `nerf` or `capture`.
    pub fn kind(&self) -> &'static str {
        self.spec().kind()
    }

    /// Refuses configurations that would allocate absurdly or not run.
    /// Every field out of range is reported, each with its value and the
    /// allowed range, so a client fixes them all in one go.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = Checks::new(self.kind());
        self.spec().check(&mut c);
        c.finish()
    }

    /// A freshly initialised model for `scene` (see [`ModelSpec::build`]).
    pub fn build(&self, scene: Scene, seed: u64) -> Result<Box<dyn Model>, ModelError> {
        self.spec().build(scene, seed)
    }

    /// Adam's settings for the kind.
    pub fn adam(&self) -> AdamConfig {
        self.spec().adam()
    }

    /// A fresh model and its optimiser; `lr` replaces the initial learning
    /// rate and scales the final one with it.
    pub fn build_with_adam(
        &self,
        scene: Scene,
        seed: u64,
        lr: Option<f32>,
    ) -> Result<(Box<dyn Model>, Adam), ModelError> {
        let mut cfg = self.adam();
        if let Some(lr) = lr {
            if !(lr.is_finite() && lr > 0.0) {
                return Err(ModelError::LearningRate(lr));
            }
            cfg.lr_end = lr * cfg.lr_end / cfg.lr;
            cfg.lr = lr;
        }
        let model = self.build(scene, seed)?;
        let adam = Adam::new(cfg, model.params().len());
        Ok((model, adam))
    }

    /// Training settings for the kind.
    pub fn train_config(&self, seed: u64, batch_rays: usize, budget: Budget) -> TrainConfig {
        TrainConfig {
            seed,
            batch_rays,
            budget,
            random_background: self.spec().random_background(),
            model_choice: None,
            drop_transients: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    #[test]
    fn presets_are_valid_and_build() {
        let ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        for name in presets() {
            let c = ModelConfig::preset(name).unwrap();
            c.check().unwrap_or_else(|e| panic!("{name}: {e}"));
            if !c.spec().trains_on_rays() {
                // Made by baking: building one fresh is refused, saying so.
                let e = c.build(ds.scene(), 1).err().expect("refused");
                assert!(e.to_string().contains("bake"), "{name}: {e}");
                continue;
            }
            let (m, adam) = c.build_with_adam(ds.scene(), 1, None).unwrap();
            assert_eq!(m.kind(), c.kind());
            assert_eq!(adam.m.len(), m.params().len());
        }
        assert!(ModelConfig::preset("nope").is_none());
    }

    #[test]
    fn json_is_tagged_by_kind_and_round_trips() {
        let c = ModelConfig::preset("instant-tiny").unwrap();
        let v = serde_json::to_value(&c).unwrap();
        assert_eq!(v["kind"], "instant");
        assert_eq!(v["hidden"], 32);
        assert_eq!(serde_json::from_value::<ModelConfig>(v).unwrap(), c);
        for name in ["capture", "capture-tiny"] {
            let c = ModelConfig::preset(name).unwrap();
            let v = serde_json::to_value(&c).unwrap();
            assert_eq!((v["kind"].as_str(), v["contraction"].as_str()), (Some("capture"), Some("linf")));
            assert_eq!(v["proposal"]["coarse_samples"], if name == "capture" { 64 } else { 16 });
            assert_eq!(serde_json::from_value::<ModelConfig>(v.clone()).unwrap(), c);
            // The untagged form a checkpoint stores parses back too.
            let mut untagged = v;
            untagged.as_object_mut().unwrap().remove("kind");
            assert_eq!(ModelConfig::parse("capture", untagged).unwrap(), c);
        }
        let bad = ModelConfig::parse("capture", serde_json::json!({ "contraction": "l3" })).unwrap_err();
        assert!(bad.to_string().starts_with("the capture model's configuration:"), "{bad}");
    }

    #[test]
    fn out_of_range_configs_are_refused() {
        let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
        c.grid.log2_table = 40;
        assert!(ModelConfig::Instant(c).check().unwrap_err().to_string().contains("log2_table"));
        let ModelConfig::Nerf(mut n) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
        n.net.skip = n.net.depth;
        assert!(ModelConfig::Nerf(n).check().unwrap_err().to_string().contains("skip"));
        // The classic sampler steps half a cell: its grid must be dilated.
        let ModelConfig::Nerf(mut n) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
        let mut o = n.occupancy.clone().expect("the preset skips");
        for (dilate, ok) in [(Some(false), false), (None, true), (Some(true), true)] {
            o.dilate = dilate;
            n.occupancy = Some(o.clone());
            let r = ModelConfig::Nerf(n.clone()).check();
            assert_eq!(r.is_ok(), ok, "{dilate:?}: {r:?}");
            assert!(ok || r.unwrap_err().to_string().contains("occupancy.dilate"));
        }
        let ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        let c = ModelConfig::preset("nerf-tiny").unwrap();
        assert!(c.build_with_adam(ds.scene(), 0, Some(f32::NAN)).is_err());
    }

    type Instant = fn(&mut InstantConfig);
    type Nerf = fn(&mut NerfConfig);
    type Capture = fn(&mut CaptureConfig);

    /// One bad value per checked field of the fast model.
    const INSTANT_CASES: [(&str, Instant); 16] = [
        ("grid.levels", |c| c.grid.levels = 0),
        ("grid.log2_table", |c| c.grid.log2_table = 40),
        ("grid.base_resolution", |c| c.grid.base_resolution = 1),
        ("grid.finest_resolution", |c| c.grid.finest_resolution = 9000),
        ("hidden", |c| c.hidden = 0),
        ("geo_features", |c| c.geo_features = 65),
        ("occupancy.resolution", |c| c.occupancy.resolution = 257),
        ("occupancy.sweep", |c| c.occupancy.sweep = 0),
        ("occupancy.update_every", |c| c.occupancy.update_every = 0),
        ("occupancy.threshold", |c| c.occupancy.threshold = f32::INFINITY),
        ("occupancy.decay", |c| c.occupancy.decay = 1.5),
        ("steps_per_diagonal", |c| c.steps_per_diagonal = 8),
        ("max_samples", |c| c.max_samples = 0),
        ("samples_per_step", |c| c.samples_per_step = 1 << 21),
        ("min_transmittance", |c| c.min_transmittance = 1.0),
        ("chunk_rays", |c| c.chunk_rays = 5000),
    ];

    /// One bad value per checked field of the classic model.
    const NERF_CASES: [(&str, Nerf); 15] = [
        ("net.width", |c| c.net.width = 0),
        ("net.depth", |c| c.net.depth = 33),
        ("net.skip", |c| c.net.skip = 100),
        ("net.pos_freqs", |c| c.net.pos_freqs = 25),
        ("net.dir_freqs", |c| c.net.dir_freqs = 25),
        ("net.dir_width", |c| c.net.dir_width = 2000),
        ("coarse_samples", |c| c.coarse_samples = 0),
        ("fine_samples", |c| c.fine_samples = 1025),
        ("chunk_rays", |c| c.chunk_rays = 0),
        ("min_transmittance", |c| c.min_transmittance = f32::NAN),
        ("occupancy.resolution", |c| c.occupancy.as_mut().unwrap().resolution = 0),
        ("occupancy.sweep", |c| c.occupancy.as_mut().unwrap().sweep = 0),
        ("occupancy.update_every", |c| c.occupancy.as_mut().unwrap().update_every = 0),
        ("occupancy.decay", |c| c.occupancy.as_mut().unwrap().decay = -0.5),
        ("occupancy.dilate", |c| c.occupancy.as_mut().unwrap().dilate = Some(false)),
    ];

    /// One bad value per checked field of the real-capture model.
    const CAPTURE_CASES: [(&str, Capture); 34] = [
        ("camera_radius", |c| c.camera_radius = 0.0),
        ("near", |c| c.near = -1.0),
        ("far", |c| c.far = 0.01),
        ("grid.levels", |c| c.grid.levels = 0),
        ("grid.log2_table", |c| c.grid.log2_table = 30),
        ("grid.base_resolution", |c| c.grid.base_resolution = 1),
        ("grid.finest_resolution", |c| c.grid.finest_resolution = 10_000),
        ("hidden", |c| c.hidden = 300),
        ("geo_features", |c| c.geo_features = 0),
        ("init_density", |c| c.init_density = f32::NAN),
        ("appearance_dim", |c| c.appearance_dim = 65),
        ("max_images", |c| c.max_images = 0),
        ("proposal.coarse_samples", |c| c.proposal.coarse_samples = 0),
        ("proposal.fine_samples", |c| c.proposal.fine_samples = 2000),
        ("proposal.coarse_grid.levels", |c| c.proposal.coarse_grid.levels = 40),
        ("proposal.coarse_grid.log2_table", |c| c.proposal.coarse_grid.log2_table = 4),
        ("proposal.coarse_grid.base_resolution", |c| c.proposal.coarse_grid.base_resolution = 0),
        ("proposal.coarse_grid.finest_resolution", |c| c.proposal.coarse_grid.finest_resolution = 8),
        ("proposal.fine_grid.levels", |c| c.proposal.fine_grid.levels = 0),
        ("proposal.fine_grid.log2_table", |c| c.proposal.fine_grid.log2_table = 25),
        ("proposal.fine_grid.base_resolution", |c| c.proposal.fine_grid.base_resolution = 1),
        ("proposal.fine_grid.finest_resolution", |c| c.proposal.fine_grid.finest_resolution = 9000),
        ("proposal.hidden", |c| c.proposal.hidden = 0),
        ("proposal.padding", |c| c.proposal.padding = -0.1),
        ("proposal.anneal_slope", |c| c.proposal.anneal_slope = 0.0),
        ("samples", |c| c.samples = 0),
        ("rays_per_step", |c| c.rays_per_step = 1 << 17),
        ("chunk_rays", |c| c.chunk_rays = 0),
        ("interlevel", |c| c.interlevel = f32::INFINITY),
        ("distortion", |c| c.distortion = -1.0),
        ("min_transmittance", |c| c.min_transmittance = 1.0),
        ("max_dropped_weight", |c| c.max_dropped_weight = -0.5),
        // Both bounds of the ray interval: a far bound below the near one
        // names the far bound.
        ("far", |c| c.far = f32::INFINITY),
        ("near", |c| c.near = f32::NAN),
    ];

    /// Checks that `bad` fails on `field` alone and that its message names
    /// that field, with its value, and no other field of `all`.
    fn assert_names_only(bad: ModelConfig, field: &str, all: &[&str]) {
        let e = bad.check().expect_err(field);
        let fields: Vec<&str> = e.fields.iter().map(|f| f.field).collect();
        assert_eq!(fields, [field]);
        let msg = e.to_string();
        assert!(
            msg.starts_with(&format!("{} config: {field} is {}, allowed ", bad.kind(), e.fields[0].value)),
            "{msg}"
        );
        for other in all.iter().filter(|&&o| o != field) {
            assert!(!names_field(&msg, other), "{field}: the message also names {other}: {msg}");
        }
    }

    /// Whether `msg` holds `name` as a whole field name (not as the end of
    /// a longer one: `samples` in `proposal.coarse_samples`).
    fn names_field(msg: &str, name: &str) -> bool {
        let part = |c: char| c.is_ascii_alphanumeric() || c == '_' || c == '.';
        msg.match_indices(name).any(|(i, _)| {
            let before = msg[..i].chars().next_back().is_none_or(|c| !part(c));
            let after = msg[i + name.len()..].chars().next().is_none_or(|c| !part(c));
            before && after
        })
    }

    #[test]
    fn each_field_out_of_range_is_named_alone() {
        let names: Vec<&str> = INSTANT_CASES.iter().map(|(n, _)| *n).collect();
        for (field, spoil) in INSTANT_CASES {
            let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
            spoil(&mut c);
            assert_names_only(ModelConfig::Instant(c), field, &names);
        }
        let names: Vec<&str> = NERF_CASES.iter().map(|(n, _)| *n).collect();
        for (field, spoil) in NERF_CASES {
            let ModelConfig::Nerf(mut c) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
            spoil(&mut c);
            assert_names_only(ModelConfig::Nerf(c), field, &names);
        }
        let names: Vec<&str> = CAPTURE_CASES.iter().map(|(n, _)| *n).collect();
        for (field, spoil) in CAPTURE_CASES {
            let ModelConfig::Capture(mut c) = ModelConfig::preset("capture").unwrap() else { unreachable!() };
            spoil(&mut c);
            assert_names_only(ModelConfig::Capture(c), field, &names);
        }
    }

    #[test]
    fn every_failing_field_is_reported_with_its_value_and_range() {
        let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
        c.grid.log2_table = 40;
        c.hidden = 0;
        c.occupancy.decay = 1.5;
        let e = ModelConfig::Instant(c).check().unwrap_err();
        assert_eq!(
            e.to_string(),
            "instant config: grid.log2_table is 40, allowed 8..=24; hidden is 0, allowed 1..=256; \
             occupancy.decay is 1.5, allowed [0, 1]"
        );
        assert_eq!(
            serde_json::to_value(&e.fields).unwrap(),
            serde_json::json!([
                { "field": "grid.log2_table", "value": 40, "allowed": "8..=24" },
                { "field": "hidden", "value": 0, "allowed": "1..=256" },
                { "field": "occupancy.decay", "value": 1.5, "allowed": "[0, 1]" },
            ])
        );
        let ModelConfig::Nerf(mut n) = ModelConfig::preset("nerf").unwrap() else { unreachable!() };
        n.net.skip = 9;
        n.net.depth = 8;
        n.occupancy.as_mut().unwrap().sweep = 0;
        let e = ModelConfig::Nerf(n).check().unwrap_err();
        assert_eq!(e.to_string(), "nerf config: net.skip is 9, allowed 0..8; occupancy.sweep is 0, allowed >= 1");
    }
}
