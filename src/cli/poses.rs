//! `radiance poses`: camera poses for plain photos (or a video) with COLMAP,
//! written as a COLMAP-format dataset that `train` reads as is.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::Common;
use crate::poses::{self, Matcher, PoseOptions, Tools, colmap, video};

#[derive(Args, Debug)]
pub struct PosesArgs {
    /// A folder of photos (JPEG or PNG, searched with its subfolders), or a
    /// video file (MP4, MOV, M4V, MKV).
    #[arg(long, visible_alias = "video")]
    pub images: PathBuf,
    /// The dataset folder to write (must not exist, or be empty).
    #[arg(long)]
    pub out: PathBuf,
    /// Longest side of the photos given to COLMAP and kept for training, in pixels.
    #[arg(long, default_value_t = poses::DEFAULT_MAX_SIZE)]
    pub max_size: u32,
    /// Frames taken from a video (the sharpest of every few).
    #[arg(long, default_value_t = video::DEFAULT_FRAMES)]
    pub frames: usize,
    /// How photos are paired for matching (default: exhaustive up to 100
    /// photos, sequential beyond and for videos).
    #[arg(long, value_enum)]
    pub matcher: Option<Matcher>,
    /// Stop and fail after this many minutes.
    #[arg(long, default_value_t = poses::DEFAULT_TIME_LIMIT.as_secs_f64() / 60.0)]
    pub time_limit_min: f64,
    /// The COLMAP binary (default: $RADIANCE_COLMAP, else `colmap` on PATH).
    #[arg(long)]
    pub colmap: Option<PathBuf>,
    #[command(flatten)]
    pub common: Common,
}

pub fn run(a: PosesArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    anyhow::ensure!(a.max_size >= 64, "--max-size must be at least 64 pixels");
    anyhow::ensure!(
        a.time_limit_min.is_finite() && a.time_limit_min > 0.0,
        "--time-limit-min must be a positive number"
    );
    let colmap = colmap::find(a.colmap.as_deref()).map_err(anyhow::Error::msg)?;
    // ffmpeg matters only for a video; its absence is said when one comes.
    let ffmpeg = video::find(None).ok();
    eprintln!("pose estimation of {} with {} ({threads} threads)", a.images.display(), colmap.version);
    let tools = Tools { colmap, ffmpeg };
    let opts = PoseOptions {
        max_size: a.max_size,
        threads,
        time_limit: Duration::from_secs_f64(a.time_limit_min * 60.0),
        matcher: a.matcher,
        frames: a.frames,
        resume_in: None,
    };
    let cancel = Arc::new(AtomicBool::new(false));
    {
        let c = cancel.clone();
        ctrlc::set_handler(move || c.store(true, Ordering::SeqCst)).context("installing the Ctrl-C handler")?;
    }
    let bar = ProgressBar::new(1000);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {percent:>3}% {msg}")
            .expect("a valid template")
            .progress_chars("=> "),
    );
    let result = poses::estimate(
        &a.images,
        &a.out,
        &tools,
        &opts,
        &mut |p| {
            bar.set_position((p.fraction * 1000.0) as u64);
            bar.set_message(format!("{} {:.0}%", p.stage.name(), 100.0 * p.stage_fraction));
        },
        &cancel,
    );
    bar.finish_and_clear();
    let r = result?;
    for w in &r.warnings {
        eprintln!("warning: {w}");
    }
    let error = r.mean_reprojection_error_px.map_or("unknown".to_string(), |e| format!("{e:.2} px"));
    println!(
        "posed {} of {} {} ({}x{}) in {:.1} s: features {:.1} s, {} matching {:.1} s, mapping {:.1} s; \
         {} sparse points, mean reprojection error {error}",
        r.registered,
        r.images,
        if r.source == "video" { "frames" } else { "photos" },
        r.width,
        r.height,
        r.seconds.total,
        r.seconds.features,
        r.matcher.name(),
        r.seconds.matching,
        r.seconds.mapping,
        r.points,
    );
    println!(
        "wrote {}: train on it with `radiance train --data {} --out model.ckpt`",
        a.out.display(),
        a.out.display()
    );
    Ok(())
}
