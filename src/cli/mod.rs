//! The command line: `radiance demo | train | render | bake | export | mesh | eval | bench | poses | video | serve`.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

mod bench;
mod demo;
mod eval;
mod mesh;
mod poses;
mod serve;
mod setup;
mod splats;
mod train;
mod video;

pub use bench::{BenchArgs, BenchReport, BenchRow};
pub use demo::DemoArgs;
pub use eval::{EvalArgs, RenderArgs};
pub use mesh::MeshArgs;
pub use poses::PosesArgs;
pub use serve::ServeArgs;
pub use splats::{BakeArgs, ExportArgs};
pub use train::{SPLATS_FIELD_MIN_STEPS, TrainArgs};
pub use video::VideoArgs;

/// Train Neural Radiance Fields on CPUs and render novel views.
#[derive(Parser, Debug)]
#[command(name = "radiance", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// No data needed: generate a demo scene, train it briefly, write an orbit video.
    Demo(DemoArgs),
    /// Train a model on a dataset's training views.
    Train(TrainArgs),
    /// Render every view of a split to PNG files named by the frames' file stems.
    Render(RenderArgs),
    /// Turn a trained model into 3D Gaussian splats (rendered in real time, exported to splat viewers).
    Bake(BakeArgs),
    /// Write a splats model as a .ply (3DGS layout) or .splat file.
    Export(ExportArgs),
    /// Write a trained model as a textured mesh (.glb or .usdz) for web shops, phones and AR.
    Mesh(MeshArgs),
    /// Render a split and print PSNR and SSIM against its ground truth.
    Eval(EvalArgs),
    /// Train each model once and score its test views at several training-time budgets.
    Bench(BenchArgs),
    /// Estimate camera poses for plain photos (or a video) with COLMAP; writes a dataset `train` reads.
    Poses(PosesArgs),
    /// Write an orbit video of a trained model (a spiral for forward-facing captures); no other parameters needed.
    Video(VideoArgs),
    /// Run the REST service: upload scenes, train as jobs, render views.
    Serve(ServeArgs),
}

/// Options every command takes.
#[derive(Args, Debug, Clone)]
pub struct Common {
    /// Worker threads (default: all cores, or RAYON_NUM_THREADS when set).
    #[arg(long, global = true)]
    pub threads: Option<usize>,
}

impl Common {
    /// Sizes the global rayon pool.
    pub fn init_threads(&self) -> anyhow::Result<usize> {
        let mut b = rayon::ThreadPoolBuilder::new();
        if let Some(n) = self.threads {
            anyhow::ensure!(n > 0, "--threads must be at least 1");
            b = b.num_threads(n);
        }
        // Fails only if the pool was already built (e.g. twice in tests).
        let _ = b.build_global();
        Ok(rayon::current_num_threads())
    }
}

/// Dataset location and the split to use.
#[derive(Args, Debug, Clone)]
pub struct DataArgs {
    /// Dataset folder (Blender transforms_*.json, transforms.json, LLFF poses_bounds.npy, or a COLMAP sparse/0 model).
    #[arg(long)]
    pub data: PathBuf,
    /// Which split to use.
    #[arg(long, default_value = "test")]
    pub split: crate::engine::front::Split,
    /// Use only the first N frames of the split.
    #[arg(long)]
    pub limit: Option<usize>,
    #[command(flatten)]
    pub masks: MaskArgs,
}

/// What per-image masks do (`train`, `eval`, `bench`, `render`).
#[derive(Args, Debug, Clone)]
pub struct MaskArgs {
    /// Per-image masks (a masks/ or masks_N/ folder beside images/ or
    /// images_N/, same stems; or the alpha channel): `auto` (a mask folder
    /// scores, else off), `score` (eval and bench also score inside the
    /// masks), `ignore` (train only inside them), `composite` (the mask
    /// becomes alpha: trained on random backgrounds, scored on white), `off`.
    #[arg(long, default_value = "auto", value_name = "auto|score|ignore|composite|off")]
    pub masks: crate::engine::front::MaskUse,
}

/// Transient occluders in the training photos (`train`, `bench`).
#[derive(Args, Debug, Clone, Default)]
pub struct TransientArgs {
    /// Find transient occluders (something in a few photos only: a
    /// passer-by, a hand) from the training errors and stop training on
    /// them. The default for `capture` models; other models refuse it.
    #[arg(long, conflicts_with = "keep_transients")]
    pub drop_transients: bool,
    /// Train a `capture` model on every pixel: no transient occluders are
    /// looked for.
    #[arg(long)]
    pub keep_transients: bool,
}

impl TransientArgs {
    /// `config` (of a model of kind `kind`) as these arguments ask: a
    /// `capture` model drops transients unless `--keep-transients` says
    /// not to; another model asked to is refused.
    pub fn apply(
        &self,
        kind: &str,
        config: crate::engine::front::TrainConfig,
    ) -> anyhow::Result<crate::engine::front::TrainConfig> {
        let capture = kind == crate::engine::front::CAPTURE_KIND;
        anyhow::ensure!(
            !self.drop_transients || capture,
            "--drop-transients needs a capture model (this one is {kind})"
        );
        Ok(crate::engine::front::TrainConfig { drop_transients: capture && !self.keep_transients, ..config })
    }
}

/// The appearance of a capture model's views (`render`, `eval`, `bench`).
#[derive(Args, Debug, Clone)]
pub struct AppearanceArgs {
    /// The appearance of the views of a capture model, or of splats baked
    /// from one (each training photo's colour correction): `mean` (of the
    /// images trained on; for splats, their own look), a training image's
    /// index (its dataset frame number), or
    /// `nearest` (each view takes the nearest training camera's). Default:
    /// as held-out views are scored, the nearest training camera's (the
    /// mean for a checkpoint that kept no training cameras). Other models
    /// ignore it.
    #[arg(long, value_name = "mean|N|nearest")]
    pub appearance: Option<crate::engine::front::Appearance>,
}

impl AppearanceArgs {
    /// Checks the choice against `model` before any view is rendered.
    pub fn check(&self, model: &dyn crate::engine::front::Model) -> anyhow::Result<()> {
        match self.appearance {
            Some(a) => a.check(model).map_err(|e| anyhow::anyhow!("--appearance {a}: {e}")),
            None => Ok(()),
        }
    }

    /// The options a view of `model` from `camera` renders with.
    pub fn options(
        &self,
        model: &dyn crate::engine::front::Model,
        camera: &crate::engine::front::Camera,
    ) -> anyhow::Result<crate::engine::front::RenderOptions> {
        match self.appearance {
            Some(a) => a.resolve(model, camera).map_err(|e| anyhow::anyhow!("--appearance {a}: {e}")),
            None => Ok(crate::engine::front::held_out_options(model, camera)),
        }
    }
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Train(a) => train::run(a),
        Command::Render(a) => eval::render(a),
        Command::Bake(a) => splats::bake_cmd(a),
        Command::Export(a) => splats::export_cmd(a),
        Command::Mesh(a) => mesh::run(a),
        Command::Eval(a) => eval::eval(a),
        Command::Bench(a) => bench::run(a),
        Command::Poses(a) => poses::run(a),
        Command::Video(a) => video::run(a),
        Command::Serve(a) => serve::run(a),
    }
}
