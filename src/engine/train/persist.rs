//! Saving and restoring a model with its optimiser and trainer state, on top
//! of the generic checkpoint container.
//!
//! A finished model does not need its optimiser state (Adam's `m` and `v`,
//! two thirds of the file): [`strip_training_state`] rewrites a checkpoint
//! without them and marks it render-only (`meta.render_only`). [`load`]
//! reads both kinds (a render-only one with a zeroed Adam and
//! `Restored::render_only` set); [`load_resumable`] refuses a render-only
//! one, since training cannot continue exactly from it.
//!
//! Determinism: a checkpoint is a function of the data, the configuration,
//! the seed and the thread count, except for one field: `meta.timing` holds
//! the wall-clock training time (`TrainState::elapsed`, needed to resume a
//! time budget), and nothing else in the file depends on time. Two runs that
//! should agree give equal [`identity_bytes`], which are the checkpoint's
//! bytes without `meta.timing`.

use std::path::Path;

use serde_json::json;

use crate::engine::geometry::scene::Scene;
use crate::engine::io::checkpoint::{Checkpoint, CheckpointError, Tensor};
use crate::engine::models::Model;
use crate::engine::models::config::ModelConfig;
use crate::engine::models::training::TrainConfig;
use crate::engine::nn::adam::{Adam, AdamConfig};
use crate::engine::train::trainer::TrainState;
use crate::engine::transient::{SavedPhoto, TransientMaps};

/// A model restored from a checkpoint, ready to render or to train on.
pub struct Restored {
    pub model: Box<dyn Model>,
    pub adam: Adam,
    pub train: TrainConfig,
    pub state: TrainState,
    /// The checkpoint had no optimiser state ([`strip_training_state`]):
    /// `adam` is zeroed, and training would not continue exactly.
    pub render_only: bool,
    /// The transient maps of a run that dropped transients (they compare
    /// no photos: a resumed run's take their cells).
    pub transients: Option<TransientMaps>,
}

/// The meta key and tensors of the transient maps.
const TRANSIENT_PHOTOS: &str = "transient_photos";
const TRANSIENT_TENSORS: [&str; 3] = ["transients.sum", "transients.count", "transients.flags"];
/// The surface points the maps' cells saw, and how many rays met one
/// (absent from checkpoints written before the maps kept them: the cells
/// then gather them again).
const SURFACE_TENSORS: [&str; 2] = ["transients.points", "transients.hits"];

/// Builds the checkpoint of a training run, with its transient maps when it
/// drops transients.
pub fn to_checkpoint(
    model: &dyn Model,
    adam: &Adam,
    train: &TrainConfig,
    state: &TrainState,
    transients: Option<&TransientMaps>,
) -> Checkpoint {
    let mut c = Checkpoint::new(model.kind(), state.step);
    let mut state_json = serde_json::to_value(state).unwrap_or_default();
    if let Some(o) = state_json.as_object_mut() {
        o.remove("elapsed");
    }
    c.meta = json!({
        "model": model.config_json(),
        "scene": model.scene(),
        "train": train,
        "state": state_json,
        "adam": adam.config,
        TIMING: { "elapsed": state.elapsed },
    });
    c.insert("params", Tensor::F32(model.params().to_vec()));
    c.insert("adam.m", Tensor::F32(adam.m.clone()));
    c.insert("adam.v", Tensor::F32(adam.v.clone()));
    c.insert("adam.t", Tensor::U64(vec![adam.t]));
    for (name, data) in model.state_tensors() {
        c.insert(name, Tensor::F32(data));
    }
    if let Some(t) = transients {
        if let Some(o) = c.meta.as_object_mut() {
            o.insert(TRANSIENT_PHOTOS.into(), serde_json::to_value(t.photos()).unwrap_or_default());
        }
        let (sum, count, flags) = t.cells();
        c.insert(TRANSIENT_TENSORS[0], Tensor::F32(sum));
        c.insert(TRANSIENT_TENSORS[1], Tensor::F32(count));
        c.insert(TRANSIENT_TENSORS[2], Tensor::U8(flags));
        let (points, hits) = t.surfaces();
        c.insert(SURFACE_TENSORS[0], Tensor::F32(points));
        c.insert(SURFACE_TENSORS[1], Tensor::F32(hits));
    }
    c
}

/// The transient maps a checkpoint holds (none when its run kept every
/// pixel).
fn transients(c: &mut Checkpoint, path: &Path) -> Result<Option<TransientMaps>, CheckpointError> {
    if c.meta.get(TRANSIENT_PHOTOS).is_none() {
        return Ok(None);
    }
    let photos: Vec<SavedPhoto> = field(&c.meta, TRANSIENT_PHOTOS, path)?;
    let sum = c.take_f32(TRANSIENT_TENSORS[0]).map_err(|e| e.with_path(path))?;
    let count = c.take_f32(TRANSIENT_TENSORS[1]).map_err(|e| e.with_path(path))?;
    let flags = c.u8(TRANSIENT_TENSORS[2]).map_err(|e| e.with_path(path))?;
    let header = |message| CheckpointError::Header { path: Some(path.to_path_buf()), message };
    let mut maps = TransientMaps::from_saved(&photos, &sum, &count, flags).map_err(header)?;
    if c.tensor(SURFACE_TENSORS[0]).is_some() {
        let points = c.take_f32(SURFACE_TENSORS[0]).map_err(|e| e.with_path(path))?;
        let hits = c.take_f32(SURFACE_TENSORS[1]).map_err(|e| e.with_path(path))?;
        maps.set_surfaces(&points, &hits).map_err(header)?;
    }
    Ok(Some(maps))
}

/// The meta key of the only time-dependent part of a checkpoint.
pub const TIMING: &str = "timing";

/// The checkpoint's bytes without its wall-clock timing: equal for runs with
/// the same data, configuration, seed and thread count.
pub fn identity_bytes(c: &Checkpoint) -> Vec<u8> {
    let mut c = c.clone();
    if let Some(o) = c.meta.as_object_mut() {
        o.remove(TIMING);
    }
    c.to_bytes()
}

/// Saves atomically. Refuses to write parameters that are not finite.
pub fn save(
    path: &Path,
    model: &dyn Model,
    adam: &Adam,
    train: &TrainConfig,
    state: &TrainState,
    transients: Option<&TransientMaps>,
) -> Result<(), CheckpointError> {
    if let Some(i) = model.params().iter().position(|p| !p.is_finite()) {
        return Err(CheckpointError::Header {
            path: Some(path.to_path_buf()),
            message: format!("refusing to save a model with a non-finite parameter (index {i})"),
        });
    }
    to_checkpoint(model, adam, train, state, transients).save(path)
}

fn field<T: serde::de::DeserializeOwned>(
    meta: &serde_json::Value,
    key: &str,
    path: &Path,
) -> Result<T, CheckpointError> {
    serde_json::from_value(meta.get(key).cloned().unwrap_or(serde_json::Value::Null))
        .map_err(|e| CheckpointError::Header { path: Some(path.to_path_buf()), message: format!("meta.{key}: {e}") })
}

/// The meta key that marks a checkpoint without optimiser state.
pub const RENDER_ONLY: &str = "render_only";
/// The tensors [`strip_training_state`] drops.
const OPTIMISER_TENSORS: [&str; 2] = ["adam.m", "adam.v"];

/// Rewrites the checkpoint at `path` atomically without its optimiser
/// moments, marked render-only; the model renders exactly as before.
/// Returns `false` (and writes nothing) when it already was render-only.
pub fn strip_training_state(path: &Path) -> Result<bool, CheckpointError> {
    let mut c = Checkpoint::load(path)?;
    if is_render_only(&c) {
        return Ok(false);
    }
    let Some(meta) = c.meta.as_object_mut() else {
        return Err(CheckpointError::Header {
            path: Some(path.to_path_buf()),
            message: "meta is not an object".into(),
        });
    };
    meta.insert(RENDER_ONLY.into(), true.into());
    c.tensors.retain(|(name, _)| !OPTIMISER_TENSORS.contains(&name.as_str()));
    c.save(path)?;
    Ok(true)
}

fn is_render_only(c: &Checkpoint) -> bool {
    c.meta.get(RENDER_ONLY).and_then(|v| v.as_bool()) == Some(true)
}

/// Like [`load`], but refuses a render-only checkpoint: training resumed
/// from it would not continue the run exactly.
pub fn load_resumable(path: &Path) -> Result<Restored, CheckpointError> {
    let r = load(path)?;
    if r.render_only {
        return Err(CheckpointError::Header {
            path: Some(path.to_path_buf()),
            message:
                "this checkpoint was stripped of its optimiser state (render-only); training cannot resume from it"
                    .into(),
        });
    }
    Ok(r)
}

/// Restores a checkpoint written by [`save`] (or stripped by
/// [`strip_training_state`]: then with a zeroed Adam and `render_only`).
pub fn load(path: &Path) -> Result<Restored, CheckpointError> {
    let mut c = Checkpoint::load(path)?;
    let bad = |message: String| CheckpointError::Header { path: Some(path.to_path_buf()), message };
    let scene: Scene = field(&c.meta, "scene", path)?;
    let params = c.take_f32("params").map_err(|e| e.with_path(path))?;
    let nparams = params.len();
    // The mirror of `to_checkpoint`: the kind and its config rebuild the
    // model, which takes back the state tensors it saved.
    let config = ModelConfig::parse(&c.kind, c.meta.get("model").cloned().unwrap_or_default())
        .map_err(|e| bad(format!("meta.model: {e}")))?;
    let mut model = config.spec().rebuild(scene, params).map_err(|e| bad(e.to_string()))?;
    let step = c.step;
    model.restore_state(&mut |name| c.take_f32(name).ok(), step).map_err(|e| bad(e.to_string()))?;
    let adam_cfg: AdamConfig = field(&c.meta, "adam", path)?;
    let state: TrainState = field(&c.meta, "state", path)?;
    let transients = transients(&mut c, path)?;
    let render_only = is_render_only(&c);
    let (m, v) = if render_only {
        (vec![0.0; nparams], vec![0.0; nparams])
    } else {
        (c.take_f32("adam.m").map_err(|e| e.with_path(path))?, c.take_f32("adam.v").map_err(|e| e.with_path(path))?)
    };
    let t = match render_only {
        true => 0,
        false => c.u64("adam.t").map_err(|e| e.with_path(path))?.first().copied().unwrap_or(0),
    };
    if m.len() != nparams || v.len() != nparams {
        return Err(bad(format!("optimizer state has {} / {} values for {nparams} parameters", m.len(), v.len())));
    }
    Ok(Restored {
        model,
        adam: Adam { config: adam_cfg, m, v, t },
        train: field(&c.meta, "train", path)?,
        state: TrainState {
            // Checkpoints before `meta.timing` kept it in the state.
            elapsed: c.meta.pointer("/timing/elapsed").and_then(|v| v.as_f64()).unwrap_or(state.elapsed),
            ..state
        },
        render_only,
        transients,
    })
}
