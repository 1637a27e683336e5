//! `radiance render` and `radiance eval`.

use std::ops::Range;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;

use super::{AppearanceArgs, Common, DataArgs};
use crate::engine::front::{
    AppearanceFit, Camera, Dataset, FitError, FitSettings, Frame, Half, LoadOptions, Model, RenderOptions, Restored,
    View, heldout_pose, load_checkpoint, mask_inside, psnr, psnr_inside, render_heldout_view, ssim_map,
};
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
    pub appearance: AppearanceArgs,
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
    /// Also write the rendered views here (NAME.png; with fitted
    /// appearances also NAME_fitted.png, the view as the fitted score reads
    /// it: each half rendered with the appearance fitted on the other).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub appearance: AppearanceArgs,
    #[command(flatten)]
    pub fit: FitArgs,
    #[command(flatten)]
    pub common: Common,
}

/// How `eval` and `bench` also score a capture model's held-out views with
/// fitted appearances.
#[derive(Args, Debug, Clone, Copy)]
pub struct FitArgs {
    /// For a model with per-image appearance, also score each held-out view
    /// as NeRF in the Wild does: an appearance optimised for this many
    /// steps on the left half of the photo (the network frozen), the right
    /// half scored ("fitted right half"); and the whole frame, each half
    /// rendered with the appearance fitted on the other ("fitted whole
    /// frame"). 0: don't.
    #[arg(long, default_value_t = FitSettings::default().steps)]
    pub fit_steps: usize,
}

/// Loads the model and the split's frames.
fn setup(model: &std::path::Path, data: &DataArgs) -> anyhow::Result<(Restored, Dataset, Vec<usize>)> {
    let restored = load_checkpoint(model)?;
    let opts = LoadOptions { splits: vec![data.split], masks: data.masks.masks, ..Default::default() };
    let ds = Dataset::load(&data.data, &opts).with_context(|| format!("loading {}", data.data.display()))?;
    let mut idx = ds.split(data.split).to_vec();
    anyhow::ensure!(!idx.is_empty(), "{}: the {} split is empty", data.data.display(), data.split.name());
    if let Some(n) = data.limit {
        idx.truncate(n);
    }
    Ok((restored, ds, idx))
}

/// Renders frame `f` with `options`, and how long it took.
fn render_one(model: &dyn Model, f: &Frame, bg: [f32; 3], options: &RenderOptions) -> (View, f64) {
    let t = Instant::now();
    let v = render_heldout_view(model, &f.camera, bg, options);
    (v, t.elapsed().as_secs_f64())
}

/// A frame rendered and scored (`eval`, `bench`).
pub(super) struct Scored {
    pub view: View,
    /// Seconds the render took.
    pub secs: f64,
    pub scores: Scores,
    /// For a model with per-image appearance, the PSNR with the mean
    /// appearance (rendered again unless the view already had it).
    pub psnr_mean: Option<f64>,
    /// With a fit, its scores ([`fitted_scores`]).
    pub fit: Option<Fitted>,
}

/// A held-out view scored with fitted appearances.
pub(super) struct Fitted {
    /// PSNR of the right half, rendered with an appearance fitted on the
    /// left half (NeRF in the Wild's rule).
    pub right_half: f64,
    /// PSNR of the whole frame: the right half as above, the left half
    /// rendered with an appearance fitted on the right half.
    pub whole: f64,
    /// The view so scored: its halves from the two renders.
    pub view: View,
}

/// Frame `f` scored with appearances fitted on its halves
/// (`train::appearance_fit`), each fit starting from the appearance
/// `options` gives: the right half rendered with the appearance fitted on
/// the left half, and the left half with the one fitted on the right half.
pub(super) fn fitted_scores(
    fit: &mut AppearanceFit,
    model: &dyn Model,
    f: &Frame,
    background: [f32; 3],
    options: &RenderOptions,
) -> anyhow::Result<Fitted> {
    let camera = Camera { c2w: heldout_pose(model, f.camera.c2w), ..f.camera.clone() };
    let mut render = |half: Half| -> anyhow::Result<View> {
        let e = fit.fit(model, f, &camera, background, options, half)?;
        Ok(fit.render(&camera, background, &e))
    };
    let mut view = render(Half::Left)?;
    let other = render(Half::Right)?;
    let w = f.camera.width as usize;
    let left = Half::Left.columns(f.camera.width);
    let (lo, hi) = (left.start as usize, left.end as usize);
    for row in 0..view.height as usize {
        let (a, b) = (row * w + lo, row * w + hi);
        view.rgb[3 * a..3 * b].copy_from_slice(&other.rgb[3 * a..3 * b]);
        view.depth[a..b].copy_from_slice(&other.depth[a..b]);
        view.opacity[a..b].copy_from_slice(&other.opacity[a..b]);
    }
    view.stats.add(&other.stats);
    let (ours, gt) = cropped(&view, f, background, Half::Right.columns(f.camera.width))?;
    let right_half = psnr(&ours, &gt);
    let (ours, gt) = cropped(&view, f, background, 0..f.camera.width)?;
    Ok(Fitted { right_half, whole: psnr(&ours, &gt), view })
}

/// What `--fit-steps` asks for: a fit of `model`'s held-out appearances
/// (`None` for 0 steps, a model without per-image appearance, or, with a
/// warning, one whose embedding table has no row left to fit in).
pub(super) fn appearance_fit(model: &dyn Model, step: u64, steps: usize) -> anyhow::Result<Option<AppearanceFit>> {
    if steps == 0 {
        return Ok(None);
    }
    match AppearanceFit::new(model, step, FitSettings { steps, ..FitSettings::default() }) {
        // Every row trained on: the views are scored without it.
        Err(e @ FitError::NoSpareRow) => {
            eprintln!("warning: {e}; held-out views are not scored with fitted appearances");
            Ok(None)
        }
        r => Ok(r?),
    }
}

/// Renders frame `f` with the appearance `appearance` gives it and scores
/// it; a model with per-image appearance is also scored with the mean
/// appearance (design `real-captures.md` 2.6: held-out views take the
/// nearest training camera's appearance, the mean is reported beside it).
pub(super) fn render_and_score(
    model: &dyn Model,
    f: &Frame,
    background: [f32; 3],
    appearance: &AppearanceArgs,
    fit: Option<&mut AppearanceFit>,
) -> anyhow::Result<Scored> {
    let options = appearance.options(model, &f.camera)?;
    let (view, secs) = render_one(model, f, background, &options);
    let scores = score(&view, f, background)?;
    let psnr_mean = match model.appearance().map(|a| a.images()) {
        None => None,
        Some(_) if options == RenderOptions::default() => Some(scores.psnr),
        Some(_) => {
            let (mean, _) = render_one(model, f, background, &RenderOptions::default());
            Some(score(&mean, f, background)?.psnr)
        }
    };
    let fit = match fit {
        Some(fit) => Some(fitted_scores(fit, model, f, background, &options)?),
        None => None,
    };
    Ok(Scored { view, secs, scores, psnr_mean, fit })
}

/// A rendered view's scores against its ground truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Scores {
    pub psnr: f64,
    pub ssim: f64,
    /// Inside the frame's mask (`metrics::psnr_inside`,
    /// `SsimMap::mean_inside`): `None` without a mask, or where the mask
    /// has no pixel (no SSIM window centre) inside.
    pub psnr_mask: Option<f64>,
    pub ssim_mask: Option<f64>,
}

/// PSNR and SSIM of a rendered view against the frame's ground truth
/// composited on `background`, over the whole view and inside the frame's
/// mask when it has one. Scores the 8-bit image that `render` writes, so
/// the numbers match an independent check of the PNG files.
pub(super) fn score(v: &View, f: &Frame, background: [f32; 3]) -> anyhow::Result<Scores> {
    score_columns(v, f, background, 0..f.camera.width)
}

/// The view (8-bit, as `render` writes it) and the photo composited on
/// `background`, both cropped to columns `cols`: interleaved RGB in [0, 1].
fn cropped(v: &View, f: &Frame, background: [f32; 3], cols: Range<u32>) -> anyhow::Result<(Vec<f32>, Vec<f32>)> {
    let (w, h) = (f.camera.width as usize, f.camera.height as usize);
    anyhow::ensure!(
        v.width as usize == w && v.height as usize == h && cols.start < cols.end && cols.end as usize <= w,
        "scoring {}: a {}x{} view against a {w}x{h} photo, columns {cols:?}",
        f.name,
        v.width,
        v.height
    );
    let q = png::quantise_rgb(&v.rgb);
    let pixels = || (0..h).flat_map(|j| cols.clone().map(move |i| j * w + i as usize));
    let ours = pixels().flat_map(|p| &q[3 * p..3 * p + 3]).map(|&b| b as f32 / 255.0).collect();
    let gt = pixels().flat_map(|p| f.image.rgb_on((p % w) as u32, (p / w) as u32, background)).collect();
    Ok((ours, gt))
}

/// [`score`] over the view's columns `cols` only (as if the view and the
/// photo were cropped to them).
pub(super) fn score_columns(v: &View, f: &Frame, background: [f32; 3], cols: Range<u32>) -> anyhow::Result<Scores> {
    let (w, h) = (f.camera.width as usize, f.camera.height as usize);
    let (ours, gt) = cropped(v, f, background, cols.clone())?;
    let pixels = || (0..h).flat_map(|j| cols.clone().map(move |i| (i as usize, j)));
    let width = (cols.end - cols.start) as usize;
    let context = || format!("SSIM of {}", f.name);
    let map = ssim_map(&ours, &gt, width, h, 3).with_context(context)?;
    let (psnr_mask, ssim_mask) = match &f.mask {
        Some(m) => {
            let cropped: Vec<u8> = pixels().map(|(i, j)| m[j * w + i]).collect();
            let inside = mask_inside(&cropped);
            let p = psnr_inside(&ours, &gt, 3, &inside).with_context(|| format!("PSNR of {}", f.name))?;
            (p, map.mean_inside(&inside).with_context(context)?)
        }
        None => (None, None),
    };
    Ok(Scores { psnr: psnr(&ours, &gt), ssim: map.mean(), psnr_mask, ssim_mask })
}

/// ` | inside mask PSNR 27.10 dB  SSIM 0.9012` for a view with a mask.
fn mask_text(psnr: Option<f64>, ssim: Option<f64>) -> String {
    let p = psnr.map_or("    -".into(), |p| format!("{p:6.2}"));
    let s = ssim.map_or("     -".into(), |s| format!("{s:.4}"));
    format!(" | inside mask PSNR {p} dB  SSIM {s}")
}

/// ` (mean 26.50)` after a PSNR, for a model with per-image appearance.
fn mean_text(psnr_mean: Option<f64>) -> String {
    psnr_mean.map_or(String::new(), |p| format!(" (mean {p:.2})"))
}

/// ` (fitted right half 26.50, whole frame 26.10)` after a PSNR, when
/// views were fitted.
fn fit_text(right_half: Option<f64>, whole: Option<f64>) -> String {
    match (right_half, whole) {
        (Some(r), Some(w)) => format!(" (fitted right half {r:.2}, whole frame {w:.2})"),
        _ => String::new(),
    }
}

/// The mean of the values that exist, and how many there were.
fn mean_of(values: &[Option<f64>]) -> Option<(f64, usize)> {
    let v: Vec<f64> = values.iter().flatten().copied().collect();
    (!v.is_empty()).then(|| (v.iter().sum::<f64>() / v.len() as f64, v.len()))
}

pub fn render(a: RenderArgs) -> anyhow::Result<()> {
    a.common.init_threads()?;
    let (r, ds, idx) = setup(&a.model, &a.data)?;
    a.appearance.check(&*r.model)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    for &i in &idx {
        let f = &ds.frames[i];
        let options = a.appearance.options(&*r.model, &f.camera)?;
        let (v, secs) = render_one(&*r.model, f, ds.background, &options);
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
    a.appearance.check(&*r.model)?;
    if let Some(o) = &a.out {
        std::fs::create_dir_all(o).with_context(|| format!("creating {}", o.display()))?;
    }
    if r.model.appearance().map(|a| a.images()).is_some() {
        let chosen = a.appearance.appearance.map_or("the nearest training camera's".into(), |c| c.to_string());
        println!("appearance: {chosen}; the mean appearance's PSNR in brackets");
    }
    let mut fit = appearance_fit(&*r.model, r.state.step, a.fit.fit_steps)?;
    if fit.is_some() {
        println!(
            "fitted: appearances fitted on each view's halves, {} steps each; the right half's PSNR with the left \
             half's fit, and the whole frame's with each half rendered with the other half's fit",
            a.fit.fit_steps
        );
    }
    let (mut sum_p, mut sum_s, mut sum_t) = (0.0, 0.0, 0.0);
    let (mut mask_p, mut mask_s, mut mean_p) = (Vec::new(), Vec::new(), Vec::new());
    let (mut fit_p, mut fit_whole) = (Vec::new(), Vec::new());
    for &i in &idx {
        let f = &ds.frames[i];
        let Scored { view: v, secs, scores: sc, psnr_mean, fit: fitted } =
            render_and_score(&*r.model, f, ds.background, &a.appearance, fit.as_mut())?;
        if let Some(o) = &a.out {
            for (v, suffix) in [(Some(&v), ""), (fitted.as_ref().map(|f| &f.view), "_fitted")] {
                let Some(v) = v else { continue };
                let path = o.join(format!("{}{suffix}.png", f.name));
                png::write_rgb(&path, v.width, v.height, &v.rgb)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
        }
        let mask = if f.mask.is_some() { mask_text(sc.psnr_mask, sc.ssim_mask) } else { String::new() };
        let (psnr_fit, psnr_whole) = (fitted.as_ref().map(|f| f.right_half), fitted.as_ref().map(|f| f.whole));
        let mean = mean_text(psnr_mean) + &fit_text(psnr_fit, psnr_whole);
        println!("{:<12} PSNR {:6.2} dB{mean}  SSIM {:.4}  {:.0} ms{mask}", f.name, sc.psnr, sc.ssim, secs * 1000.0);
        sum_p += sc.psnr;
        sum_s += sc.ssim;
        sum_t += secs;
        mask_p.push(sc.psnr_mask);
        mask_s.push(sc.ssim_mask);
        mean_p.push(psnr_mean);
        fit_p.push(psnr_fit);
        fit_whole.push(psnr_whole);
    }
    let n = idx.len() as f64;
    let mut mask = String::new();
    if ds.frames[idx[0]].mask.is_some() {
        let (p, s) = (mean_of(&mask_p), mean_of(&mask_s));
        mask = mask_text(p.map(|p| p.0), s.map(|s| s.0));
        let counted = p.map_or(0, |p| p.1);
        if counted < idx.len() {
            mask += &format!(" ({counted} views with pixels inside)");
        }
    }
    let mean = mean_text(mean_of(&mean_p).map(|m| m.0))
        + &fit_text(mean_of(&fit_p).map(|m| m.0), mean_of(&fit_whole).map(|m| m.0));
    println!(
        "{} views  PSNR {:.2} dB{mean}  SSIM {:.4}  {:.0} ms/view{mask}",
        idx.len(),
        sum_p / n,
        sum_s / n,
        sum_t / n * 1000.0
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;
    use crate::engine::metrics::ssim;

    /// A frame of the ball with a mask, and a "render" that is its ground
    /// truth with the right half changed.
    fn frame_and_view() -> (Frame, View) {
        let mut f = BallScene { size: 24, views: 1, ..Default::default() }.dataset().frames.remove(0);
        f.mask = Some((0..24 * 24).map(|p| if p % 24 < 14 { 255 } else { 0 }).collect());
        let mut rgb: Vec<f32> = (0..24)
            .flat_map(|j| (0..24).map(move |i| (i, j)))
            .flat_map(|(i, j)| f.image.rgb_on(i, j, [1.0; 3]))
            .collect();
        for (p, v) in rgb.iter_mut().enumerate() {
            if (p / 3) % 24 >= 14 {
                *v *= 0.5;
            } else if (p / 3) % 24 == 13 {
                *v = (*v - 0.1).max(0.0);
            }
        }
        let n = rgb.len() / 3;
        let view =
            View { width: 24, height: 24, rgb, depth: vec![0.0; n], opacity: vec![0.0; n], stats: Default::default() };
        (f, view)
    }

    #[test]
    fn masked_scores_are_those_of_the_pixels_inside() {
        let (f, v) = frame_and_view();
        let s = score(&v, &f, [1.0; 3]).unwrap();
        // By hand: the 8-bit render and the ground truth, inside pixels only.
        let ours: Vec<f32> = png::quantise_rgb(&v.rgb).iter().map(|&b| b as f32 / 255.0).collect();
        let gt: Vec<f32> = (0..24)
            .flat_map(|j| (0..24).map(move |i| (i, j)))
            .flat_map(|(i, j)| f.image.rgb_on(i, j, [1.0; 3]))
            .collect();
        let (mut sum, mut n) = (0.0f64, 0);
        for p in 0..24 * 24 {
            if p % 24 < 14 {
                for c in 0..3 {
                    let d = ours[3 * p + c] as f64 - gt[3 * p + c] as f64;
                    sum += d * d;
                }
                n += 3;
            }
        }
        let want = -10.0 * (sum / n as f64).log10();
        assert!((s.psnr_mask.unwrap() - want).abs() < 1e-9, "{:?} {want}", s.psnr_mask);
        assert!(s.psnr_mask.unwrap() > s.psnr + 3.0, "{s:?}");
        // Whole-view scores are unchanged by the mask.
        assert_eq!((s.psnr, s.ssim), (psnr(&ours, &gt), ssim(&ours, &gt, 24, 24, 3).unwrap()));
        // SSIM inside: windows centred on columns 5..=13 (rows 5..=18).
        assert!(s.ssim_mask.unwrap() > s.ssim && s.ssim_mask.unwrap() < 1.0, "{s:?}");
        let mut plain = f.clone();
        plain.mask = None;
        let p = score(&v, &plain, [1.0; 3]).unwrap();
        assert_eq!((p.psnr, p.ssim, p.psnr_mask, p.ssim_mask), (s.psnr, s.ssim, None, None));
    }

    /// Scoring columns is scoring the view and the photo cropped to them:
    /// the render's left 13 columns are the ground truth (only the right
    /// half was changed), the whole range is `score`'s, and a range that
    /// does not fit the view is refused.
    #[test]
    fn column_scores_are_those_of_the_cropped_view() {
        let (f, v) = frame_and_view();
        let whole = score(&v, &f, [1.0; 3]).unwrap();
        assert_eq!(score_columns(&v, &f, [1.0; 3], 0..24).unwrap(), whole);
        let left = score_columns(&v, &f, [1.0; 3], 0..13).unwrap();
        assert!(left.psnr.is_infinite() && left.psnr_mask.unwrap().is_infinite(), "{left:?}");
        assert!((left.ssim - 1.0).abs() < 1e-9, "{left:?}");
        let right = score_columns(&v, &f, [1.0; 3], 12..24).unwrap();
        // By hand over columns 12..24; the mask's inside there is columns 12 and 13.
        let ours: Vec<f32> = png::quantise_rgb(&v.rgb).iter().map(|&b| b as f32 / 255.0).collect();
        let (mut sum, mut n, mut sum_in, mut n_in) = (0.0f64, 0, 0.0f64, 0);
        for j in 0..24u32 {
            for i in 12..24u32 {
                let gt = f.image.rgb_on(i, j, [1.0; 3]);
                for c in 0..3 {
                    let d = (ours[3 * (j * 24 + i) as usize + c] as f64 - gt[c] as f64).powi(2);
                    sum += d;
                    n += 1;
                    if i < 14 {
                        sum_in += d;
                        n_in += 1;
                    }
                }
            }
        }
        assert!((right.psnr - -10.0 * (sum / n as f64).log10()).abs() < 1e-9, "{right:?}");
        assert!((right.psnr_mask.unwrap() - -10.0 * (sum_in / n_in as f64).log10()).abs() < 1e-9, "{right:?}");
        assert!(right.psnr < whole.psnr, "{right:?} {whole:?}");
        for bad in [0..25, 5..5, 30..40] {
            let e = score_columns(&v, &f, [1.0; 3], bad.clone()).unwrap_err().to_string();
            assert!(e.contains("columns"), "{bad:?}: {e}");
        }
    }

    /// `--fit-steps`: 0 fits nothing; a model whose embedding table has no
    /// row left to fit in is scored without a fit (a warning), not refused.
    #[test]
    fn a_fit_that_cannot_be_made_is_left_out() {
        use crate::engine::models::capture::config::CaptureConfig;
        use crate::engine::models::config::ModelConfig;
        let ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
        let config = CaptureConfig { max_images: 4, ..CaptureConfig::tiny() };
        let mut m = ModelConfig::Capture(config).build(ds.scene(), 1).unwrap();
        assert!(appearance_fit(&*m, 1, 64).unwrap().is_some());
        assert!(appearance_fit(&*m, 1, 0).unwrap().is_none());
        m.restore_state(&mut |_| Some(vec![1.0; 4]), 1).unwrap();
        assert!(appearance_fit(&*m, 1, 64).unwrap().is_none());
    }

    /// The fitted scores: the view's left half is the render with the
    /// appearance fitted on the right half, its right half the one fitted
    /// on the left half (the fits are repeatable: the same seed); the right
    /// half's PSNR and the whole frame's are those of that view, by hand.
    #[test]
    fn fitted_scores_cross_the_halves() {
        use crate::engine::models::capture::config::CaptureConfig;
        use crate::engine::models::config::ModelConfig;
        let ds = BallScene { size: 9, views: 4, ..Default::default() }.dataset();
        let config = CaptureConfig { max_images: 4, ..CaptureConfig::tiny() };
        let mut m = ModelConfig::Capture(config).build(ds.scene(), 1).unwrap();
        m.restore_state(&mut |_| Some(vec![0.0, 1.0, 1.0, 0.0]), 1).unwrap();
        let mut rng = crate::engine::rng::Rng::new(4);
        m.params_mut().iter_mut().for_each(|p| *p += 0.3 * rng.normal());
        let f = &ds.frames[0];
        let (bg, opts) = (ds.background, RenderOptions::default());
        let mut fit = appearance_fit(&*m, 1, 6).unwrap().unwrap();
        let got = fitted_scores(&mut fit, &*m, f, bg, &opts).unwrap();
        let camera = Camera { c2w: crate::engine::models::heldout_pose(&*m, f.camera.c2w), ..f.camera.clone() };
        let mut alone = |half| {
            let e = fit.fit(&*m, f, &camera, bg, &opts, half).unwrap();
            fit.render(&camera, bg, &e)
        };
        let (from_left, from_right) = (alone(Half::Left), alone(Half::Right));
        assert_ne!(from_left.rgb, from_right.rgb, "the two fits should differ on this model");
        let w = 9;
        for k in 0..w * 9 {
            let src = if k % w < w / 2 { &from_right } else { &from_left };
            assert_eq!(got.view.rgb[3 * k..3 * k + 3], src.rgb[3 * k..3 * k + 3], "pixel {k}");
            assert_eq!(got.view.depth[k], src.depth[k], "pixel {k}");
        }
        let mse = |cols: Range<usize>| {
            let q = png::quantise_rgb(&got.view.rgb);
            let (mut sum, mut n) = (0.0f64, 0);
            for k in (0..w * 9).filter(|k| cols.contains(&(k % w))) {
                let gt = f.image.rgb_on((k % w) as u32, (k / w) as u32, bg);
                for c in 0..3 {
                    sum += (f64::from(q[3 * k + c]) / 255.0 - f64::from(gt[c])).powi(2);
                    n += 1;
                }
            }
            -10.0 * (sum / n as f64).log10()
        };
        assert!((got.right_half - mse(4..9)).abs() < 1e-4, "{} {}", got.right_half, mse(4..9));
        assert!((got.whole - mse(0..9)).abs() < 1e-4, "{} {}", got.whole, mse(0..9));
    }

    #[test]
    fn mask_text_and_means() {
        assert_eq!(mask_text(Some(27.104), Some(0.90123)), " | inside mask PSNR  27.10 dB  SSIM 0.9012");
        assert_eq!(mask_text(None, None), " | inside mask PSNR     - dB  SSIM      -");
        assert_eq!(mean_text(Some(26.504)), " (mean 26.50)");
        assert_eq!(mean_text(None), "");
        assert_eq!(fit_text(Some(22.254), Some(21.5)), " (fitted right half 22.25, whole frame 21.50)");
        assert_eq!(fit_text(None, None), "");
        assert_eq!(mean_of(&[Some(1.0), None, Some(3.0)]), Some((2.0, 2)));
        assert_eq!(mean_of(&[None]), None);
    }
}
