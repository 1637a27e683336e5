//! `bench --bake`: the splats baked from the benched model, scored as
//! baked and as export gives them (after the floater cleanup, through SPZ);
//! on a capture taken all around, the splats inside the automatic crop
//! (`engine::models::splats::crop`) too, and, where the capture has masks
//! (which the crop does not use), how much of what lies outside them the
//! crop removed.

use std::sync::atomic::AtomicBool;

use super::{BenchArgs, BenchRow, SPLATS_LABEL, ViewScores, score_views, scored_row};
use crate::engine::front::{
    BakeSettings, Budget, CleanupSettings, CropBox, Dataset, MaskUse, Model, SplatsModel, Split, TransientMaps,
    auto_crop_for, bake, cleanup, crop, mask_inside, ply_len, read_spz, write_spz,
};

/// What the crop kept of the Gaussians the masks call outside.
pub struct MaskedCrop {
    /// Gaussians whose centre falls outside the masks in most of the
    /// training photos that see it.
    pub outside: usize,
    /// Of those, the ones the crop removed.
    pub removed: usize,
    /// Gaussians the crop removed in all.
    pub removed_all: usize,
}

/// Scores `b` against `ds`'s training masks; `None` without masks.
pub fn against_masks(model: &SplatsModel, ds: &Dataset, b: &CropBox) -> Option<MaskedCrop> {
    if ds.masks == MaskUse::Off {
        return None;
    }
    let frames: Vec<_> = ds.split_frames(Split::Train).filter(|f| f.mask.is_some()).collect();
    let inside: Vec<Vec<bool>> = frames.iter().map(|f| mask_inside(f.mask.as_ref().unwrap())).collect();
    let mut m = MaskedCrop { outside: 0, removed: 0, removed_all: 0 };
    for p in crate::engine::front::world_centres(model) {
        let (mut out, mut seen) = (0, 0);
        for (f, ins) in frames.iter().zip(&inside) {
            if let Some((u, v)) = f.camera.project(p) {
                seen += 1;
                out += usize::from(!ins[v as usize * f.camera.width as usize + u as usize]);
            }
        }
        let gone = !b.contains(p);
        m.removed_all += usize::from(gone);
        if seen > 0 && 2 * out > seen {
            m.outside += 1;
            m.removed += usize::from(gone);
        }
    }
    Some(m)
}

/// Each baked row's Gaussians and file size.
pub fn print_sizes(rows: &[BenchRow]) {
    for row in rows {
        let (n, b) = (row.gaussians.unwrap_or(0), row.bytes.unwrap_or(0));
        let file = if row.model == "spz" { ".spz" } else { ".ply" };
        println!(
            "{:<8} {n} Gaussians, {file} {:.2} MB, .splat {:.2} MB",
            row.model,
            b as f64 / 1e6,
            (32 * n) as f64 / 1e6
        );
    }
}

/// Bakes `source` (`kind`, trained) into splats for `seconds` and scores
/// them: a row labelled `splats`, its budget the bake's, its time and
/// steps the bake's own; then the same splats as export gives them: after
/// the floater cleanup (`cleaned`), and those written as SPZ and read back
/// (`spz`).
pub fn measure_bake(
    source: &dyn Model,
    ds: &Dataset,
    views: &[usize],
    args: &BenchArgs,
    seconds: f64,
    dropped: Option<&TransientMaps>,
) -> anyhow::Result<Vec<BenchRow>> {
    let settings =
        BakeSettings { budget: Budget { seconds: Some(seconds), steps: None }, seed: args.seed, ..Default::default() };
    let started = std::time::Instant::now();
    let (model, _, steps) = bake(source, ds, &settings, dropped, &AtomicBool::new(false), |_| {})?;
    let elapsed = started.elapsed().as_secs_f64();
    let v = score_views(&model, steps, ds, views, args)?;
    let row = |label: &str, m: &SplatsModel, bytes: u64, v: &ViewScores| BenchRow {
        train_seconds: elapsed,
        steps,
        gaussians: Some(m.layout().n),
        bytes: Some(bytes),
        ..scored_row(label, seconds, v, views.len())
    };
    let l = model.layout();
    let mut rows = vec![row(SPLATS_LABEL, &model, ply_len(l.n, l.k), &v)];
    let (cleaned, removed) = cleanup(&model, &CleanupSettings::default())?;
    println!("cleanup: {removed}");
    let l = cleaned.layout();
    rows.push(row("cleaned", &cleaned, ply_len(l.n, l.k), &score_views(&cleaned, steps, ds, views, args)?));
    let mut spz = Vec::new();
    write_spz(&cleaned, &mut spz)?;
    let mut back = read_spz(&spz, l.n)?.into_model(cleaned.scene().clone())?;
    // The file has no looks: the splats' own are kept, so that the row
    // differs from `cleaned` by the format alone.
    back.set_looks(cleaned.looks().cloned());
    rows.push(row("spz", &back, spz.len() as u64, &score_views(&back, steps, ds, views, args)?));
    if let Some(b) = auto_crop_for(&cleaned, ds)? {
        println!("crop: centre {:?}, half extents {:?}, axes {:?}", b.centre, b.half, b.axes);
        if let Some(m) = against_masks(&cleaned, ds, &b) {
            println!(
                "crop: removed {} of the {} Gaussians outside the masks in most photos ({:.1}%), {} in all",
                m.removed,
                m.outside,
                100.0 * m.removed as f64 / m.outside.max(1) as f64,
                m.removed_all
            );
        }
        let (c, _) = crop(&cleaned, &b)?;
        let l = c.layout();
        rows.push(row("cropped", &c, ply_len(l.n, l.k), &score_views(&c, steps, ds, views, args)?));
    }
    Ok(rows)
}
