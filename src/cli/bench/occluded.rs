//! `bench --occlude`: occluders pasted into the training photos, and the
//! transient masks training found scored against them.

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::BenchArgs;
use crate::engine::front::{Dataset, Occluders, Pasted, Trainer, load_cutouts, occlude};

/// The transient masks robust training found, against the pasted ones.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct FoundMasks {
    /// Share of the pasted occluders' pixels found transient.
    pub recall: f64,
    /// Share of the other pixels (the static scene) found transient.
    pub static_share: f64,
}

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

/// How the transient masks training found compare with the occluders
/// pasted: the share of the pasted pixels they cover (recall), and of the
/// other pixels of every training photo (the static scene).
pub(super) fn score_found(trainer: &Trainer, ds: &Dataset, pasted: &[Pasted]) -> Option<FoundMasks> {
    let maps = trainer.transients.as_ref()?;
    let (mut hit, mut missed, mut wrong, mut static_pixels) = (0u64, 0u64, 0u64, 0u64);
    for (k, &f) in ds.train.iter().enumerate() {
        let cam = &ds.frames[f].camera;
        let found = maps.mask(k, cam.width, cam.height);
        let truth = pasted.iter().find(|p| p.frame == f).map(|p| &p.mask);
        for (i, &t) in found.iter().enumerate() {
            match (truth.is_some_and(|m| m[i] == 255), t) {
                (true, true) => hit += 1,
                (true, false) => missed += 1,
                (false, true) => {
                    wrong += 1;
                    static_pixels += 1;
                }
                (false, false) => static_pixels += 1,
            }
        }
    }
    Some(FoundMasks {
        recall: hit as f64 / (hit + missed).max(1) as f64,
        static_share: wrong as f64 / static_pixels.max(1) as f64,
    })
}
