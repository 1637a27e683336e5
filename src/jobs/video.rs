//! A video job: render an orbit around a trained model's scene, or a camera
//! path through keyframes, frame by frame on the worker pool, and encode it (GIF or MP4). The file and then
//! its record are written atomically, so a video either exists whole or not
//! at all; an interrupted job renders again from the start.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::host::JobHost;
use super::{Job, Outcome, VideoSpec};
use crate::engine::geometry::camera::Camera;
use crate::engine::train::persist;
use crate::engine::view::render_view_with;
use crate::media::{png, video};
use crate::storage::{VideoInfo, now_ms};

pub(crate) fn run(host: &dyn JobHost, job: &Job, spec: &VideoSpec, cancel: &AtomicBool) -> Outcome {
    match render(host, job, spec, cancel) {
        Ok(o) => o,
        Err(e) => Outcome::Failed(e),
    }
}

fn render(host: &dyn JobHost, job: &Job, spec: &VideoSpec, cancel: &AtomicBool) -> Result<Outcome, String> {
    let model_id = job.model_id.clone().unwrap_or_default();
    let info = host
        .model(&model_id)
        .map_err(|e| e.to_string())?
        .ok_or_else(|| format!("model '{model_id}' no longer exists"))?;
    let ckpt = host.model_checkpoint(&info).map_err(|e| format!("loading the model: {e}"))?;
    let model = persist::load(&ckpt.path).map_err(|e| format!("loading the model: {e}"))?.model;
    let orbit = info.view.orbit(spec.elevation, spec.radius);
    let started = Instant::now();
    let mut frames = Vec::with_capacity(spec.frames as usize);
    for k in 0..spec.frames {
        if cancel.load(Ordering::Relaxed) {
            return Ok(Outcome::Stopped);
        }
        let camera = match &spec.path {
            Some(path) => {
                let (c2w, fov) = path.at(path.frame_time(k, spec.frames));
                Camera::from_fov(spec.width, spec.height, fov.to_radians(), c2w)
            }
            None => orbit
                .camera(360.0 * k as f32 / spec.frames as f32, spec.width, spec.height, spec.fov)
                .ok_or("this orbit gives no well-defined camera (elevation of +-90 degrees?)")?,
        };
        let options = spec.appearance.resolve(&*model, &camera).map_err(|e| e.to_string())?;
        let view = render_view_with(&*model, &camera, [1.0; 3], &options);
        frames.push(png::rgb_image(&view).map_err(|e| e.to_string())?);
        let done = k as u64 + 1;
        let elapsed = started.elapsed().as_secs_f64();
        host.set_progress(&job.id, &mut |j| {
            j.progress.step = done;
            j.progress.total_steps = Some(spec.frames as u64);
            j.progress.elapsed = elapsed;
            j.progress.eta = Some(elapsed / done as f64 * (spec.frames as u64 - done) as f64);
        });
    }
    let bytes = video::encode(spec.format, &frames, spec.fps).map_err(|e| format!("encoding the video: {e}"))?;
    let id = job.reserved_video_id();
    let record = VideoInfo {
        id: id.clone(),
        model_id,
        job_id: job.id.clone(),
        format: spec.format,
        frames: spec.frames,
        fps: spec.fps,
        width: spec.width,
        height: spec.height,
        size_bytes: bytes.len() as u64,
        created_at: now_ms(),
    };
    host.publish_video(job, &record, &bytes).map_err(|e| e.to_string())?;
    let elapsed = started.elapsed().as_secs_f64();
    host.set_progress(&job.id, &mut |j| {
        j.video_id = Some(id.clone());
        j.progress.elapsed = elapsed;
        j.progress.eta = Some(0.0);
    });
    Ok(Outcome::Succeeded)
}
