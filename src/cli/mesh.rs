//! `radiance mesh`: a trained model (field or splats) as a textured mesh,
//! GLB or USDZ, inside a crop box; `--eval` scores the mesh against the
//! model at the held-out views.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::{Common, MaskArgs};
use crate::engine::front::{
    CAPTURE_KIND, CropBox, Dataset, LoadOptions, MESH_STAGES, MeshOptions, MeshStats, Model, Placement, RenderOptions,
    Split, TexturedMesh, View, crop_model, heldout_pose, load_checkpoint, make_mesh, mesh_as_written, mesh_glb,
    mesh_photos, mesh_usdz, render_heldout_view, render_mesh, scene_box, write_atomic,
};
use crate::media::png;

#[derive(Args, Debug)]
pub struct MeshArgs {
    /// A trained model's checkpoint (any kind: instant, nerf, capture, splats).
    #[arg(long)]
    pub model: PathBuf,
    /// The file to write: `.glb` (glTF 2.0, for `<model-viewer>` and
    /// Android) or `.usdz` (for AR Quick Look on iPhone and iPad).
    #[arg(long)]
    pub out: PathBuf,
    /// Most triangles.
    #[arg(long, default_value_t = MeshOptions::default().triangles)]
    pub triangles: usize,
    /// The texture's side, texels.
    #[arg(long, default_value_t = MeshOptions::default().texture)]
    pub texture: u32,
    /// Grid points along the crop box's longest side (the finest detail
    /// the surface keeps is about one grid step).
    #[arg(long, default_value_t = MeshOptions::default().resolution)]
    pub resolution: usize,
    /// Views of the model the surface and texture are made from.
    #[arg(long, default_value_t = MeshOptions::default().views)]
    pub views: usize,
    /// Their side, pixels.
    #[arg(long, default_value_t = MeshOptions::default().view_size)]
    pub view_size: u32,
    /// The box the mesh is made in: `auto` (the box around what the
    /// training cameras all see, found from `--data`) or a JSON
    /// file of one (`{"centre": [x, y, z], "axes": [[..], [..], [..]],
    /// "half": [hx, hy, hz]}`, world units). Default: the scene's box, for
    /// every kind but `capture` (whose scene reaches the horizon).
    #[arg(long)]
    pub crop: Option<String>,
    /// The dataset the model was trained on: the texture is fitted to its
    /// training photos (unless `--no-photos`), and `--crop auto` and
    /// `--eval` need it.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// With `--data`, colour the texture from the model alone, not fitted
    /// to the training photos too.
    #[arg(long)]
    pub no_photos: bool,
    /// The mesh's longest side in the file, metres.
    #[arg(long, default_value_t = 0.5)]
    pub size: f32,
    /// Also score the mesh against the model at the dataset's held-out
    /// views (`--data`): PSNR of each against the photos, inside their
    /// masks where there are masks.
    #[arg(long)]
    pub eval: bool,
    /// With `--eval`, also write each held-out view as the mesh and as the
    /// model draw it (`DIR/NAME.mesh.png`, `DIR/NAME.model.png`), to look at.
    #[arg(long, requires = "eval")]
    pub renders: Option<PathBuf>,
    #[command(flatten)]
    pub masks: MaskArgs,
    #[command(flatten)]
    pub common: Common,
}

pub fn run(a: MeshArgs) -> anyhow::Result<()> {
    let threads = a.common.init_threads()?;
    let ext = a.out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    anyhow::ensure!(
        matches!(ext.as_deref(), Some("glb" | "usdz")),
        "--out {}: write a .glb or a .usdz",
        a.out.display()
    );
    anyhow::ensure!(a.size.is_finite() && a.size > 0.0, "--size must be a positive number of metres");
    let options = MeshOptions {
        triangles: a.triangles,
        texture: a.texture,
        resolution: a.resolution,
        views: a.views,
        view_size: a.view_size,
        ..Default::default()
    };
    options.check().map_err(|e| anyhow::anyhow!("--{}", e.to_string().replace('_', "-")))?;
    anyhow::ensure!(!a.eval || a.data.is_some(), "--eval needs --data DIR: the held-out views are the dataset's");
    let restored = load_checkpoint(&a.model).with_context(|| format!("loading {}", a.model.display()))?;
    let model = &*restored.model;
    let train = match (&a.data, a.crop.as_deref() == Some("auto") || !a.no_photos) {
        (Some(d), true) => Some(load(d, Split::Train, Default::default())?),
        _ => None,
    };
    let photos = match (&train, a.no_photos) {
        (Some(ds), false) => mesh_photos(model, ds),
        _ => Vec::new(),
    };
    let crop = crop_for(&a, model, train.as_ref())?;
    let cropped = crop_model(model, &crop)?;
    let source: &dyn Model = cropped.as_ref().map_or(model, |m| m as &dyn Model);
    let started = Instant::now();
    let mut last = usize::MAX;
    let mut progress = |stage: usize, done: f32| {
        if stage != last {
            eprintln!("  {:5.1} s  {:3.0}%  {}", started.elapsed().as_secs_f64(), 100.0 * done, MESH_STAGES[stage]);
            last = stage;
        }
    };
    let (mesh, stats) = make_mesh(source, &crop, &options, &photos, &mut progress, &AtomicBool::new(false))?;
    let secs = started.elapsed().as_secs_f64();
    print_stats(&stats, photos.len(), a.data.is_some() && !a.no_photos);
    let front = model.scene().rig.as_ref().map(|r| r.front);
    let place = Placement::new(&mesh, &crop, front, a.size);
    let bytes = if ext.as_deref() == Some("glb") { mesh_glb(&mesh, &place)? } else { mesh_usdz(&mesh, &place)? };
    write_atomic(&a.out, &bytes).with_context(|| format!("writing {}", a.out.display()))?;
    eprintln!(
        "wrote {} ({} triangles, a {}x{} texture, {} bytes) in {secs:.1} s on {threads} threads",
        a.out.display(),
        mesh.triangles.len(),
        mesh.texture_size,
        mesh.texture_size,
        bytes.len()
    );
    if a.eval {
        let data = a.data.as_ref().expect("checked above");
        let opts = LoadOptions { masks: a.masks.masks, ..Default::default() };
        evaluate(model, &mesh_as_written(&mesh)?, &load(data, Split::Test, opts)?, a.renders.as_deref())?;
    }
    Ok(())
}

/// What making the mesh did: the surface, and the texture's fits.
fn print_stats(stats: &MeshStats, photos: usize, wanted: bool) {
    let [gx, gy, gz] = stats.grid;
    let how = stats.level.map_or("depths fused".to_string(), |l| format!("density level {l:.3}"));
    eprintln!(
        "{} views ({:.0}% of their pixels solid), a {gx}x{gy}x{gz} grid ({how}): {} triangles extracted, {} kept without the small pieces",
        stats.views,
        100.0 * stats.solid,
        stats.extracted,
        stats.kept
    );
    let db = |e: f32| -20.0 * e.max(1e-6).log10();
    if let Some(f) = &stats.fit {
        eprintln!("texture fitted to {} pixels of the views: {:.2} -> {:.2} dB", f.pixels, db(f.before), db(f.after));
    }
    match &stats.photos {
        Some(f) => eprintln!(
            "then to {} pixels of {} training photos: {:.2} -> {:.2} dB",
            f.pixels,
            photos,
            db(f.before),
            db(f.after)
        ),
        None if wanted => {
            eprintln!("no training photo to fit the texture to (none without lens distortion)")
        }
        None => {}
    }
}

fn load(data: &std::path::Path, split: Split, opts: LoadOptions) -> anyhow::Result<Dataset> {
    let opts = LoadOptions { splits: vec![split], ..opts };
    Dataset::load(data, &opts).with_context(|| format!("loading {}", data.display()))
}

/// The box `--crop` names, or the scene's box.
fn crop_for(a: &MeshArgs, model: &dyn Model, train: Option<&Dataset>) -> anyhow::Result<CropBox> {
    if let Some(c) = &a.crop {
        return super::splats::crop_box(c, train, model);
    }
    anyhow::ensure!(
        model.kind() != CAPTURE_KIND,
        "a capture model's scene reaches the horizon: give --crop auto --data DIR, or --crop BOX.json"
    );
    Ok(scene_box(model))
}

/// Prints the mesh's and the model's PSNR at each held-out view, against
/// the photo (inside its mask where it has one), and their means.
fn evaluate(model: &dyn Model, mesh: &TexturedMesh, test: &Dataset, renders: Option<&Path>) -> anyhow::Result<()> {
    let bg = test.background;
    if let Some(dir) = renders {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let (mut ours, mut theirs) = (Vec::new(), Vec::new());
    for &i in test.split(Split::Test) {
        let f = &test.frames[i];
        let source = render_heldout_view(model, &f.camera, bg, &RenderOptions::default());
        let camera = crate::engine::front::Camera { c2w: heldout_pose(model, f.camera.c2w), ..f.camera.clone() };
        let m = render_mesh(mesh, &camera, bg, 3);
        let view = View { rgb: m.rgb, opacity: m.coverage, ..source.clone() };
        let (a, b) = (super::eval::score(&view, f, bg)?, super::eval::score(&source, f, bg)?);
        let (pa, pb) = (a.psnr_mask.unwrap_or(a.psnr), b.psnr_mask.unwrap_or(b.psnr));
        println!("{:<12} mesh {pa:6.2} dB  model {pb:6.2} dB", f.name);
        if let Some(dir) = renders {
            for (v, what) in [(&view, "mesh"), (&source, "model")] {
                let path = dir.join(format!("{}.{what}.png", f.name));
                png::write_rgb(&path, v.width, v.height, &v.rgb)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
        }
        ours.push(pa);
        theirs.push(pb);
    }
    anyhow::ensure!(!ours.is_empty(), "the dataset has no held-out views");
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let inside = if test.frames.first().is_some_and(|f| f.mask.is_some()) { " inside the masks" } else { "" };
    println!(
        "{} views{inside}: mesh {:.2} dB, model {:.2} dB (mean appearance)",
        ours.len(),
        mean(&ours),
        mean(&theirs)
    );
    Ok(())
}
