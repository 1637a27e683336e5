//! `radiance render` and `radiance eval`.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::{Common, DataArgs};
use crate::engine::dataset::{Dataset, Frame, LoadOptions};
use crate::engine::io::persist;
use crate::engine::metrics::{psnr, ssim};
use crate::engine::render::{View, render_view};
use crate::media::png;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// Model checkpoint written by `radiance train`.
    #[arg(long)]
    pub model: PathBuf,
    #[command(flatten)]
    pub data: DataArgs,
    /// Output folder (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write 16-bit depth maps as NAME_depth.png: distance / far * 65535,
    /// composited over the far plane (a pixel that hits nothing is white).
    #[arg(long)]
    pub depth: bool,
    #[command(flatten)]
    pub common: Common,
}

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Model checkpoint written by `radiance train`.
    #[arg(long)]
    pub model: PathBuf,
    #[command(flatten)]
    pub data: DataArgs,
    /// Also write the rendered views here.
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub common: Common,
}

/// Loads the model and the split's frames.
fn setup(model: &std::path::Path, data: &DataArgs) -> anyhow::Result<(persist::Restored, Dataset, Vec<usize>)> {
    let restored = persist::load(model)?;
    let opts = LoadOptions { splits: vec![data.split], ..Default::default() };
    let ds = Dataset::load(&data.data, &opts).with_context(|| format!("loading {}", data.data.display()))?;
    let mut idx = ds.split(data.split).to_vec();
    anyhow::ensure!(!idx.is_empty(), "{}: the {} split is empty", data.data.display(), data.split.name());
    if let Some(n) = data.limit {
        idx.truncate(n);
    }
    Ok((restored, ds, idx))
}

fn render_one(r: &persist::Restored, f: &Frame, bg: [f32; 3]) -> (View, f64) {
    let t = Instant::now();
    let v = render_view(&*r.model, &f.camera, bg);
    (v, t.elapsed().as_secs_f64())
}

/// PSNR and SSIM of a rendered view against the frame's ground truth
/// composited on `background`. Scores the 8-bit image that `render` writes,
/// so the numbers match an independent check of the PNG files.
pub(super) fn score(v: &View, f: &Frame, background: [f32; 3]) -> anyhow::Result<(f64, f64)> {
    let ours: Vec<f32> = png::quantise_rgb(&v.rgb).iter().map(|&b| b as f32 / 255.0).collect();
    let gt: Vec<f32> = (0..f.camera.height)
        .flat_map(|j| (0..f.camera.width).map(move |i| (i, j)))
        .flat_map(|(i, j)| f.image.rgb_on(i, j, background))
        .collect();
    let p = psnr(&ours, &gt);
    let s = ssim(&ours, &gt, v.width as usize, v.height as usize, 3).with_context(|| format!("SSIM of {}", f.name))?;
    Ok((p, s))
}

pub fn render(a: RenderArgs) -> anyhow::Result<()> {
    a.common.init_threads()?;
    let (r, ds, idx) = setup(&a.model, &a.data)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    for &i in &idx {
        let f = &ds.frames[i];
        let (v, secs) = render_one(&r, f, ds.background);
        let path = a.out.join(format!("{}.png", f.name));
        png::write_rgb(&path, v.width, v.height, &v.rgb).with_context(|| format!("writing {}", path.display()))?;
        if a.depth {
            let p = a.out.join(format!("{}_depth.png", f.name));
            png::write_depth(&p, &v, ds.far).with_context(|| format!("writing {}", p.display()))?;
        }
        println!("{}  {:.0} ms", path.display(), secs * 1000.0);
    }
    Ok(())
}

pub fn eval(a: EvalArgs) -> anyhow::Result<()> {
    a.common.init_threads()?;
    let (r, ds, idx) = setup(&a.model, &a.data)?;
    if let Some(o) = &a.out {
        std::fs::create_dir_all(o).with_context(|| format!("creating {}", o.display()))?;
    }
    let (mut sum_p, mut sum_s, mut sum_t) = (0.0, 0.0, 0.0);
    for &i in &idx {
        let f = &ds.frames[i];
        let (v, secs) = render_one(&r, f, ds.background);
        let (p, s) = score(&v, f, ds.background)?;
        if let Some(o) = &a.out {
            let path = o.join(format!("{}.png", f.name));
            png::write_rgb(&path, v.width, v.height, &v.rgb).with_context(|| format!("writing {}", path.display()))?;
        }
        println!("{:<12} PSNR {:6.2} dB  SSIM {:.4}  {:.0} ms", f.name, p, s, secs * 1000.0);
        sum_p += p;
        sum_s += s;
        sum_t += secs;
    }
    let n = idx.len() as f64;
    println!("{} views  PSNR {:.2} dB  SSIM {:.4}  {:.0} ms/view", idx.len(), sum_p / n, sum_s / n, sum_t / n * 1000.0);
    Ok(())
}
