//! Frames from a phone video: ffmpeg (a subprocess) decodes evenly spaced
//! candidates, turned upright and downscaled; of each run of
//! [`CANDIDATES_PER_FRAME`] neighbours the sharpest by the variance of the
//! Laplacian is kept.
//!
//! Why ffmpeg and not a Rust decoder: phones record H.264 or HEVC in MP4/MOV
//! with a rotation flag; no Rust crate decodes HEVC, and ffmpeg (a Debian
//! package like COLMAP) decodes every codec, applies the rotation and scales
//! in one pass.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use rayon::prelude::*;

use super::PoseError;
use super::process::{self, RunError};

/// The environment variable naming the ffmpeg binary.
pub const ENV: &str = "RADIANCE_FFMPEG";

/// Candidates decoded per frame kept.
pub const CANDIDATES_PER_FRAME: usize = 3;

/// The frames a video gives by default.
pub const DEFAULT_FRAMES: usize = 100;

/// ffmpeg and ffprobe, found together.
#[derive(Debug, Clone)]
pub struct Ffmpeg {
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
    pub version: String,
}

/// Finds ffmpeg (`explicit`, else `$RADIANCE_FFMPEG`, else `PATH`) and the
/// ffprobe beside it.
pub fn find(explicit: Option<&Path>) -> Result<Ffmpeg, String> {
    let ffmpeg = explicit
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os(ENV).filter(|v| !v.is_empty()).map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("ffmpeg"));
    let ffprobe = match ffmpeg.parent().filter(|p| !p.as_os_str().is_empty()) {
        Some(dir) => dir.join("ffprobe"),
        None => PathBuf::from("ffprobe"),
    };
    let hint = "install it (Debian/Ubuntu: `apt-get install ffmpeg`) or name it with RADIANCE_FFMPEG";
    let mut version = String::new();
    for bin in [&ffmpeg, &ffprobe] {
        let mut cmd = Command::new(bin);
        cmd.arg("-version");
        let first = process::first_lines(cmd, Duration::from_secs(20), 1)
            .map_err(|e| format!("{} does not run ({e}); {hint}", bin.display()))?;
        if version.is_empty() {
            version = first.into_iter().next().unwrap_or_default();
        }
    }
    Ok(Ffmpeg { ffmpeg, ffprobe, version })
}

/// Decodes `frames` sharp frames of `video` into `out` as `frame_00001.jpg`,
/// ... with the longer side at most `max_size` (the candidates go to
/// `scratch`, left for the caller to remove); `progress` gets the fraction
/// decoded. Returns the names written, in time order.
#[allow(clippy::too_many_arguments)]
pub fn extract(
    tools: &Ffmpeg,
    video: &Path,
    out: &Path,
    scratch: &Path,
    frames: usize,
    max_size: u32,
    deadline: Instant,
    cancel: &AtomicBool,
    progress: &mut dyn FnMut(f32),
) -> Result<Vec<String>, PoseError> {
    if frames < super::photos::MIN_PHOTOS {
        return Err(PoseError::Input(format!("--frames must be at least {}", super::photos::MIN_PHOTOS)));
    }
    let (duration, packets) = probe_duration(tools, video, deadline, cancel)?;
    let shown = video.file_name().map_or_else(|| video.display().to_string(), |n| n.to_string_lossy().into_owned());
    if packets.is_some_and(|n| n < super::photos::MIN_PHOTOS as u64) {
        let n = packets.unwrap_or(0);
        return Err(too_few(&shown, n, n));
    }
    let candidates_dir = scratch.to_path_buf();
    std::fs::create_dir_all(&candidates_dir).map_err(|e| PoseError::io(&candidates_dir, e))?;
    std::fs::create_dir_all(out).map_err(|e| PoseError::io(out, e))?;
    // No more candidates than the video has frames: more would repeat them.
    let wanted = (frames * CANDIDATES_PER_FRAME).min(packets.map_or(usize::MAX, |n| n as usize));
    let rate = wanted as f64 / duration;
    let scale =
        format!("fps={rate:.6},scale='if(gt(iw,ih),min({max_size},iw),-2)':'if(gt(iw,ih),-2,min({max_size},ih))'");
    let mut cmd = Command::new(&tools.ffmpeg);
    cmd.args(["-nostdin", "-hide_banner", "-loglevel", "error", "-progress", "pipe:1", "-i"]).arg(video);
    cmd.args(["-map", "0:v:0", "-vf", &scale, "-q:v", "2", "-frames:v", &wanted.to_string()]);
    cmd.arg(candidates_dir.join("c_%05d.jpg"));
    let mut on_line = |l: &str| {
        if let Some(us) = l.strip_prefix("out_time_us=").and_then(|v| v.trim().parse::<f64>().ok()) {
            progress((us / 1e6 / duration).clamp(0.0, 1.0) as f32);
        }
    };
    process::run(cmd, deadline, cancel, &mut on_line).map_err(|e| match e {
        RunError::Cancelled => PoseError::Cancelled,
        RunError::TimedOut { seconds, .. } => PoseError::TimedOut { stage: "frame extraction", seconds },
        e => PoseError::Input(format!("the video '{}' could not be decoded: {e}", video.display())),
    })?;
    let mut names: Vec<PathBuf> = std::fs::read_dir(&candidates_dir)
        .map_err(|e| PoseError::io(&candidates_dir, e))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "jpg"))
        .collect();
    names.sort();
    // A candidate the same as the one before (a still, or a frame repeated
    // to fill the rate) is no new view.
    let before = names.len();
    let mut last: Option<Vec<u8>> = None;
    names.retain(|p| {
        let bytes = std::fs::read(p).ok();
        let repeat = bytes.is_some() && bytes == last;
        last = bytes;
        !repeat
    });
    if names.len() < super::photos::MIN_PHOTOS && before >= super::photos::MIN_PHOTOS {
        return Err(too_few(&shown, before as u64, names.len() as u64));
    }
    if names.len() < super::photos::MIN_PHOTOS {
        return Err(PoseError::Input(format!(
            "the video '{}' gave only {} frame(s); it needs to be longer or have more frames",
            video.display(),
            names.len()
        )));
    }
    let sharpness: Vec<Result<f64, PoseError>> = names.par_iter().map(|p| sharpness_of(p)).collect();
    let sharpness = sharpness.into_iter().collect::<Result<Vec<_>, _>>()?;
    let keep = pick_sharpest(&sharpness, frames);
    let mut written = Vec::with_capacity(keep.len());
    for (k, &i) in keep.iter().enumerate() {
        let name = format!("frame_{:05}.jpg", k + 1);
        std::fs::rename(&names[i], out.join(&name)).map_err(|e| PoseError::io(&names[i], e))?;
        written.push(name);
    }
    Ok(written)
}

/// What [`probe`] found out about a video.
#[derive(Debug, Clone, PartialEq)]
pub struct Probe {
    pub width: u32,
    pub height: u32,
    pub duration: f64,
    /// Frames in the file (packets of its video stream).
    pub frames: u64,
    /// Frames that differ from the one before (ffmpeg's `mpdecimate`);
    /// `None` when decoding them all did not finish in time.
    pub distinct: Option<u64>,
}

/// The longest a [`probe`] decodes the whole video to count its distinct
/// frames.
pub const PROBE_DECODE_LIMIT: Duration = Duration::from_secs(60);

/// Reads `video` as a pose estimation would take it, without writing a
/// frame: ffprobe counts its frames (all of them there: a file cut short
/// lists frames its index holds and its data does not), then ffmpeg decodes
/// it small, through `mpdecimate`, to count the frames that differ (a
/// still or a one-frame clip gives no two views). Errors name the problem
/// and the file as `shown`; `deadline` bounds both runs.
pub fn probe(tools: &Ffmpeg, video: &Path, shown: &str, deadline: Instant) -> Result<Probe, PoseError> {
    let cancel = AtomicBool::new(false);
    let bad = |m: String| PoseError::Input(format!("'{shown}' {m}"));
    let mut cmd = Command::new(&tools.ffprobe);
    cmd.args(["-v", "error", "-select_streams", "v:0", "-count_packets", "-show_entries"]);
    cmd.args(["stream=width,height,nb_frames,nb_read_packets:format=duration", "-of", "default=noprint_wrappers=1"]);
    cmd.arg(video);
    let mut fields = std::collections::BTreeMap::new();
    let mut errors = Vec::new();
    let ran = process::run(cmd, deadline, &cancel, &mut |l| match l.split_once('=') {
        Some((k, v)) if !k.contains(' ') => {
            fields.insert(k.to_string(), v.trim().to_string());
        }
        _ if !l.trim().is_empty() && errors.len() < 3 => {
            errors.push(l.trim().replace(&*video.to_string_lossy(), shown))
        }
        _ => {}
    });
    let why = || if errors.is_empty() { String::new() } else { format!(" ({})", errors.join("; ")) };
    match ran {
        Ok(()) => {}
        Err(RunError::TimedOut { .. }) => return Err(bad("could not be read in time".into())),
        Err(_) => return Err(bad(format!("is not a video ffmpeg can read{}", why()))),
    }
    let num = |k: &str| fields.get(k).and_then(|v| v.parse::<f64>().ok()).filter(|v| v.is_finite());
    let (Some(width), Some(height)) = (num("width"), num("height")) else {
        return Err(bad(format!("holds no video stream{}", why())));
    };
    let (width, height) = (width as u32, height as u32);
    let frames = num("nb_read_packets").unwrap_or(0.0) as u64;
    if let Some(listed) = num("nb_frames").map(|n| n as u64)
        && listed > frames
    {
        return Err(bad(format!("is cut short: its index lists {listed} frames, the file holds {frames}")));
    }
    check_frame_size(width, height).map_err(bad)?;
    let duration = num("duration").filter(|d| *d > 0.0).unwrap_or(0.0);
    if frames < super::photos::MIN_PHOTOS as u64 {
        return Err(too_few(shown, frames, frames));
    }
    // Every frame decoded, small, duplicates dropped: what is left counts.
    let mut cmd = Command::new(&tools.ffmpeg);
    cmd.args(["-nostdin", "-v", "error", "-progress", "pipe:1", "-i"]).arg(video);
    cmd.args(["-map", "0:v:0", "-vf", "scale=160:-2,mpdecimate", "-fps_mode", "passthrough", "-f", "null", "-"]);
    let (mut distinct, mut errors) = (0u64, Vec::new());
    let decode_deadline = deadline.min(Instant::now() + PROBE_DECODE_LIMIT);
    let ran = process::run(cmd, decode_deadline, &cancel, &mut |l| match l.split_once('=') {
        Some(("frame", n)) => distinct = n.trim().parse().unwrap_or(distinct),
        Some((k, _)) if !k.contains(' ') => {}
        _ if !l.trim().is_empty() && errors.len() < 3 => {
            errors.push(l.trim().replace(&*video.to_string_lossy(), shown))
        }
        _ => {}
    });
    let distinct = match ran {
        Err(RunError::TimedOut { .. }) => None,
        Err(e) => return Err(bad(format!("cannot be decoded: {e}"))),
        Ok(()) if !errors.is_empty() => {
            return Err(bad(format!("is damaged: ffmpeg could not decode it ({})", errors.join("; "))));
        }
        Ok(()) => Some(distinct),
    };
    if let Some(d) = distinct
        && d < super::photos::MIN_PHOTOS as u64
    {
        return Err(too_few(shown, frames, d));
    }
    Ok(Probe { width, height, duration, frames, distinct })
}

/// Refuses frames too large to decode safely or too small to pose.
fn check_frame_size(width: u32, height: u32) -> Result<(), String> {
    let pixels = width as u64 * height as u64;
    if pixels == 0 || pixels > super::photos::MAX_PIXELS {
        return Err(format!(
            "has frames of {width}x{height} pixels; a video's frames may have at most {} megapixels",
            super::photos::MAX_PIXELS / 1_000_000
        ));
    }
    if width.min(height) < super::photos::MIN_SIDE {
        return Err(format!(
            "has frames of {width}x{height} pixels; pose estimation needs frames at least {} pixels on each side",
            super::photos::MIN_SIDE
        ));
    }
    Ok(())
}

/// A video with fewer distinct frames than pose estimation needs.
fn too_few(shown: &str, frames: u64, distinct: u64) -> PoseError {
    let all = if distinct == frames { String::new() } else { format!(" ({frames} in all, the rest repeats)") };
    PoseError::Input(format!(
        "'{shown}' has {distinct} distinct frame{}{all}; pose estimation needs at least {} views of the scene \
         from different places: film a longer walk around it",
        if distinct == 1 { "" } else { "s" },
        super::photos::MIN_PHOTOS
    ))
}

/// The memory decoding a video of `width`x`height` frames takes: ffmpeg's
/// frames in flight (its threads, the reference frames and the filter
/// chain, about 40 frames of 1.5 bytes a pixel at most).
pub fn decode_memory(width: u32, height: u32) -> u64 {
    (width as u64 * height as u64 * 3 / 2).saturating_mul(40)
}

/// The video's duration in seconds and the frames (packets) of its video
/// stream, from ffprobe.
fn probe_duration(
    tools: &Ffmpeg,
    video: &Path,
    deadline: Instant,
    cancel: &AtomicBool,
) -> Result<(f64, Option<u64>), PoseError> {
    let mut cmd = Command::new(&tools.ffprobe);
    cmd.args(["-v", "error", "-select_streams", "v:0", "-count_packets"]);
    cmd.args(["-show_entries", "format=duration:stream=nb_read_packets", "-of", "default=noprint_wrappers=1"]);
    cmd.arg(video);
    let (mut value, mut packets) = (None, None);
    process::run(cmd, deadline, cancel, &mut |l| match l.trim().split_once('=') {
        Some(("duration", v)) => value = v.parse::<f64>().ok(),
        Some(("nb_read_packets", v)) => packets = v.parse::<u64>().ok(),
        _ => {}
    })
    .map_err(|e| match e {
        RunError::Cancelled => PoseError::Cancelled,
        e => PoseError::Input(format!("'{}' is not a video ffmpeg can read: {e}", video.display())),
    })?;
    match value {
        Some(d) if d.is_finite() && d > 0.0 => Ok((d, packets)),
        _ => Err(PoseError::Input(format!("'{}' has no duration: is it a video?", video.display()))),
    }
}

fn sharpness_of(path: &Path) -> Result<f64, PoseError> {
    let img = image::open(path).map_err(|e| PoseError::Io { path: path.to_path_buf(), message: e.to_string() })?;
    let gray = img.to_luma32f();
    Ok(laplacian_variance(gray.width() as usize, gray.height() as usize, gray.as_raw()))
}

/// The variance of the 4-neighbour Laplacian over the interior pixels of a
/// grey image: high for crisp edges, low for blur.
pub fn laplacian_variance(w: usize, h: usize, px: &[f32]) -> f64 {
    if w < 3 || h < 3 {
        return 0.0;
    }
    let (mut sum, mut sum2) = (0.0f64, 0.0f64);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = y * w + x;
            let l = (px[i - 1] + px[i + 1] + px[i - w] + px[i + w] - 4.0 * px[i]) as f64;
            sum += l;
            sum2 += l * l;
        }
    }
    let n = ((w - 2) * (h - 2)) as f64;
    let mean = sum / n;
    (sum2 / n - mean * mean).max(0.0)
}

/// Splits `sharpness` (one per candidate, in time order) into `frames` runs
/// of about equal length and returns the index of the sharpest of each.
pub fn pick_sharpest(sharpness: &[f64], frames: usize) -> Vec<usize> {
    let n = sharpness.len();
    let frames = frames.min(n);
    (0..frames)
        .map(|k| {
            let (a, b) = (k * n / frames, ((k + 1) * n / frames).max(k * n / frames + 1));
            (a..b).max_by(|&i, &j| sharpness[i].total_cmp(&sharpness[j]).then(j.cmp(&i))).unwrap_or(a)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laplacian_variance_is_zero_on_flat_and_linear_images_and_falls_with_blur() {
        let (w, h) = (16, 12);
        assert_eq!(laplacian_variance(w, h, &vec![0.3; w * h]), 0.0);
        let ramp: Vec<f32> = (0..w * h).map(|i| 0.01 * (i % w) as f32 + 0.02 * (i / w) as f32).collect();
        assert!(laplacian_variance(w, h, &ramp) < 1e-10);
        let checker: Vec<f32> = (0..w * h).map(|i| ((i % w / 2 + i / w / 2) % 2) as f32).collect();
        // Box-blurred 3x3 (edges clamped).
        let at = |x: isize, y: isize| {
            checker[(y.clamp(0, h as isize - 1) as usize) * w + x.clamp(0, w as isize - 1) as usize]
        };
        let blurred: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (dx, dy))).map(|(dx, dy)| at(x + dx, y + dy)).sum::<f32>()
                    / 9.0
            })
            .collect();
        let (sharp, soft) = (laplacian_variance(w, h, &checker), laplacian_variance(w, h, &blurred));
        assert!(sharp > 4.0 * soft && soft > 0.0, "{sharp} vs {soft}");
    }

    #[test]
    fn the_sharpest_of_each_run_is_kept() {
        let s = [1.0, 5.0, 2.0, 9.0, 1.0, 1.0, 0.0, 0.5, 0.1];
        assert_eq!(pick_sharpest(&s, 3), [1, 3, 7]);
        assert_eq!(pick_sharpest(&s, 9), (0..9).collect::<Vec<_>>());
        // Fewer candidates than frames asked: every candidate once.
        assert_eq!(pick_sharpest(&s[..2], 5), [0, 1]);
        // Uneven runs cover every candidate and keep time order.
        let picked = pick_sharpest(&[1.0; 10], 4);
        assert_eq!(picked.len(), 4);
        assert!(picked.windows(2).all(|p| p[0] < p[1]));
    }
}
