//! Per-image masks: which pixels of each photo show the object, and what
//! training and scoring do with them ([`MaskUse`]).
//!
//! Masks come from a folder beside the images, or from the images' alpha
//! channel. For images in a folder named `images_N` the mask folder is the
//! first of `masks_N/` and `masks/` that exists beside it, for `images/` it
//! is `masks/` (the LLFF, COLMAP and Instant-NGP layouts; Blender scenes
//! keep their alpha channel). An image's mask is the file of that folder
//! with the image's stem and any image extension (`images_8/IMG_1.jpg` ->
//! `masks_8/IMG_1.png`): greyscale, or its first channel, 255 inside. It
//! must have the image's size, and once a folder exists every image needs
//! its mask.
//!
//! With masks in effect every frame holds one ([`Frame::mask`]), and
//! [`Dataset::masks`] says what they do: `Score`, `Ignore` or `Composite`
//! (never `Auto`; `Off` when no mask is in effect).

use std::collections::{BTreeMap, HashMap};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::images::{decode_image, has_image_extension};
use super::{Dataset, DatasetError, DatasetFormat, Frame, Image};

/// What per-image masks do. `LoadOptions::masks` asks for one; the loaded
/// [`Dataset::masks`] holds the one in effect.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskUse {
    /// A mask folder gives `Score`, with a warning saying how to train with
    /// the masks; otherwise `Off`, which leaves RGBA images composited as
    /// they always are (their alpha channel acting as `Composite` does).
    #[default]
    Auto,
    /// Training uses every pixel; `eval` and `bench` also score inside the
    /// masks.
    Score,
    /// Training draws its pixels only where the mask is at least
    /// [`INSIDE`]; scored inside the masks too.
    Ignore,
    /// The mask becomes the image's alpha (soft edges kept, multiplied into
    /// an alpha channel the image has): training composites on a random
    /// background where the model does, scoring on white, as for a
    /// transparent object; scored inside the masks too.
    Composite,
    /// No masks: mask folders are not read, RGBA images composite as always.
    Off,
}

impl MaskUse {
    pub const ALL: [MaskUse; 5] = [MaskUse::Auto, MaskUse::Score, MaskUse::Ignore, MaskUse::Composite, MaskUse::Off];

    pub fn name(self) -> &'static str {
        match self {
            MaskUse::Auto => "auto",
            MaskUse::Score => "score",
            MaskUse::Ignore => "ignore",
            MaskUse::Composite => "composite",
            MaskUse::Off => "off",
        }
    }
}

impl std::fmt::Display for MaskUse {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for MaskUse {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        MaskUse::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| format!("unknown mask use '{s}' (expected auto, score, ignore, composite or off)"))
    }
}

/// Mask values from this one up count as inside (0.5 of 255, rounded up).
pub const INSIDE: u8 = 128;

/// One flag per pixel of `mask`: whether it is inside.
pub fn inside(mask: &[u8]) -> Vec<bool> {
    mask.iter().map(|&m| m >= INSIDE).collect()
}

/// Reads the masks `wanted` asks for into `ds` (see the module's
/// documentation) and sets `ds.masks` to the use in effect.
pub(super) fn attach(ds: &mut Dataset, wanted: MaskUse) -> Result<(), DatasetError> {
    ds.masks = MaskUse::Off;
    if wanted == MaskUse::Off {
        return Ok(());
    }
    let found = if ds.format == DatasetFormat::Blender { None } else { find(&ds.frames)? };
    let (masks, from_folder) = match &found {
        Some(found) => (decode(&ds.frames, &found.files)?, true),
        None if wanted == MaskUse::Auto => return Ok(()),
        None if ds.frames.iter().any(|f| f.image.has_alpha) => {
            (ds.frames.iter().map(|f| f.image.rgba.chunks_exact(4).map(|p| p[3]).collect()).collect(), false)
        }
        None => return Err(no_masks(ds, wanted)),
    };
    let effect = if wanted == MaskUse::Auto { MaskUse::Score } else { wanted };
    ds.mask_folder = found.map(|f| f.folder);
    let shown = ds.mask_folder_name().unwrap_or_else(|| "the alpha channel".into());
    if wanted == MaskUse::Auto {
        ds.warnings.push(format!(
            "{shown}: per-image masks, used only to score inside them (eval, bench); `--masks ignore` trains only \
             inside them, `--masks composite` makes the outside transparent (a job's `masks` field)"
        ));
    }
    if effect == MaskUse::Ignore {
        check_trainable(ds, &masks, &shown)?;
    }
    for (f, m) in ds.frames.iter_mut().zip(masks) {
        if effect == MaskUse::Composite && from_folder {
            composite(&mut f.image, &m);
        }
        f.mask = Some(m);
    }
    ds.masks = effect;
    Ok(())
}

/// The folder `path` relative to `root`, with a trailing slash (`masks_8/`).
pub(super) fn folder_name(path: &Path, root: &Path) -> String {
    format!("{}/", path.strip_prefix(root).unwrap_or(path).display())
}

/// The error for a use that needs masks on a dataset without any.
fn no_masks(ds: &Dataset, wanted: MaskUse) -> DatasetError {
    let looked = if ds.format == DatasetFormat::Blender {
        "Blender scenes take their masks from the alpha channel".to_string()
    } else {
        let mut dirs: Vec<String> = Vec::new();
        for f in &ds.frames {
            for d in candidates(f.path.parent().unwrap_or(Path::new("."))) {
                let d = folder_name(&d, &ds.root);
                if !dirs.contains(&d) {
                    dirs.push(d);
                }
            }
        }
        if dirs.is_empty() {
            "the images are not in an images/ or images_N/ folder, so there is no mask folder".to_string()
        } else {
            format!("no {} beside the images", dirs.join(" or "))
        }
    };
    DatasetError::Invalid {
        path: ds.root.clone(),
        message: format!(
            "masks '{wanted}' needs masks, and there are none: {looked}, and no image has an alpha channel"
        ),
    }
}

/// With `Ignore`, some training pixel must be inside; training images with
/// empty masks are named in a warning.
fn check_trainable(ds: &mut Dataset, masks: &[Vec<u8>], shown: &str) -> Result<(), DatasetError> {
    let empty: Vec<&str> = ds
        .train
        .iter()
        .filter(|&&i| !masks[i].iter().any(|&m| m >= INSIDE))
        .map(|&i| ds.frames[i].name.as_str())
        .collect();
    if !ds.train.is_empty() && empty.len() == ds.train.len() {
        return Err(DatasetError::Invalid {
            path: ds.mask_folder.clone().unwrap_or_else(|| ds.root.clone()),
            message: format!(
                "masks 'ignore': no training image has a pixel inside its mask ({shown}, values >= {INSIDE}): \
                 there is nothing to train on"
            ),
        });
    }
    if !empty.is_empty() {
        let shown_names = empty.iter().take(5).copied().collect::<Vec<_>>().join(", ");
        let more = if empty.len() > 5 { format!(" and {} more", empty.len() - 5) } else { String::new() };
        ds.warnings.push(format!(
            "{} training image{} with an empty mask ({shown_names}{more}) {} not trained on",
            empty.len(),
            if empty.len() == 1 { "" } else { "s" },
            if empty.len() == 1 { "is" } else { "are" }
        ));
    }
    Ok(())
}

/// The mask folders an image folder may have, in order of preference:
/// `masks_N/` then `masks/` for `images_N/`, `masks/` for `images/`, none
/// for any other folder.
fn candidates(image_dir: &Path) -> Vec<PathBuf> {
    let (Some(name), Some(parent)) = (image_dir.file_name().and_then(|n| n.to_str()), image_dir.parent()) else {
        return Vec::new();
    };
    match name.strip_prefix("images") {
        Some("") => vec![parent.join("masks")],
        Some(n) if n.strip_prefix('_').is_some_and(|d| !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit())) => {
            vec![parent.join(format!("masks{n}")), parent.join("masks")]
        }
        _ => Vec::new(),
    }
}

/// The mask files of a folder by stem (several files may share one).
type StemIndex = HashMap<OsString, Vec<PathBuf>>;

fn index(dir: &Path) -> Result<StemIndex, DatasetError> {
    let io = |e| DatasetError::Io { path: dir.to_path_buf(), source: e };
    let mut out = StemIndex::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let p = entry.map_err(io)?.path();
        if has_image_extension(&p)
            && p.is_file()
            && let Some(stem) = p.file_stem()
        {
            out.entry(stem.to_os_string()).or_default().push(p);
        }
    }
    Ok(out)
}

/// Where the masks are: every frame's mask file and the (first) folder.
struct Found {
    files: Vec<PathBuf>,
    folder: PathBuf,
}

/// The mask file of every frame, `None` when no image folder has a mask
/// folder; a frame without its mask is an error naming the first.
fn find(frames: &[Frame]) -> Result<Option<Found>, DatasetError> {
    let mut folders: BTreeMap<PathBuf, Option<(PathBuf, StemIndex)>> = BTreeMap::new();
    for f in frames {
        let dir = f.path.parent().unwrap_or(Path::new("."));
        if let std::collections::btree_map::Entry::Vacant(e) = folders.entry(dir.to_path_buf()) {
            let entry = match candidates(dir).into_iter().find(|d| d.is_dir()) {
                Some(d) => Some((d.clone(), index(&d)?)),
                None => None,
            };
            e.insert(entry);
        }
    }
    if folders.values().all(Option::is_none) {
        return Ok(None);
    }
    let mut files = Vec::with_capacity(frames.len());
    let mut missing: Vec<(&Path, String)> = Vec::new();
    let mut first_folder = None;
    for f in frames {
        let dir = f.path.parent().unwrap_or(Path::new("."));
        let stem = f.path.file_stem().unwrap_or_default();
        match &folders[dir] {
            Some((folder, index)) => {
                first_folder.get_or_insert_with(|| folder.clone());
                match index.get(stem).map(Vec::as_slice) {
                    Some([one]) => files.push(one.clone()),
                    Some(several) => {
                        let names: Vec<String> =
                            several.iter().filter_map(|p| p.file_name()).map(|n| n.to_string_lossy().into()).collect();
                        return Err(DatasetError::Invalid {
                            path: folder.clone(),
                            message: format!(
                                "several masks for {}: {} (keep one per image)",
                                f.path.display(),
                                names.join(", ")
                            ),
                        });
                    }
                    None => missing.push((&f.path, format!("{}", folder.display()))),
                }
            }
            None => {
                let looked: Vec<String> = candidates(dir).iter().map(|d| d.display().to_string()).collect();
                let looked = if looked.is_empty() { "any mask folder".into() } else { looked.join(" or ") };
                missing.push((&f.path, looked));
            }
        }
    }
    if let Some((image, looked_in)) = missing.first() {
        return Err(DatasetError::MissingMask {
            image: image.to_path_buf(),
            looked_in: looked_in.clone(),
            missing: missing.len(),
            total: frames.len(),
        });
    }
    Ok(first_folder.map(|folder| Found { files, folder }))
}

/// Decodes the masks in parallel (greyscale, or the first channel), each
/// checked against its frame's size; on failure the error of the first
/// failing mask in frame order.
fn decode(frames: &[Frame], files: &[PathBuf]) -> Result<Vec<Vec<u8>>, DatasetError> {
    let results: Vec<Result<Vec<u8>, DatasetError>> = frames
        .par_iter()
        .zip(files)
        .map(|(f, path)| {
            let m = decode_image(path, &f.path)?;
            let (w, h) = (f.image.width, f.image.height);
            if (m.width, m.height) != (w, h) {
                return Err(DatasetError::SizeMismatch {
                    path: path.clone(),
                    got_w: m.width,
                    got_h: m.height,
                    want_w: w,
                    want_h: h,
                });
            }
            Ok(m.rgba.chunks_exact(4).map(|p| p[0]).collect())
        })
        .collect();
    results.into_iter().collect()
}

/// Makes `mask` the image's alpha: multiplied into the alpha it has
/// (rounded), or replacing the opaque alpha of an image without one.
fn composite(image: &mut Image, mask: &[u8]) {
    for (p, &m) in image.rgba.chunks_exact_mut(4).zip(mask) {
        p[3] = ((p[3] as u32 * m as u32 + 127) / 255) as u8;
    }
    image.has_alpha = true;
}

#[cfg(test)]
#[path = "masks_tests.rs"]
mod tests;
