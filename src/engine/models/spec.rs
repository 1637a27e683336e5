//! What each model kind's configuration provides the registry
//! (`config`): the one trait a kind implements ([`ModelSpec`]), the sizes it
//! reports for estimates, and the checks of its fields. A leaf of
//! `models`: the kinds use it, and the registry uses them and it.

use std::ops::RangeInclusive;

use crate::engine::geometry::scene::Scene;
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::AdamConfig;
use crate::engine::sampling::occupancy::OccupancyConfig;

/// What a model kind's configuration provides: the one interface through
/// which a kind plugs into checks, building, loading and estimates. Each
/// model's file implements it for its config.
pub trait ModelSpec {
    /// The kind's name, as checkpoints and the API tag it.
    fn kind(&self) -> &'static str;
    /// Records every field out of range in `c`.
    fn check(&self, c: &mut Checks);
    /// A freshly initialised model for `scene`; an error when the
    /// configuration does not suit the scene (e.g. `capture`'s NDC space on
    /// cameras that do not face one way).
    fn build(&self, scene: Scene, seed: u64) -> Result<Box<dyn Model>, ModelError>;
    /// A model with saved parameters (its state then comes back through
    /// `Model::restore_state`).
    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError>;
    /// Whether the trainer can train the kind from rays (`Model::train_rays`);
    /// `false` for a kind made another way (splats, by `bake`).
    fn trains_on_rays(&self) -> bool {
        true
    }
    /// The optimiser's settings.
    fn adam(&self) -> AdamConfig;
    /// Whether training composites RGBA images on a random colour per ray
    /// (to learn transparency) rather than on the dataset's background.
    fn random_background(&self) -> bool;
    /// Sizes for the memory estimate, with `threads` training threads.
    fn footprint(&self, threads: u64) -> Footprint;
}

/// What a model holds, for `train::estimate`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Footprint {
    pub params: u64,
    /// Cells of its occupancy grid (0 without one).
    pub occupancy_cells: u64,
    /// f32 values of one training thread's activations and scratch.
    pub activations: u64,
}

/// The occupancy grid's fields, shared by the kinds that have one.
pub fn check_occupancy(o: &OccupancyConfig, c: &mut Checks) {
    c.int("occupancy.resolution", o.resolution, 1..=256);
    c.int("occupancy.sweep", o.sweep, 1..=u64::MAX);
    c.int("occupancy.update_every", o.update_every, 1..=u64::MAX);
    if !o.threshold.is_finite() {
        c.fail("occupancy.threshold", FieldValue::Float(o.threshold), "a finite number".into());
    }
    if !(o.decay.is_finite() && (0.0..=1.0).contains(&o.decay)) {
        c.fail("occupancy.decay", FieldValue::Float(o.decay), "[0, 1]".into());
    }
}

/// A configuration refused by [`ModelConfig::check`]: every field out of
/// range, in the order they appear in the configuration.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{kind} config: {}", .fields.iter().map(|f| f.to_string()).collect::<Vec<_>>().join("; "))]
pub struct ConfigError {
    /// `instant`, `nerf` or `capture`.
    pub kind: &'static str,
    pub fields: Vec<FieldError>,
}

/// One field out of range: its dotted path, its value and what is allowed.
/// Serialised as the API's error details (`{"field", "value", "allowed"}`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, thiserror::Error)]
#[error("{field} is {value}, allowed {allowed}")]
pub struct FieldError {
    pub field: &'static str,
    pub value: FieldValue,
    pub allowed: String,
}

/// A field's value as found (a JSON number or boolean; NaN serialises as
/// `null`, which JSON input cannot produce anyway).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(untagged)]
pub enum FieldValue {
    Int(u64),
    Float(f32),
    Bool(bool),
}

impl std::fmt::Display for FieldValue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FieldValue::Int(v) => write!(f, "{v}"),
            FieldValue::Float(v) => write!(f, "{v}"),
            FieldValue::Bool(v) => write!(f, "{v}"),
        }
    }
}

/// Collects the failures of one configuration.
pub struct Checks {
    kind: &'static str,
    fields: Vec<FieldError>,
}

impl Checks {
    /// An integer field that must lie in `allowed` (`N..=u64::MAX` reads
    /// `>= N`).
    pub fn int(&mut self, field: &'static str, value: impl TryInto<u64>, allowed: RangeInclusive<u64>) {
        let value = value.try_into().unwrap_or(u64::MAX);
        if !allowed.contains(&value) {
            let text = match *allowed.end() {
                u64::MAX => format!(">= {}", allowed.start()),
                end => format!("{}..={end}", allowed.start()),
            };
            self.fail(field, FieldValue::Int(value), text);
        }
    }

    /// A float field in [0, 1).
    pub fn unit_open(&mut self, field: &'static str, value: f32) {
        if !(value.is_finite() && (0.0..1.0).contains(&value)) {
            self.fail(field, FieldValue::Float(value), "[0, 1)".into());
        }
    }

    pub fn fail(&mut self, field: &'static str, value: FieldValue, allowed: String) {
        self.fields.push(FieldError { field, value, allowed });
    }

    /// No failures yet, for a configuration of `kind`.
    pub fn new(kind: &'static str) -> Self {
        Self { kind, fields: Vec::new() }
    }

    /// The failures found, as one error.
    pub fn finish(self) -> Result<(), ConfigError> {
        if self.fields.is_empty() { Ok(()) } else { Err(ConfigError { kind: self.kind, fields: self.fields }) }
    }
}
