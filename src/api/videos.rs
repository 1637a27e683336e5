//! Videos: `POST /v1/models/{id}/videos` enqueues a video job (an orbit, or
//! a camera `path`: see `camera_path`; 202,
//! polled like a training job); `GET /v1/videos/{id}` serves the result,
//! `DELETE /v1/videos/{id}` removes it.

use axum::Json;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::http::header::CONTENT_TYPE;
use axum::response::IntoResponse;
use serde::Deserialize;

use super::{ApiError, ApiResult, AppState, camera_path, limits, models};
use crate::backend::Artifact;
use crate::backend::NewJob;
use crate::engine::front::{CameraPath, ModelConfig, estimate_video};
use crate::jobs::{Job, JobSpec, VideoSpec};
use crate::media::video::VideoFormat;
use crate::records::ViewDefaults;

/// `POST /v1/models/{id}/videos` body; every field is optional.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateVideo {
    /// Frames in one turn (60).
    pub frames: Option<u32>,
    /// Frames per second (30).
    pub fps: Option<u32>,
    /// Frame size (the training cameras').
    pub width: Option<u32>,
    pub height: Option<u32>,
    /// Degrees above the horizon (the training cameras' mean elevation).
    pub elevation: Option<f32>,
    /// Distance from the scene centre (the training cameras' median).
    pub radius: Option<f32>,
    /// Horizontal field of view in degrees (the training cameras').
    pub fov: Option<f32>,
    /// `mp4` (default when built with the `mp4` feature) or `gif`.
    pub format: Option<String>,
    /// Keyframes to fly through instead of an orbit (see `camera_path`).
    pub path: Option<serde_json::Value>,
    /// `mean` (default) or a training image's index: the frames'
    /// appearance (checked against the model in [`create`]).
    pub appearance: Option<String>,
}

/// Most frames in one video.
pub const MAX_FRAMES: u32 = 600;

/// The format asked for (MP4 by default where this build has it), refused
/// when unknown or not in this build.
fn video_format(asked: Option<&str>) -> ApiResult<VideoFormat> {
    let format = match asked {
        None if cfg!(feature = "mp4") => VideoFormat::Mp4,
        None => VideoFormat::Gif,
        Some(f) => f.parse::<VideoFormat>().map_err(|_| {
            ApiError::bad_field(format!("unknown video format '{f}' (expected mp4 or gif)"), "format", f, "mp4, gif")
        })?,
    };
    if !format.is_available() {
        let message = format!("{format} videos are not available in this build (cargo feature `mp4`); ask for gif");
        return Err(ApiError::bad_field(message, "format", format.to_string(), "gif"));
    }
    Ok(format)
}

/// Checks a request against the model's view defaults and the render cap.
pub fn to_spec(mut r: CreateVideo, view: &ViewDefaults, max_render_pixels: u64) -> ApiResult<VideoSpec> {
    let path = r.path.as_ref().map(|p| camera_path::parse(p, view.fov)).transpose()?;
    let appearance = models::parse_appearance(r.appearance.as_deref())?;
    if let Some(p) = &path {
        if let Some((field, value)) =
            [("elevation", r.elevation), ("radius", r.radius)].into_iter().find_map(|(f, v)| v.map(|v| (f, v)))
        {
            let message = format!("{field} describes an orbit: leave it out of a video along a path");
            return Err(ApiError::bad_field(message, field, value, "not with path"));
        }
        (r.frames, r.fps) = (r.frames.or(p.frames), r.fps.or(p.fps));
        (r.width, r.height) = (r.width.or(p.width), r.height.or(p.height));
    }
    let frames = r.frames.unwrap_or(60);
    if !(1..=MAX_FRAMES).contains(&frames) {
        let allowed = format!("1..={MAX_FRAMES}");
        return Err(ApiError::bad_field(format!("frames must be in {allowed}"), "frames", frames, &allowed));
    }
    let fps = r.fps.unwrap_or(30);
    if !(1..=60).contains(&fps) {
        return Err(ApiError::bad_field("fps must be in 1..=60", "fps", fps, "1..=60"));
    }
    let format = video_format(r.format.as_deref())?;
    let (width, height) = frame_size(&r, view, format)?;
    let max_side = 4096;
    if !(16..=max_side).contains(&width)
        || !(16..=max_side).contains(&height)
        || width as u64 * height as u64 > max_render_pixels
    {
        let allowed = format!("sides 16..={max_side}, at most {max_render_pixels} pixels");
        let message = format!("video frame size {width}x{height} is out of range ({allowed})");
        return Err(ApiError::bad_field(message, "width,height", [width, height], &allowed));
    }
    let elevation = r.elevation.unwrap_or(view.elevation.clamp(-89.0, 89.0));
    if !(elevation.is_finite() && (-89.0..=89.0).contains(&elevation)) {
        let message = "elevation must be in [-89, 89] degrees";
        return Err(ApiError::bad_field(message, "elevation", elevation, "[-89, 89]"));
    }
    let radius = r.radius.unwrap_or(view.radius);
    if !(radius.is_finite() && radius > 0.0) {
        return Err(ApiError::bad_field("radius must be a positive number", "radius", radius, "> 0"));
    }
    let fov = r.fov.unwrap_or(view.fov);
    if !(fov.is_finite() && fov > 1.0 && fov < 179.0) {
        return Err(ApiError::bad_field("fov must be between 1 and 179 degrees", "fov", fov, "(1, 179)"));
    }
    crate::media::video::validate(format, width, height, fps)?;
    // A capture seen from where no photo was taken is no view: with no
    // orbit asked for, a forward-facing capture's video follows a spiral
    // through the cameras' spread, and a one-sided capture's sweeps across
    // the cameras' arc and back.
    let default_path = |poses: Option<Vec<[[f32; 4]; 3]>>, what: &str| {
        let poses =
            poses.ok_or_else(|| ApiError::bad_request(format!("the default {what} has a degenerate camera")))?;
        let keys = poses.into_iter().map(|c2w| (c2w, fov)).collect();
        CameraPath::evenly_timed(keys).map_err(|e| ApiError::bad_request(format!("the default {what}: {e}")))
    };
    let orbit_asked = r.elevation.is_some() || r.radius.is_some();
    let path = match (path, &view.spiral, view.arc) {
        (Some(p), _, _) => Some(p.path),
        (None, Some(spiral), _) if !orbit_asked => {
            let mut poses = spiral.poses(view.centre, frames as usize);
            poses.truncate(frames as usize);
            Some(default_path(Some(poses), "spiral")?)
        }
        (None, None, Some(arc)) if !orbit_asked => {
            Some(default_path(view.orbit(elevation, radius).sweep(arc, frames as usize), "sweep")?)
        }
        (None, _, _) => None,
    };
    Ok(VideoSpec { frames, fps, width, height, elevation, radius, fov, format, path, appearance })
}

/// The frame size: the requested sides, the others from the training
/// cameras. H.264 4:2:0 (MP4) needs even sides, and the encoder would pad an
/// odd one, making the video a pixel larger than its record says: so for MP4
/// an odd side that was asked for is refused, naming the even sizes around
/// it, and an odd side taken from the cameras is rounded down to even.
fn frame_size(r: &CreateVideo, view: &ViewDefaults, format: VideoFormat) -> ApiResult<(u32, u32)> {
    let (width, height) = view.frame_size(r.width, r.height);
    if format != VideoFormat::Mp4 {
        return Ok((width, height));
    }
    let odd = |asked: Option<u32>| asked.is_some_and(|v| v % 2 == 1);
    if odd(r.width) || odd(r.height) {
        let (w, h) = (r.width.unwrap_or(width), r.height.unwrap_or(height));
        let even = |v: u32, up: bool| if up { v.next_multiple_of(2) } else { v & !1 };
        let (below, above) = ((even(w, false), even(h, false)), (even(w, true), even(h, true)));
        let message = format!(
            "MP4 frames need even sides (H.264 4:2:0) but {w}x{h} was asked for: ask for {}x{} or {}x{}, \
             or for format gif",
            below.0, below.1, above.0, above.1
        );
        return Err(ApiError::bad_field(message, "width,height", [w, h], "even sides for mp4"));
    }
    Ok((width & !1, height & !1))
}

pub async fn create(
    State(s): State<AppState>,
    Path(id): Path<String>,
    body: Result<Json<CreateVideo>, JsonRejection>,
) -> ApiResult<(StatusCode, Json<Job>)> {
    let Json(req) = body?;
    let info = s.jobs.get_model(&id).await?.ok_or_else(|| ApiError::not_found("model", &id))?;
    let free_disk = s.artifacts.free_space().await?;
    if req.appearance.is_some() {
        // An image index must be one the model trained on: refused now
        // rather than by the job.
        let appearance = models::parse_appearance(req.appearance.as_deref())?;
        appearance.check(&*models::model_of(&s, &info).await?)?;
    }
    let s2 = s.clone();
    let (spec, memory) = tokio::task::spawn_blocking(move || -> ApiResult<(VideoSpec, u64)> {
        let spec = to_spec(req, &info.view, s2.config.max_render_pixels)?;
        let config = ModelConfig::preset(&info.model)
            .and_then(|preset| ModelConfig::from_kind_json(preset.kind(), info.config.clone()))
            .ok_or_else(|| ApiError::internal(format!("model '{}' has an unreadable configuration", info.id)))?;
        let e = estimate_video(&config, spec.frames, spec.width, spec.height, rayon::current_num_threads());
        limits::check(&e, &s2.config, free_disk)?;
        Ok((spec, e.memory_bytes))
    })
    .await??;
    let new = NewJob { id: None, spec: JobSpec::Video(spec), model_id: Some(id), memory_estimate: memory };
    let job = s.jobs.enqueue(new).await?;
    tracing::info!(job = %job.id, kind = "video", "job queued");
    Ok((StatusCode::ACCEPTED, Json(job)))
}

pub async fn get_one(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<impl IntoResponse> {
    let info = s.jobs.get_video(&id).await?.ok_or_else(|| ApiError::not_found("video", &id))?;
    let bytes = s.artifacts.video(&info).await?;
    Ok(([(CONTENT_TYPE, info.format.content_type())], bytes))
}

/// Deletes a video (record, then file): 204, 404, or 409 while its job
/// has not ended.
pub async fn delete(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult<StatusCode> {
    s.jobs.delete_video(&id).await?;
    super::remove_artifact(&s, Artifact::Video(&id)).await;
    Ok(StatusCode::NO_CONTENT)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view() -> ViewDefaults {
        ViewDefaults { width: 200, height: 100, radius: 4.0, far: 6.0, ..crate::records::sample_view() }
    }

    #[test]
    fn defaults_come_from_the_view() {
        let s = to_spec(CreateVideo::default(), &view(), 1 << 20).unwrap();
        assert_eq!((s.frames, s.fps, s.width, s.height, s.radius, s.fov), (60, 30, 200, 100, 4.0, 40.0));
        let s = to_spec(CreateVideo { width: Some(100), ..Default::default() }, &view(), 1 << 20).unwrap();
        assert_eq!((s.width, s.height), (100, 50));
        let s = to_spec(CreateVideo { format: Some("gif".into()), ..Default::default() }, &view(), 1 << 20).unwrap();
        assert_eq!(s.format, VideoFormat::Gif);
        // The elevation is the training cameras'.
        let s = to_spec(CreateVideo::default(), &ViewDefaults { elevation: 12.5, ..view() }, 1 << 20).unwrap();
        assert_eq!((s.elevation, s.path.is_none()), (12.5, true));
    }

    #[test]
    fn forward_facing_scenes_get_a_spiral_unless_an_orbit_is_asked_for() {
        use crate::engine::front::Spiral;
        let spiral = Spiral { centre: [0.0; 3], right: [1.0, 0.0, 0.0], up: [0.0, 1.0, 0.0], half_widths: [0.3, 0.2] };
        let ff = ViewDefaults { centre: [0.0, 0.0, -5.0], spiral: Some(spiral), ..view() };
        let s = to_spec(CreateVideo { frames: Some(24), ..Default::default() }, &ff, 1 << 20).unwrap();
        let path = s.path.expect("a spiral");
        // One keyframe per frame, one turn without repeating the first.
        assert_eq!(path.keyframes().len(), 24);
        for k in 0..24 {
            let (c2w, fov) = path.at(path.frame_time(k, 24));
            let eye = [c2w[0][3], c2w[1][3], c2w[2][3]];
            let th = std::f32::consts::TAU * k as f32 / 24.0;
            let want = [0.3 * th.cos(), 0.2 * th.sin(), 0.0];
            assert!(eye.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-5), "frame {k}: {eye:?} vs {want:?}");
            assert_eq!(fov, 40.0);
            // Each looks at the centre, straight ahead down -z.
            assert!(c2w[2][2] > 0.99, "{c2w:?}");
        }
        for asked in [
            CreateVideo { elevation: Some(10.0), ..Default::default() },
            CreateVideo { radius: Some(2.0), ..Default::default() },
        ] {
            assert!(to_spec(asked, &ff, 1 << 20).unwrap().path.is_none());
        }
    }

    #[test]
    fn one_sided_scenes_sweep_their_arc_unless_an_orbit_is_asked_for() {
        // Sample view: up z, front None (azimuth 0 = world x), elevation 30.
        let side = ViewDefaults { arc: Some([-20.0, 60.0]), ..view() };
        let s = to_spec(CreateVideo { frames: Some(24), ..Default::default() }, &side, 1 << 20).unwrap();
        let path = s.path.expect("a sweep");
        assert_eq!(path.keyframes().len(), 24);
        let azimuths: Vec<f32> = (0..24)
            .map(|k| {
                let (c2w, _) = path.at(path.frame_time(k, 24));
                c2w[1][3].atan2(c2w[0][3]).to_degrees()
            })
            .collect();
        // Middle first, both ends reached, never outside the arc.
        assert!((azimuths[0] - 20.0).abs() < 1e-3, "{azimuths:?}");
        assert!((azimuths[6] - 60.0).abs() < 1e-3 && (azimuths[18] + 20.0).abs() < 1e-3, "{azimuths:?}");
        assert!(azimuths.iter().all(|a| (-20.01..=60.01).contains(a)), "{azimuths:?}");
        // An explicit elevation or radius asks for the full orbit.
        let asked = CreateVideo { radius: Some(2.0), ..Default::default() };
        assert!(to_spec(asked, &side, 1 << 20).unwrap().path.is_none());
    }

    #[test]
    fn bad_requests_name_the_field() {
        let cases = [
            (CreateVideo { frames: Some(0), ..Default::default() }, "frames"),
            (CreateVideo { fps: Some(1000), ..Default::default() }, "fps"),
            (CreateVideo { width: Some(100_000), ..Default::default() }, "size"),
            (CreateVideo { elevation: Some(f32::NAN), ..Default::default() }, "elevation"),
            (CreateVideo { radius: Some(-1.0), ..Default::default() }, "radius"),
            (CreateVideo { fov: Some(0.0), ..Default::default() }, "fov"),
            (CreateVideo { format: Some("avi".into()), ..Default::default() }, "avi"),
        ];
        for (req, word) in cases {
            let e = to_spec(req, &view(), 1 << 20).unwrap_err().message;
            assert!(e.contains(word), "{e} should name {word}");
        }
        let e = to_spec(CreateVideo { width: Some(2000), height: Some(2000), ..Default::default() }, &view(), 1 << 20);
        let e = e.unwrap_err();
        assert!(e.message.contains("pixels"));
        let allowed = "sides 16..=4096, at most 1048576 pixels";
        assert_eq!(
            e.details,
            serde_json::json!({ "field": "width,height", "value": [2000, 2000], "allowed": allowed })
        );
        let e = to_spec(CreateVideo { fps: Some(1000), ..Default::default() }, &view(), 1 << 20).unwrap_err();
        assert_eq!(e.details, serde_json::json!({ "field": "fps", "value": 1000, "allowed": "1..=60" }));
    }

    fn mp4(width: Option<u32>, height: Option<u32>) -> CreateVideo {
        CreateVideo { width, height, format: Some("mp4".into()), ..Default::default() }
    }

    #[test]
    #[cfg(feature = "mp4")]
    fn mp4_refuses_odd_sides_asked_for() {
        let e = to_spec(mp4(Some(33), Some(17)), &view(), 1 << 20).unwrap_err().message;
        assert!(e.contains("33x17") && e.contains("32x16") && e.contains("34x18") && e.contains("gif"), "{e}");
        let e = to_spec(mp4(Some(32), Some(17)), &view(), 1 << 20).unwrap_err().message;
        assert!(e.contains("32x17") && e.contains("32x16 or 32x18"), "{e}");
        // The same sizes are fine as GIF, and even ones as MP4.
        let gif = CreateVideo { format: Some("gif".into()), ..mp4(Some(33), Some(17)) };
        let s = to_spec(gif, &view(), 1 << 20).unwrap();
        assert_eq!((s.width, s.height), (33, 17));
        let s = to_spec(mp4(Some(34), Some(18)), &view(), 1 << 20).unwrap();
        assert_eq!((s.width, s.height), (34, 18));
    }

    #[test]
    #[cfg(feature = "mp4")]
    fn mp4_rounds_odd_default_sides_down_to_even() {
        let odd = ViewDefaults { width: 33, height: 17, ..view() };
        let s = to_spec(mp4(None, None), &odd, 1 << 20).unwrap();
        assert_eq!((s.width, s.height, s.format), (32, 16, VideoFormat::Mp4));
        // A height taken from the aspect ratio of an asked-for width: 42 * 17 / 33 = 21.6 -> 21, odd -> 20.
        let s = to_spec(mp4(Some(42), None), &odd, 1 << 20).unwrap();
        assert_eq!((s.width, s.height), (42, 20));
        // GIF keeps the cameras' size.
        let s = to_spec(CreateVideo { format: Some("gif".into()), ..Default::default() }, &odd, 1 << 20).unwrap();
        assert_eq!((s.width, s.height), (33, 17));
    }
}
