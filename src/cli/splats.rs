//! `radiance bake` (a trained model becomes Gaussian splats) and
//! `radiance export` (splats in the files other tools read).

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::Common;
use crate::engine::dataset::{Dataset, LoadOptions, Split};
use crate::engine::io::fsio::write_atomic;
use crate::engine::models::splats::export::{self, Format};
use crate::engine::models::training::{Budget, TrainConfig};
use crate::engine::train::bake::{BakeSettings, bake};
use crate::engine::train::persist;
use crate::engine::train::trainer::TrainState;

#[derive(Args, Debug)]
pub struct BakeArgs {
    /// A trained instant, nerf or capture model's checkpoint.
    #[arg(long)]
    pub model: PathBuf,
    /// The dataset the model was trained on (its training photos are what
    /// the splats are optimised against).
    #[arg(long)]
    pub data: PathBuf,
    /// The splats' checkpoint to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Time budget in seconds (placing and optimising).
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Stop after this many optimisation steps (one photo each) instead,
    /// if reached first.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Gaussians placed from the field before optimising.
    #[arg(long, default_value_t = BakeSettings::default().initial)]
    pub initial: usize,
    /// Spherical-harmonic degree of the colours (0-3).
    #[arg(long, default_value_t = 3)]
    pub sh_degree: u32,
    /// The most Gaussians.
    #[arg(long, default_value_t = 500_000)]
    pub max_gaussians: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[command(flatten)]
    pub common: Common,
}

pub fn bake_cmd(a: BakeArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    anyhow::ensure!(a.seconds.is_finite() && a.seconds > 0.0, "--seconds must be a positive number");
    let source = persist::load(&a.model)?;
    let opts = LoadOptions { splits: vec![Split::Train], ..Default::default() };
    let ds = Dataset::load(&a.data, &opts).with_context(|| format!("loading {}", a.data.display()))?;
    let mut settings = BakeSettings {
        seconds: Some(a.seconds),
        steps: a.steps,
        initial: a.initial,
        seed: a.seed,
        ..Default::default()
    };
    settings.splats.sh_degree = a.sh_degree;
    settings.splats.max_gaussians = a.max_gaussians;
    crate::engine::models::config::ModelConfig::Splats(settings.splats.clone())
        .check()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    eprintln!(
        "baking {} ({}) into splats on {threads} threads, {} s",
        a.model.display(),
        source.model.kind(),
        a.seconds
    );
    let started = Instant::now();
    let mut last = 0.0;
    let (model, adam, steps) = bake(&*source.model, &ds, &settings, &AtomicBool::new(false), |p| {
        if p.elapsed - last >= 5.0 {
            last = p.elapsed;
            eprintln!(
                "  {:5.1} s  step {:5}  {:7} Gaussians  {:.2} dB (training photos)",
                p.elapsed, p.step, p.gaussians, p.psnr
            );
        }
    })?;
    let elapsed = started.elapsed().as_secs_f64();
    let train =
        TrainConfig { seed: a.seed, budget: Budget { steps: a.steps, seconds: Some(a.seconds) }, ..Default::default() };
    let state = TrainState { step: steps, elapsed, ..Default::default() };
    persist::save(&a.out, &model, &adam, &train, &state)?;
    eprintln!("wrote {}: {} Gaussians, {steps} steps in {elapsed:.1} s", a.out.display(), model.layout().n);
    Ok(())
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// A splats checkpoint written by `radiance bake`.
    #[arg(long)]
    pub model: PathBuf,
    /// `ply` (the 3DGS paper's layout) or `splat` (antimatter15's 32 bytes a Gaussian).
    #[arg(long, value_parser = parse_format)]
    pub format: Format,
    /// The file to write.
    #[arg(long)]
    pub out: PathBuf,
}

fn parse_format(s: &str) -> Result<Format, String> {
    Format::parse(s).ok_or_else(|| format!("unknown format '{s}' (known: ply, splat)"))
}

pub fn export_cmd(a: ExportArgs) -> anyhow::Result<()> {
    let restored = persist::load(&a.model)?;
    let Some(splats) = export::splats_of(&*restored.model) else {
        anyhow::bail!(
            "{} holds a '{}' model: export takes splats (make them with `radiance bake`)",
            a.model.display(),
            restored.model.kind()
        );
    };
    let mut bytes = Vec::new();
    export::write(splats, a.format, &mut bytes)?;
    write_atomic(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
    eprintln!("wrote {} ({} Gaussians, {} bytes)", a.out.display(), splats.layout().n, bytes.len());
    Ok(())
}
