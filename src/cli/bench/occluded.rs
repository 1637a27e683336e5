//! `bench --occlude`: occluders pasted into the training photos, and the
//! transient masks training found scored against them.

use anyhow::Context;
use serde::{Deserialize, Serialize};

use std::path::Path;

use super::BenchArgs;
use crate::engine::front::{Dataset, Occluders, Pasted, TransientMaps, View, load_cutouts, occlude, write_atomic};
use crate::media::png::{ViewImage, encode_gray, encode_rgb, encode_view, quantise_rgb};

/// A photo `--occlude` pasted into.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct OccludedPhoto {
    pub name: String,
    /// Share of its pixels covered.
    pub share: f64,
}

/// `--occlude`'s occluders, checked (and their cut-outs read) before the
/// dataset is loaded.
pub(super) fn occluders(a: &BenchArgs, share: f32) -> anyhow::Result<Occluders> {
    fn range<T: Copy>(v: &[T], flag: &str) -> anyhow::Result<(T, T)> {
        match v {
            [one] => Ok((*one, *one)),
            [least, most] => Ok((*least, *most)),
            _ => anyhow::bail!("{flag} takes one number or LEAST,MOST (got {} numbers)", v.len()),
        }
    }
    let cutouts = match &a.occluder_cutouts {
        Some(dir) => load_cutouts(dir).with_context(|| format!("reading the cut-outs in {}", dir.display()))?,
        None => Vec::new(),
    };
    let o = Occluders {
        share,
        per_photo: range(&a.occluders_per_photo, "--occluders-per-photo")?,
        area: range(&a.occluder_area, "--occluder-area")?,
        cutouts,
        seed: a.seed,
    };
    o.check().context("--occlude")?;
    Ok(o)
}

/// Pastes occluders `o` into `ds`'s training photos and says where.
pub(super) fn occlude_photos(ds: &mut Dataset, o: &Occluders) -> anyhow::Result<(Vec<OccludedPhoto>, Vec<Pasted>)> {
    let pasted = occlude(ds, o).context("--occlude")?;
    let photos: Vec<OccludedPhoto> =
        pasted.iter().map(|p| OccludedPhoto { name: ds.frames[p.frame].name.clone(), share: p.share() }).collect();
    let mean = photos.iter().map(|p| p.share).sum::<f64>() / photos.len().max(1) as f64;
    eprintln!(
        "occluded {} of {} training photos, {:.1}% of each on average",
        photos.len(),
        ds.train.len(),
        100.0 * mean
    );
    Ok((photos, pasted))
}

/// Writes a rendered view's colour as a PNG (`bench --save`).
pub(super) fn save_rgb(path: &Path, view: &View) -> anyhow::Result<()> {
    let png = encode_view(view, ViewImage::Rgb)?;
    write_atomic(path, &png).with_context(|| format!("writing {}", path.display()))
}

/// `bench --save`: each occluded training photo as pasted, and the mask
/// training found for it when it dropped transients.
pub(super) fn save_photos(
    dir: &Path,
    ds: &Dataset,
    pasted: &[Pasted],
    maps: Option<&TransientMaps>,
) -> anyhow::Result<()> {
    for p in pasted {
        let f = &ds.frames[p.frame];
        let (w, h) = (f.image.width, f.image.height);
        let rgb: Vec<f32> =
            (0..h).flat_map(|j| (0..w).flat_map(move |i| f.image.rgb_on(i, j, ds.background))).collect();
        let path = dir.join(format!("{}.occluded.png", f.name));
        write_atomic(&path, &encode_rgb(w, h, &quantise_rgb(&rgb))?)
            .with_context(|| format!("writing {}", path.display()))?;
        let found = maps.and_then(|m| m.mask_image(ds.train.iter().position(|&t| t == p.frame)?));
        if let Some((w, h, gray)) = found {
            let path = dir.join(format!("{}.found.png", f.name));
            write_atomic(&path, &encode_gray(w, h, &gray)?).with_context(|| format!("writing {}", path.display()))?;
        }
    }
    Ok(())
}
