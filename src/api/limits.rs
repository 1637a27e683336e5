//! What a job may cost: its estimated peak memory against the per-job limit,
//! and its checkpoint against the free disk space less a reserve. A job that
//! does not fit is refused before it is queued, with the estimate and the
//! limit in the error's `details`.

use serde_json::json;

use super::{ApiError, Code, ServiceConfig};
use crate::engine::front::{DataSize, DatasetFormat, Estimate, MaskUse, mib};
use crate::records::SceneInfo;

/// The dataset a training job will load with `masks`: every frame of every
/// split at the scene's resolution (formats without a split hold their
/// held-out frames once, as both `val` and `test`), and at most what masks
/// add: a byte per pixel when they may be in effect (asked for, or `auto`
/// on a scene with a mask folder), and with `ignore` every training pixel
/// counted as inside.
pub fn scene_data(scene: &SceneInfo, masks: MaskUse) -> DataSize {
    let i = &scene.images;
    let frames = match scene.format {
        DatasetFormat::Blender => i.train + i.val + i.test,
        DatasetFormat::Ngp | DatasetFormat::Llff | DatasetFormat::Colmap => i.train + i.test.max(i.val),
    };
    let mut data = DataSize::uniform(frames, scene.resolution[0], scene.resolution[1]);
    let masked = match masks {
        MaskUse::Off => false,
        MaskUse::Auto => scene.mask_folder.is_some(),
        MaskUse::Score | MaskUse::Ignore | MaskUse::Composite => true,
    };
    if masked {
        data.mask_pixels = data.pixels;
    }
    if masks == MaskUse::Ignore {
        data.inside_pixels = DataSize::uniform(i.train, scene.resolution[0], scene.resolution[1]).pixels;
    }
    data
}

/// Refuses a job whose estimate passes the per-job memory limit (422
/// `resource_limit`) or whose checkpoint would leave less free disk than
/// the reserve (507 `insufficient_storage`); `free_disk` is the artifact
/// store's free space (`None`: not known, not checked).
pub fn check(e: &Estimate, config: &ServiceConfig, free_disk: Option<u64>) -> Result<(), ApiError> {
    let parts: serde_json::Map<String, serde_json::Value> =
        e.parts.iter().map(|(k, v)| (k.clone(), json!(v))).collect();
    if e.memory_bytes > config.scheduler.max_job_memory_bytes {
        return Err(ApiError::new(
            Code::ResourceLimit,
            format!(
                "this job would need about {} of memory ({}), more than the server allows a job ({}, \
                 --max-job-memory-mb): use a smaller configuration",
                mib(e.memory_bytes),
                e.describe(),
                mib(config.scheduler.max_job_memory_bytes)
            ),
        )
        .with_details(json!({
            "estimate_bytes": e.memory_bytes,
            "limit_bytes": config.scheduler.max_job_memory_bytes,
            "parts": parts,
        })));
    }
    if let Some(free) = free_disk {
        let need = e.disk_bytes.saturating_add(config.min_free_disk_bytes);
        if free < need {
            return Err(ApiError::new(
                Code::InsufficientStorage,
                format!(
                    "not enough disk space: this job writes up to {}, {} are free and {} must stay free \
                     (--min-free-disk-mb); delete models or videos you no longer need",
                    mib(e.disk_bytes),
                    mib(free),
                    mib(config.min_free_disk_bytes)
                ),
            )
            .with_details(json!({
                "output_bytes": e.disk_bytes,
                "free_bytes": free,
                "reserve_bytes": config.min_free_disk_bytes,
            })));
        }
    }
    Ok(())
}
