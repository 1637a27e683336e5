//! `radiance demo --out DIR`: the whole flow without data. Generates the
//! demo scene (the engine's product shot, a mug on a tiled mat seen from
//! all around, as `POST /v1/demo` does), trains
//! the fast model on it for a few seconds and writes an orbit video.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::Common;
use super::setup::new_model_and_adam;
use crate::engine::front::{
    Budget, DEFAULT_BATCH_RAYS, Dataset, LoadOptions, Orbit, ProductScene, Session, SessionConfig, Start, Vec3,
    render_view, write_atomic,
};
use crate::media::png;
use crate::media::video::{self, VideoFormat};

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Folder to write into: `scene/` (the generated dataset), `model.ckpt`
    /// and `orbit.mp4` (`orbit.gif` in a build without the `mp4` feature).
    #[arg(long)]
    pub out: PathBuf,
    /// Seconds of training.
    #[arg(long, default_value_t = 15.0)]
    pub seconds: f64,
    /// Train this many steps instead (the same model whatever the machine's load).
    #[arg(long, conflicts_with = "seconds")]
    pub steps: Option<u64>,
    /// Frames of the orbit video (30 per second).
    #[arg(long, default_value_t = 60)]
    pub frames: u32,
    #[command(flatten)]
    pub common: Common,
}

pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    anyhow::ensure!(a.seconds.is_finite() && a.seconds > 0.0, "--seconds must be a positive number");
    anyhow::ensure!((1..=600).contains(&a.frames), "--frames must be in 1..=600");
    let scene_dir = a.out.join("scene");
    std::fs::create_dir_all(&scene_dir).with_context(|| format!("creating {}", scene_dir.display()))?;
    let demo = ProductScene::default();
    demo.write_blender(&scene_dir).with_context(|| format!("writing the demo scene to {}", scene_dir.display()))?;
    let ds = Dataset::load(&scene_dir, &LoadOptions::default())?;
    eprintln!(
        "demo scene: {} training views of {}x{} in {}",
        ds.train.len(),
        demo.size,
        demo.size,
        scene_dir.display()
    );
    let budget = match a.steps {
        Some(n) => {
            anyhow::ensure!(n > 0, "--steps must be at least 1");
            eprintln!("training the fast model for {n} steps on {threads} threads...");
            Budget { steps: Some(n), seconds: None }
        }
        None => {
            eprintln!("training the fast model for {} s on {threads} threads...", a.seconds);
            Budget { steps: None, seconds: Some(a.seconds) }
        }
    };
    let checkpoint = a.out.join("model.ckpt");
    let (config, model, adam) = new_model_and_adam("instant", ds.scene(), 0, true, None, &[])?;
    let train = config.train_config(0, DEFAULT_BATCH_RAYS, budget);
    let session_config = SessionConfig { train, out: checkpoint.clone(), checkpoint_every: 1e9, held_out: None };
    let mut session = Session::new(Start::Fresh { model, adam }, session_config, &ds)?;
    session.run(&AtomicBool::new(false), |_| true)?;
    let state = &session.trainer().state;
    eprintln!("{} steps; model saved to {}", state.step, checkpoint.display());

    let format = if VideoFormat::Mp4.is_available() { VideoFormat::Mp4 } else { VideoFormat::Gif };
    let size = 256;
    let fov = 2.0 * (0.5 * ds.frames[0].camera.width as f32 / ds.frames[0].camera.fx).atan().to_degrees();
    let orbit = Orbit {
        centre: Vec3::new(0.0, 0.0, -0.15),
        up: Vec3::new(0.0, 0.0, 1.0),
        front: None,
        elevation_deg: 22.0,
        radius: 2.4,
    };
    let started = Instant::now();
    let model = &*session.trainer().model;
    let mut frames = Vec::with_capacity(a.frames as usize);
    for k in 0..a.frames {
        let camera = orbit.camera(360.0 * k as f32 / a.frames as f32, size, size, fov).context("orbit camera")?;
        frames.push(png::rgb_image(&render_view(model, &camera, [1.0; 3]))?);
    }
    let bytes = video::encode(format, &frames, 30)?;
    let path = a.out.join(format!("orbit.{}", format.extension()));
    write_atomic(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
    eprintln!("{} frames rendered in {:.1} s", a.frames, started.elapsed().as_secs_f64());
    println!("{}", path.display());
    Ok(())
}
