//! `radiance video --model M --out orbit.mp4`: a video around a trained
//! model with no other parameters. The checkpoint's scene holds the training
//! cameras' rig (`engine::geometry::rig`): the orbit turns around the point
//! they looked at, at their distance and elevation; a forward-facing capture
//! gets a spiral through the cameras' own spread instead of a full turn, and
//! a capture whose cameras saw one side (`CameraRig::arc_deg`) a sweep
//! across their arc and back.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::Common;
use crate::engine::front::{Appearance, Camera, load_checkpoint, render_view_with, write_atomic};
use crate::media::png;
use crate::media::video::{self, VideoFormat};

#[derive(Args, Debug)]
pub struct VideoArgs {
    /// Model checkpoint written by `radiance train`.
    #[arg(long)]
    pub model: PathBuf,
    /// Video file to write: `.mp4` or `.gif`.
    #[arg(long)]
    pub out: PathBuf,
    /// Frames in one turn.
    #[arg(long, default_value_t = 120)]
    pub frames: u32,
    #[arg(long, default_value_t = 30)]
    pub fps: u32,
    /// Frame width (default: the training cameras'; the height keeps their aspect ratio).
    #[arg(long)]
    pub width: Option<u32>,
    #[arg(long)]
    pub height: Option<u32>,
    /// Degrees above the horizon (default: the training cameras' mean). Given
    /// (or --radius), a forward-facing or one-sided capture is orbited all
    /// around too.
    #[arg(long)]
    pub elevation: Option<f32>,
    /// Distance from the point the cameras look at (default: theirs, median).
    #[arg(long)]
    pub radius: Option<f32>,
    /// Horizontal field of view in degrees (default: the training cameras').
    #[arg(long)]
    pub fov: Option<f32>,
    /// The appearance of the frames of a capture model, or of splats baked
    /// from one: `mean` (of the images trained on; for splats, their own
    /// look), a training image's index (its dataset frame number), or
    /// `nearest` (each frame takes the nearest training camera's). Other
    /// models ignore it.
    #[arg(long, default_value = "mean", value_name = "mean|N|nearest")]
    pub appearance: Appearance,
    #[command(flatten)]
    pub common: Common,
}

pub fn run(a: VideoArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    let format: VideoFormat = match a.out.extension().and_then(|e| e.to_str()) {
        Some(e) => e.parse().map_err(|_| anyhow::anyhow!("--out {}: write a .mp4 or a .gif", a.out.display()))?,
        None => anyhow::bail!("--out {}: write a .mp4 or a .gif", a.out.display()),
    };
    anyhow::ensure!(
        format.is_available(),
        "{format} videos are not available in this build (cargo feature `mp4`); write a .gif"
    );
    anyhow::ensure!((1..=3600).contains(&a.frames), "--frames must be in 1..=3600");
    anyhow::ensure!((1..=60).contains(&a.fps), "--fps must be in 1..=60");
    let restored = load_checkpoint(&a.model).with_context(|| format!("loading {}", a.model.display()))?;
    a.appearance.check(&*restored.model).map_err(|e| anyhow::anyhow!("--appearance {}: {e}", a.appearance))?;
    let rig = restored.model.scene().rig.clone().with_context(|| {
        format!(
            "{} has no camera rig (it was trained before checkpoints stored one): train it again",
            a.model.display()
        )
    })?;
    let [w0, h0] = if rig.image[0] > 0 { rig.image } else { [480, 360] };
    let width = a.width.unwrap_or(w0);
    let height = a.height.unwrap_or_else(|| ((width as u64 * h0 as u64) / w0.max(1) as u64).max(1) as u32);
    anyhow::ensure!(
        (16..=4096).contains(&width) && (16..=4096).contains(&height),
        "frame size {width}x{height}: sides must be in 16..=4096"
    );
    video::validate(format, width, height, a.fps).map_err(|e| anyhow::anyhow!("{e}"))?;
    let fov = a.fov.unwrap_or(if rig.fov_deg > 0.0 { rig.fov_deg } else { 50.0 });
    anyhow::ensure!(fov > 1.0 && fov < 179.0, "--fov must be between 1 and 179 degrees");
    let elevation = a.elevation.unwrap_or(rig.elevation_deg.clamp(-89.0, 89.0));
    anyhow::ensure!((-89.0..=89.0).contains(&elevation), "--elevation must be in [-89, 89] degrees");
    let radius = a.radius.unwrap_or(rig.radius);
    anyhow::ensure!(radius.is_finite() && radius > 0.0, "--radius must be a positive number");

    let n = a.frames as usize;
    let orbit_asked = a.elevation.is_some() || a.radius.is_some();
    let poses: Vec<[[f32; 4]; 3]> = match rig.arc_deg {
        _ if rig.forward_facing && !orbit_asked => {
            eprintln!(
                "a forward-facing capture: a spiral through the cameras' spread, looking at the point they look at"
            );
            rig.spiral.poses(rig.focus, n).into_iter().take(n).collect()
        }
        Some(arc) if !orbit_asked => {
            eprintln!(
                "the cameras saw one side ({:.0} degrees of azimuth around the point they look at): a sweep across \
                 it and back, radius {radius:.3}, elevation {elevation:.1} degrees (--elevation or --radius: a full orbit)",
                arc[1] - arc[0]
            );
            rig.orbit(elevation, radius).sweep(arc, n).context("this sweep gives no well-defined camera")?
        }
        _ => {
            eprintln!(
                "an orbit around the point the cameras look at: radius {radius:.3}, elevation {elevation:.1} degrees, azimuth 0 on the cameras' side"
            );
            let orbit = rig.orbit(elevation, radius);
            (0..n)
                .map(|k| orbit.pose(360.0 * k as f32 / n as f32).context("this orbit gives no well-defined camera"))
                .collect::<anyhow::Result<_>>()?
        }
    };
    let started = Instant::now();
    let mut frames = Vec::with_capacity(n);
    for (k, c2w) in poses.into_iter().enumerate() {
        let camera = Camera::from_fov(width, height, fov.to_radians(), c2w);
        let options = a.appearance.resolve(&*restored.model, &camera)?;
        frames.push(png::rgb_image(&render_view_with(&*restored.model, &camera, [1.0; 3], &options))?);
        eprint!("\rframe {}/{n}", k + 1);
    }
    eprintln!();
    let bytes = video::encode(format, &frames, a.fps)?;
    write_atomic(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
    eprintln!("{n} frames of {width}x{height} in {:.1} s on {threads} threads", started.elapsed().as_secs_f64());
    println!("{}", a.out.display());
    Ok(())
}
