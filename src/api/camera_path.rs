//! The `path` of `POST /v1/models/{id}/videos`, read into the engine's
//! [`CameraPath`]. Two shapes are accepted:
//!
//! - our keyframes: `[{"c2w": [...], "fov"?: degrees, "time"?: seconds}]`,
//!   `c2w` a camera-to-world matrix as 12 or 16 numbers (row-major) or as
//!   3 or 4 rows (OpenGL convention, as `render?c2w=` takes); `fov` is
//!   horizontal (default: the model's); times all given or none (then 0,
//!   1, 2, ... seconds);
//! - nerfstudio's `camera_path.json`: an object whose `camera_path` lists
//!   frames with `camera_to_world` (16 numbers, row-major), a vertical
//!   `fov` in degrees and an `aspect`; `render_width`, `render_height`,
//!   `fps` and `seconds` become the video's defaults, and every frame of the
//!   file a keyframe, so the video shows exactly its frames.

use serde_json::Value;

use super::{ApiError, ApiResult};
use crate::engine::front::{CameraPath, Keyframe, MAX_KEYFRAMES};

/// The longest a nerfstudio path may last, seconds (a day).
const MAX_SECONDS: f64 = 86_400.0;

/// A path and the video settings it brings (nerfstudio files only).
#[derive(Debug)]
pub struct ParsedPath {
    pub path: CameraPath,
    pub frames: Option<u32>,
    pub fps: Option<u32>,
    pub width: Option<u32>,
    pub height: Option<u32>,
}

/// The largest entry of a camera matrix: far beyond any scene, and far
/// inside what a 32-bit float holds.
const MAX_COORDINATE: f64 = 1e9;

const C2W: &str = "12 or 16 numbers (row-major) or 3 or 4 rows of 4: a rigid camera-to-world transform";
const SHAPES: &str = "an array of keyframes {c2w, fov?, time?}, or a nerfstudio camera_path.json object";

/// Reads `path`; `default_fov` is the model's horizontal field of view.
pub fn parse(v: &Value, default_fov: f32) -> ApiResult<ParsedPath> {
    match v {
        Value::Array(keys) => {
            Ok(ParsedPath { path: keyframes(keys, default_fov)?, frames: None, fps: None, width: None, height: None })
        }
        Value::Object(o) if o.contains_key("camera_path") => nerfstudio(v),
        _ => Err(ApiError::bad_field(format!("path must be {SHAPES}"), "path", short(v), SHAPES)),
    }
}

/// A value to quote in an error, cut short.
fn short(v: &Value) -> String {
    let s = v.to_string();
    if s.len() > 120 { format!("{}...", &s[..s.floor_char_boundary(117)]) } else { s }
}

/// A matrix given as 12/16 numbers or 3/4 rows of 4.
fn matrix(v: &Value, field: &str) -> ApiResult<[[f32; 4]; 3]> {
    let bad = |why: &str| ApiError::bad_field(format!("{field}: {why}"), field, short(v), C2W);
    let Some(items) = v.as_array() else { return Err(bad("not an array")) };
    let numbers: Vec<f64> = if items.iter().all(Value::is_array) {
        let rows: Vec<&Vec<Value>> = items.iter().filter_map(Value::as_array).collect();
        if !(rows.len() == 3 || rows.len() == 4) || rows.iter().any(|r| r.len() != 4) {
            return Err(bad("expected 3 or 4 rows of 4 numbers"));
        }
        rows.into_iter().flatten().map(|x| x.as_f64().ok_or_else(|| bad("not a number"))).collect::<ApiResult<_>>()?
    } else {
        items.iter().map(|x| x.as_f64().ok_or_else(|| bad("not a number"))).collect::<ApiResult<_>>()?
    };
    if numbers.len() != 12 && numbers.len() != 16 {
        return Err(bad(&format!("expected 12 or 16 numbers, got {}", numbers.len())));
    }
    // Finite in JSON, yet past what a coordinate holds (1e308 would become
    // infinite): refused as what it is.
    if let Some(x) = numbers.iter().find(|x| x.abs() > MAX_COORDINATE) {
        return Err(bad(&format!("{x:e} is too large (entries are at most {MAX_COORDINATE:e} in size)")));
    }
    if numbers.len() == 16 && numbers[12..] != [0.0, 0.0, 0.0, 1.0] {
        return Err(bad("the last row of a 4x4 matrix must be 0, 0, 0, 1"));
    }
    Ok([0, 1, 2].map(|r| [0, 1, 2, 3].map(|c| numbers[r * 4 + c] as f32)))
}

fn number(o: &serde_json::Map<String, Value>, key: &str, field: &str) -> ApiResult<Option<f64>> {
    match o.get(key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => v
            .as_f64()
            .filter(|x| x.is_finite())
            .map(Some)
            .ok_or_else(|| ApiError::bad_field(format!("{field} must be a number"), field, short(v), "a number")),
    }
}

fn too_many(n: usize) -> ApiResult<()> {
    if n > MAX_KEYFRAMES {
        let allowed = format!("1..={MAX_KEYFRAMES} keyframes");
        return Err(ApiError::bad_field(format!("path has {n} keyframes ({allowed})"), "path", n, &allowed));
    }
    Ok(())
}

/// Our keyframe list.
fn keyframes(keys: &[Value], default_fov: f32) -> ApiResult<CameraPath> {
    too_many(keys.len())?;
    let mut out = Vec::with_capacity(keys.len());
    for (i, k) in keys.iter().enumerate() {
        let field = format!("path[{i}]");
        let o = k.as_object().ok_or_else(|| {
            ApiError::bad_field(format!("{field} must be an object {{c2w, fov?, time?}}"), &field, short(k), SHAPES)
        })?;
        if let Some(extra) = o.keys().find(|k| !["c2w", "fov", "time"].contains(&k.as_str())) {
            let message = format!("{field} has an unknown field '{extra}' (expected c2w, fov, time)");
            return Err(ApiError::bad_field(message, &format!("{field}.{extra}"), extra, "c2w, fov, time"));
        }
        let c2w = matrix(o.get("c2w").unwrap_or(&Value::Null), &format!("{field}.c2w"))?;
        let fov = number(o, "fov", &format!("{field}.fov"))?.map_or(default_fov, |f| f as f32);
        let time = number(o, "time", &format!("{field}.time"))?;
        out.push((c2w, fov, time));
    }
    let timed = out.iter().filter(|k| k.2.is_some()).count();
    if timed != 0 && timed != out.len() {
        let message = "give every keyframe a time, or none (then they are 1 s apart)";
        return Err(ApiError::bad_field(message, "path[].time", timed, "all keyframes or none"));
    }
    let keys = out.into_iter().enumerate().map(|(i, (c2w, fov, t))| Keyframe { c2w, fov, time: t.unwrap_or(i as f64) });
    checked(keys.collect())
}

fn checked(keys: Vec<Keyframe>) -> ApiResult<CameraPath> {
    CameraPath::new(keys).map_err(|e| ApiError::bad_field(format!("path: {e}"), "path", e.to_string(), SHAPES))
}

/// nerfstudio's `camera_path.json`.
fn nerfstudio(v: &Value) -> ApiResult<ParsedPath> {
    let o = v.as_object().expect("an object");
    let frames = o.get("camera_path").and_then(Value::as_array).ok_or_else(|| {
        ApiError::bad_field("path.camera_path must be an array of frames", "path.camera_path", "", SHAPES)
    })?;
    too_many(frames.len())?;
    let size = |key: &str| -> ApiResult<Option<u32>> {
        match number(o, key, &format!("path.{key}"))? {
            Some(x) if (1.0..=8192.0).contains(&x) && x.fract() == 0.0 => Ok(Some(x as u32)),
            Some(x) => {
                Err(ApiError::bad_field(format!("path.{key} must be 1..=8192"), &format!("path.{key}"), x, "1..=8192"))
            }
            None => Ok(None),
        }
    };
    let (width, height) = (size("render_width")?, size("render_height")?);
    let fps = number(o, "fps", "path.fps")?;
    if let Some(f) = fps
        && !(1.0..=60.0).contains(&f.round())
    {
        return Err(ApiError::bad_field("path.fps must be in 1..=60", "path.fps", f, "1..=60"));
    }
    let seconds = number(o, "seconds", "path.seconds")?;
    if let Some(s) = seconds
        && !(s > 0.0 && s <= MAX_SECONDS)
    {
        let allowed = format!("more than 0 and at most {MAX_SECONDS}");
        return Err(ApiError::bad_field(format!("path.seconds must be {allowed}"), "path.seconds", s, &allowed));
    }
    let default_aspect = match (width, height) {
        (Some(w), Some(h)) => w as f64 / h as f64,
        _ => 1.0,
    };
    let n = frames.len();
    let seconds = seconds.unwrap_or_else(|| n.saturating_sub(1).max(1) as f64 / fps.unwrap_or(30.0));
    let mut keys = Vec::with_capacity(n);
    for (i, f) in frames.iter().enumerate() {
        let field = format!("path.camera_path[{i}]");
        let fo = f.as_object().ok_or_else(|| {
            ApiError::bad_field(
                format!("{field} must be an object"),
                &field,
                short(f),
                "{camera_to_world, fov, aspect}",
            )
        })?;
        let c2w = matrix(fo.get("camera_to_world").unwrap_or(&Value::Null), &format!("{field}.camera_to_world"))?;
        let fov_y = number(fo, "fov", &format!("{field}.fov"))?.unwrap_or(50.0);
        let aspect = number(fo, "aspect", &format!("{field}.aspect"))?.unwrap_or(default_aspect);
        if !(aspect > 0.0 && fov_y > 0.0 && fov_y < 180.0) {
            let message = format!("{field}: fov {fov_y} and aspect {aspect} give no camera");
            return Err(ApiError::bad_field(message, &format!("{field}.fov"), fov_y, "(0, 180) with aspect > 0"));
        }
        // nerfstudio's fov is vertical; ours horizontal.
        let fov_x = 2.0 * ((0.5 * fov_y.to_radians()).tan() * aspect).atan();
        let time = if n > 1 { seconds * i as f64 / (n - 1) as f64 } else { 0.0 };
        keys.push(Keyframe { c2w, fov: fov_x.to_degrees() as f32, time });
    }
    Ok(ParsedPath { path: checked(keys)?, frames: Some(n as u32), fps: fps.map(|f| f.round() as u32), width, height })
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    const EYE: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0];

    #[test]
    fn keyframes_take_flat_or_nested_matrices_and_default_times() {
        let nested = [[1.0, 0.0, 0.0, 2.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]];
        let p = parse(&json!([{ "c2w": EYE }, { "c2w": nested, "fov": 30.0 }]), 45.0).unwrap();
        let k = p.path.keyframes();
        assert_eq!((k[0].time, k[1].time, k[0].fov, k[1].fov), (0.0, 1.0, 45.0, 30.0));
        assert_eq!(k[1].c2w[0][3], 2.0);
        assert!(p.frames.is_none() && p.width.is_none());
    }

    #[test]
    fn bad_paths_name_the_field() {
        let field = |v: Value| parse(&v, 45.0).unwrap_err().details["field"].as_str().unwrap().to_string();
        assert_eq!(field(json!(3)), "path");
        assert_eq!(field(json!([{ "c2w": [1, 2, 3] }])), "path[0].c2w");
        assert_eq!(field(json!([{ "c2w": EYE }, { "c2w": EYE, "fov": "wide" }])), "path[1].fov");
        assert_eq!(field(json!([{ "c2w": EYE, "zoom": 2 }])), "path[0].zoom");
        assert_eq!(field(json!([{ "c2w": EYE, "time": 1 }, { "c2w": EYE }])), "path[].time");
        let e = parse(&json!([{ "c2w": EYE, "time": 2 }, { "c2w": EYE, "time": 1 }]), 45.0).unwrap_err();
        assert!(e.message.contains("keyframe 1: time 1 is not after"), "{}", e.message);
        let e = parse(&json!([]), 45.0).unwrap_err();
        assert!(e.message.contains("at least one keyframe"), "{}", e.message);
        assert_eq!(
            field(json!({ "camera_path": [{ "camera_to_world": [1, 0] }] })),
            "path.camera_path[0].camera_to_world"
        );
    }

    #[test]
    fn out_of_range_values_are_refused_not_clamped() {
        let m: Vec<f32> = EYE.iter().copied().chain([0.0, 0.0, 0.0, 1.0]).collect();
        let file = |key: &str, v: Value| {
            let mut f = json!({ "fps": 24, "camera_path": [{ "camera_to_world": m }, { "camera_to_world": m }] });
            f[key] = v;
            parse(&f, 45.0)
        };
        for (key, v) in [("fps", json!(0)), ("fps", json!(1e9)), ("fps", json!(-5)), ("seconds", json!(-1))] {
            let e = file(key, v.clone()).unwrap_err();
            assert_eq!(e.details["field"], format!("path.{key}"), "{key}={v}: {}", e.message);
        }
        assert!(file("seconds", json!(0)).is_err() && file("seconds", json!(1e12)).is_err());
        let p = file("fps", json!(29.97)).unwrap();
        assert_eq!(p.fps, Some(30));
        // A finite number too large for a coordinate is called that, not
        // "non-finite".
        let big = json!([{ "c2w": [1.0, 0.0, 0.0, 1e308, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0] }]);
        let e = parse(&big, 45.0).unwrap_err().message;
        assert!(e.contains("1e308 is too large") && !e.contains("finite"), "{e}");
    }

    #[test]
    fn nerfstudio_camera_paths_bring_their_frames_size_and_timing() {
        let m: Vec<f32> = EYE.iter().copied().chain([0.0, 0.0, 0.0, 1.0]).collect();
        let file = json!({
            "render_width": 64, "render_height": 32, "fps": 24, "seconds": 2.0,
            "camera_path": [
                { "camera_to_world": m, "fov": 50.0, "aspect": 2.0 },
                { "camera_to_world": m, "fov": 50.0, "aspect": 2.0 },
                { "camera_to_world": m, "fov": 50.0 },
            ],
        });
        let p = parse(&file, 45.0).unwrap();
        assert_eq!((p.frames, p.fps, p.width, p.height), (Some(3), Some(24), Some(64), Some(32)));
        let k = p.path.keyframes();
        assert_eq!((k[0].time, k[1].time, k[2].time), (0.0, 1.0, 2.0));
        // Vertical 50 degrees at aspect 2: horizontal 2 atan(2 tan 25 degrees).
        let want = (2.0 * (2.0 * 25f64.to_radians().tan()).atan()).to_degrees() as f32;
        assert!((k[0].fov - want).abs() < 1e-4 && (k[2].fov - want).abs() < 1e-4, "{} vs {want}", k[0].fov);
    }
}
