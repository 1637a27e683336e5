//! A video job: render an orbit around a trained model's scene, or a camera
//! path through keyframes, frame by frame on the worker pool, and encode it (GIF or MP4). The file and then
//! its record are written atomically, so a video either exists whole or not
//! at all. Where the host keeps them (`JobHost::video_frames_dir`), each
//! frame rendered is saved (a PNG, atomically), so a job cut short by a
//! crash renders only the frames it had not saved; they go when it ends.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use super::host::JobHost;
use super::{Job, JobError, Outcome, VideoSpec};
use crate::datadir::{DataDir, now_ms};
use crate::engine::front::{Camera, crop_model, load_model, render_view_with, write_atomic};
use crate::media::{png, video};
use crate::records::VideoInfo;

/// Whether the video job `job_id` saved a frame after `since` (ms since
/// the epoch): the crash rule's "progress in between" for video jobs.
pub(crate) fn saved_frames_since(storage: &DataDir, job_id: &str, since: Option<u64>) -> bool {
    let modified = std::fs::metadata(storage.video_frames_dir(job_id)).and_then(|m| m.modified()).ok();
    let ms = modified.and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_millis() as u64);
    matches!((ms, since), (Some(m), Some(s)) if m > s)
}

/// A frame saved by a run before, if it is whole and of the video's size.
fn saved_frame(path: &Path, width: u32, height: u32) -> Option<image::RgbImage> {
    let img = image::load_from_memory_with_format(&std::fs::read(path).ok()?, image::ImageFormat::Png).ok()?;
    Some(img.to_rgb8()).filter(|i| i.dimensions() == (width, height))
}

fn save_frame(path: &Path, img: &image::RgbImage) -> Result<(), JobError> {
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).map_err(JobError::PngEncode)?;
    write_atomic(path, &png).map_err(JobError::SaveFrame)
}

/// The body of a video job (see [`super::run_body`]).
pub(crate) fn run(host: &dyn JobHost, job: &Job, spec: &VideoSpec, cancel: &AtomicBool) -> Result<Outcome, JobError> {
    let outcome = render(host, job, spec, cancel);
    // Kept only for a run to come (stopped by a shutdown; a canceled job's
    // go when its end is recorded).
    if !matches!(outcome, Ok(Outcome::Stopped))
        && let Some(dir) = host.video_frames_dir(job)
    {
        let _ = std::fs::remove_dir_all(dir);
    }
    outcome
}

fn render(host: &dyn JobHost, job: &Job, spec: &VideoSpec, cancel: &AtomicBool) -> Result<Outcome, JobError> {
    let model_id = job.model_id.clone().unwrap_or_default();
    let info = host.model(&model_id)?.ok_or_else(|| JobError::ModelGone(model_id.clone()))?;
    let ckpt = host.model_checkpoint(&info).map_err(JobError::ModelFile)?;
    let mut model = load_model(&ckpt.path)?;
    // A splats model with a crop: its object alone, on the plain background.
    if let Some(b) = &info.crop
        && let Some(cropped) = crop_model(&*model, b)?
    {
        model = Box::new(cropped);
    }
    let orbit = info.view.orbit(spec.elevation, spec.radius);
    let started = Instant::now();
    let mut frames = Vec::with_capacity(spec.frames as usize);
    let saved = host.video_frames_dir(job);
    if let Some(dir) = &saved {
        std::fs::create_dir_all(dir).map_err(JobError::FramesFolder)?;
    }
    for k in 0..spec.frames {
        if cancel.load(Ordering::Relaxed) {
            return Ok(Outcome::Stopped);
        }
        let file = saved.as_ref().map(|d| d.join(format!("frame_{k:05}.png")));
        let img = match file.as_deref().and_then(|f| saved_frame(f, spec.width, spec.height)) {
            Some(img) => img,
            None => {
                let camera = match &spec.path {
                    Some(path) => {
                        let (c2w, fov) = path.at(path.frame_time(k, spec.frames));
                        Camera::from_fov(spec.width, spec.height, fov.to_radians(), c2w)
                    }
                    None => orbit
                        .camera(360.0 * k as f32 / spec.frames as f32, spec.width, spec.height, spec.fov)
                        .ok_or(JobError::NoOrbitCamera)?,
                };
                let options = spec.appearance.resolve(&*model, &camera)?;
                let view = render_view_with(&*model, &camera, [1.0; 3], &options);
                let img = png::rgb_image(&view).map_err(JobError::Frame)?;
                if let Some(f) = &file {
                    save_frame(f, &img)?;
                }
                img
            }
        };
        frames.push(img);
        let done = k as u64 + 1;
        let elapsed = started.elapsed().as_secs_f64();
        host.set_progress(&job.id, &mut |j| {
            j.progress.step = done;
            j.progress.total_steps = Some(spec.frames as u64);
            j.progress.elapsed = elapsed;
            j.progress.eta = Some(elapsed / done as f64 * (spec.frames as u64 - done) as f64);
        });
    }
    let bytes = video::encode(spec.format, &frames, spec.fps)?;
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
    host.publish_video(job, &record, &bytes)?;
    let elapsed = started.elapsed().as_secs_f64();
    host.set_progress(&job.id, &mut |j| {
        j.video_id = Some(id.clone());
        j.progress.elapsed = elapsed;
        j.progress.eta = Some(0.0);
    });
    Ok(Outcome::Succeeded)
}
