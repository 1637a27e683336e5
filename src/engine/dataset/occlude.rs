//! Occluders pasted into a share of a dataset's training photos: what a
//! passer-by, a hand or a car does to a capture, made on purpose so that
//! transient-robust training can be measured against known masks. The
//! held-out photos stay clean. An occluder is a generated shape (an
//! ellipse with a two-colour banded texture and a soft edge) or an
//! alpha-matted cut-out from images the caller gives, scaled so that it
//! covers a drawn share of the frame.

use super::{Dataset, Image};
use crate::engine::rng::Rng;

/// What to paste, where.
#[derive(Clone, Debug)]
pub struct Occluders {
    /// Share of the training photos that get occluders (rounded to the
    /// nearest photo).
    pub share: f32,
    /// Occluders in each chosen photo: drawn uniformly from this range.
    pub per_photo: (u32, u32),
    /// Each occluder's area as a share of its photo's frame, drawn
    /// uniformly from this range.
    pub area: (f32, f32),
    /// Cut-outs (RGBA, their alpha the matte); empty: generated shapes.
    pub cutouts: Vec<Image>,
    pub seed: u64,
}

impl Default for Occluders {
    fn default() -> Self {
        Self { share: 0.3, per_photo: (1, 2), area: (0.05, 0.20), cutouts: Vec::new(), seed: 0 }
    }
}

/// A photo's pasted occluders: the frame (an index into `Dataset::frames`)
/// and one byte per pixel, 255 where an occluder covers it at least half.
#[derive(Clone, Debug, PartialEq)]
pub struct Pasted {
    pub frame: usize,
    pub mask: Vec<u8>,
}

impl Pasted {
    /// Share of the frame the occluders cover.
    pub fn share(&self) -> f64 {
        self.mask.iter().filter(|&&m| m == 255).count() as f64 / self.mask.len().max(1) as f64
    }
}

/// Occluder settings that cannot be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OccludeError {
    #[error("the share of occluded photos must be within 0 and 1 (got {0})")]
    Share(f32),
    #[error("an occluder's area must be within 0 and 1 of the frame, the least first (got {0} to {1})")]
    Area(f32, f32),
    #[error("occluders per photo must be at least 1, the least first (got {0} to {1})")]
    PerPhoto(u32, u32),
    #[error("cut-out {0} is empty or has no opaque pixel")]
    EmptyCutout(usize),
}

/// Pastes occluders into a share of `ds`'s training photos (module docs);
/// the masks of what was pasted, by frame, ascending.
pub fn occlude(ds: &mut Dataset, o: &Occluders) -> Result<Vec<Pasted>, OccludeError> {
    if !(0.0..=1.0).contains(&o.share) {
        return Err(OccludeError::Share(o.share));
    }
    let (a0, a1) = o.area;
    if !(a0 > 0.0 && a0 <= a1 && a1 <= 1.0) {
        return Err(OccludeError::Area(a0, a1));
    }
    if o.per_photo.0 == 0 || o.per_photo.0 > o.per_photo.1 {
        return Err(OccludeError::PerPhoto(o.per_photo.0, o.per_photo.1));
    }
    if let Some(k) = o.cutouts.iter().position(|c| alpha_area(c) <= 0.0) {
        return Err(OccludeError::EmptyCutout(k));
    }
    let mut rng = Rng::new(o.seed);
    // The chosen photos: a seeded shuffle of the training split, its first
    // `share` of them.
    let mut train = ds.train.clone();
    for i in (1..train.len()).rev() {
        train.swap(i, rng.below(i as u64 + 1) as usize);
    }
    let chosen = (o.share * train.len() as f32).round() as usize;
    let mut frames: Vec<usize> = train[..chosen].to_vec();
    frames.sort_unstable();
    let mut pasted = Vec::with_capacity(frames.len());
    for f in frames {
        let image = &mut ds.frames[f].image;
        let mut mask = vec![0u8; image.width as usize * image.height as usize];
        let count = o.per_photo.0 + rng.below(u64::from(o.per_photo.1 - o.per_photo.0) + 1) as u32;
        for _ in 0..count {
            let area = a0 + (a1 - a0) * rng.f32();
            let occluder = if o.cutouts.is_empty() {
                generated(image.width, image.height, area, &mut rng)
            } else {
                let cut = &o.cutouts[rng.below(o.cutouts.len() as u64) as usize];
                scaled_cutout(cut, image.width, image.height, area)
            };
            paste(image, &mut mask, &occluder, &mut rng);
        }
        pasted.push(Pasted { frame: f, mask });
    }
    Ok(pasted)
}

/// The cut-outs in folder `dir`: its images (by name), each with an alpha
/// channel that mattes the object.
pub fn load_cutouts(dir: &std::path::Path) -> Result<Vec<Image>, super::DatasetError> {
    let io = |e: std::io::Error| super::DatasetError::Io { path: dir.to_path_buf(), source: e };
    let mut paths: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| super::images::has_image_extension(p))
        .collect();
    paths.sort();
    let bad = |p: &std::path::Path, message: &str| super::DatasetError::BadImage {
        path: p.to_path_buf(),
        message: message.into(),
    };
    if paths.is_empty() {
        return Err(bad(dir, "no cut-out images (PNG with an alpha channel) in this folder"));
    }
    paths
        .iter()
        .map(|p| {
            let img = super::images::decode_image(p, dir)?;
            if !img.has_alpha || alpha_area(&img) <= 0.0 {
                return Err(bad(p, "a cut-out needs an alpha channel with opaque pixels (the matte)"));
            }
            Ok(img)
        })
        .collect()
}

/// The sum of an image's alpha, in pixels.
fn alpha_area(img: &Image) -> f64 {
    img.rgba.chunks_exact(4).map(|p| f64::from(p[3]) / 255.0).sum()
}

/// A generated occluder of about `area` of a `w x h` frame: an ellipse of
/// random proportions and turn, banded in two random colours, its edge
/// soft over about a pixel and a half.
fn generated(w: u32, h: u32, area: f32, rng: &mut Rng) -> Image {
    let target = area * w as f32 * h as f32;
    let ratio = 0.5 + 1.5 * rng.f32();
    // pi a b = target, a = ratio b.
    let b = (target / (std::f32::consts::PI * ratio)).sqrt();
    let a = ratio * b;
    let turn = std::f32::consts::PI * rng.f32();
    let (c, s) = (turn.cos(), turn.sin());
    let colours = [0, 1].map(|_| [rng.f32(), rng.f32(), rng.f32()].map(|v| (v * 255.0) as u8));
    let band = 4.0 + 12.0 * rng.f32();
    let side = (2.0 * a.max(b) + 4.0).ceil() as u32;
    let mut rgba = vec![0u8; side as usize * side as usize * 4];
    let centre = side as f32 / 2.0;
    for y in 0..side {
        for x in 0..side {
            let (dx, dy) = (x as f32 + 0.5 - centre, y as f32 + 0.5 - centre);
            let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
            // Distance past the edge, in pixels (about).
            let r = ((u / a).powi(2) + (v / b).powi(2)).sqrt();
            let past = (r - 1.0) * a.min(b);
            let alpha = (0.5 - past / 1.5).clamp(0.0, 1.0);
            let colour = colours[((u + a) / band) as usize % 2];
            let p = 4 * (y as usize * side as usize + x as usize);
            rgba[p..p + 3].copy_from_slice(&colour);
            rgba[p + 3] = (alpha * 255.0).round() as u8;
        }
    }
    Image { width: side, height: side, rgba, has_alpha: true }
}

/// Cut-out `cut` scaled (bilinear) so that its alpha covers about `area`
/// of a `w x h` frame.
fn scaled_cutout(cut: &Image, w: u32, h: u32, area: f32) -> Image {
    let scale = ((f64::from(area) * f64::from(w) * f64::from(h)) / alpha_area(cut)).sqrt() as f32;
    let (sw, sh) =
        (((cut.width as f32 * scale).round() as u32).max(1), ((cut.height as f32 * scale).round() as u32).max(1));
    let mut rgba = vec![0u8; sw as usize * sh as usize * 4];
    let at = |x: i64, y: i64, c: usize| -> f32 {
        let (x, y) = (x.clamp(0, cut.width as i64 - 1) as usize, y.clamp(0, cut.height as i64 - 1) as usize);
        f32::from(cut.rgba[4 * (y * cut.width as usize + x) + c])
    };
    for y in 0..sh {
        for x in 0..sw {
            let (fx, fy) = ((x as f32 + 0.5) / scale - 0.5, (y as f32 + 0.5) / scale - 0.5);
            let (x0, y0) = (fx.floor(), fy.floor());
            let (tx, ty) = (fx - x0, fy - y0);
            let (x0, y0) = (x0 as i64, y0 as i64);
            let p = 4 * (y as usize * sw as usize + x as usize);
            // Premultiplied, so that the clear pixels' colour does not
            // bleed into the edge.
            let mix = |f: &dyn Fn(i64, i64) -> f32| {
                let top = f(x0, y0) * (1.0 - tx) + f(x0 + 1, y0) * tx;
                let bottom = f(x0, y0 + 1) * (1.0 - tx) + f(x0 + 1, y0 + 1) * tx;
                top * (1.0 - ty) + bottom * ty
            };
            let alpha = mix(&|x, y| at(x, y, 3));
            for c in 0..3 {
                let premultiplied = mix(&|x, y| at(x, y, c) * at(x, y, 3) / 255.0);
                rgba[p + c] = if alpha > 0.0 { (premultiplied / alpha * 255.0).round().min(255.0) as u8 } else { 0 };
            }
            rgba[p + 3] = alpha.round() as u8;
        }
    }
    Image { width: sw, height: sh, rgba, has_alpha: true }
}

/// Pastes `occluder` over `image` (alpha over), its centre at a random
/// point of the frame, and marks where it covers at least half in `mask`.
fn paste(image: &mut Image, mask: &mut [u8], occluder: &Image, rng: &mut Rng) {
    let (w, h) = (image.width as i64, image.height as i64);
    let cx = (rng.f32() * w as f32) as i64 - occluder.width as i64 / 2;
    let cy = (rng.f32() * h as f32) as i64 - occluder.height as i64 / 2;
    for oy in 0..occluder.height as i64 {
        for ox in 0..occluder.width as i64 {
            let (x, y) = (cx + ox, cy + oy);
            if x < 0 || y < 0 || x >= w || y >= h {
                continue;
            }
            let q = 4 * (oy as usize * occluder.width as usize + ox as usize);
            let alpha = f32::from(occluder.rgba[q + 3]) / 255.0;
            if alpha <= 0.0 {
                continue;
            }
            let k = y as usize * w as usize + x as usize;
            let p = 4 * k;
            // Straight (not premultiplied) alpha, over.
            let under = f32::from(image.rgba[p + 3]) / 255.0 * (1.0 - alpha);
            let a = alpha + under;
            for c in 0..3 {
                let over = alpha * f32::from(occluder.rgba[q + c]) + under * f32::from(image.rgba[p + c]);
                image.rgba[p + c] = (over / a).round() as u8;
            }
            image.rgba[p + 3] = (a * 255.0).round() as u8;
            if alpha >= 0.5 {
                mask[k] = 255;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    fn scene() -> Dataset {
        BallScene { size: 48, views: 10, ..Default::default() }.dataset()
    }

    #[test]
    fn a_share_of_the_training_photos_gets_occluders_of_the_asked_size_and_the_rest_stay_clean() {
        let mut ds = scene();
        let clean = ds.clone();
        let o = Occluders { share: 0.3, per_photo: (1, 1), area: (0.1, 0.1), ..Default::default() };
        let pasted = occlude(&mut ds, &o).unwrap();
        let want = (0.3 * ds.train.len() as f32).round() as usize;
        assert_eq!(pasted.len(), want);
        for (f, (a, b)) in ds.frames.iter().zip(&clean.frames).enumerate() {
            match pasted.iter().find(|p| p.frame == f) {
                None => assert_eq!(a.image.rgba, b.image.rgba, "frame {f} changed"),
                Some(p) => {
                    assert!(ds.train.contains(&f), "held-out frame {f} occluded");
                    // One ellipse of a tenth of the frame, less what falls
                    // past its edges.
                    let share = p.share();
                    assert!(share > 0.02 && share < 0.12, "frame {f}: {share}");
                    // Every pixel the mask marks changed or was already the
                    // occluder's colour; every unmarked pixel that changed is
                    // on the soft edge (beside a marked one).
                    let w = a.image.width as usize;
                    for (k, (pa, pb)) in a.image.rgba.chunks(4).zip(b.image.rgba.chunks(4)).enumerate() {
                        if pa != pb && p.mask[k] == 0 {
                            let (x, y) = (k % w, k / w);
                            let near = (y.saturating_sub(2)..(y + 3).min(p.mask.len() / w))
                                .any(|yy| (x.saturating_sub(2)..(x + 3).min(w)).any(|xx| p.mask[yy * w + xx] == 255));
                            assert!(near, "frame {f}: pixel {k} changed outside the mask");
                        }
                    }
                }
            }
        }
        // The same seed pastes the same; another, elsewhere.
        let mut again = clean.clone();
        assert_eq!(occlude(&mut again, &o).unwrap(), pasted);
        let mut other = clean.clone();
        assert_ne!(occlude(&mut other, &Occluders { seed: 1, ..o.clone() }).unwrap(), pasted);
    }

    #[test]
    fn a_cutout_is_scaled_to_the_asked_area_and_pasted_through_its_matte() {
        // A 10x10 cut-out, opaque red in its left half, clear in its right.
        let mut rgba = vec![0u8; 400];
        for k in 0..100 {
            if k % 10 < 5 {
                rgba[4 * k..4 * k + 4].copy_from_slice(&[255, 0, 0, 255]);
            }
        }
        let cut = Image { width: 10, height: 10, rgba, has_alpha: true };
        let scaled = scaled_cutout(&cut, 100, 100, 0.08);
        // 800 px of alpha: 50 x scale^2 = 800, scale 4.
        assert_eq!((scaled.width, scaled.height), (40, 40));
        assert!((alpha_area(&scaled) - 800.0).abs() < 40.0, "{}", alpha_area(&scaled));
        let mut ds = scene();
        let o =
            Occluders { share: 1.0, per_photo: (2, 2), area: (0.05, 0.05), cutouts: vec![cut], ..Default::default() };
        let pasted = occlude(&mut ds, &o).unwrap();
        assert_eq!(pasted.len(), ds.train.len());
        for p in &pasted {
            let img = &ds.frames[p.frame].image;
            // Where the mask marks, the pixel is the cut-out's red.
            for (k, _) in p.mask.iter().enumerate().filter(|(_, m)| **m == 255) {
                let px = &img.rgba[4 * k..4 * k + 3];
                assert!(px[0] >= 128 && px[1] <= 128 && px[2] <= 128, "frame {}: {px:?}", p.frame);
            }
            assert!(p.share() > 0.0);
        }
    }

    #[test]
    fn settings_out_of_range_are_refused_by_name() {
        let mut ds = scene();
        let bad = |o: Occluders| occlude(&mut scene(), &o).unwrap_err().to_string();
        assert!(bad(Occluders { share: 1.5, ..Default::default() }).contains("share"));
        assert!(bad(Occluders { area: (0.3, 0.1), ..Default::default() }).contains("area"));
        assert!(bad(Occluders { area: (0.0, 0.1), ..Default::default() }).contains("area"));
        assert!(bad(Occluders { per_photo: (0, 2), ..Default::default() }).contains("per photo"));
        let clear = Image { width: 2, height: 2, rgba: vec![0; 16], has_alpha: true };
        assert!(bad(Occluders { cutouts: vec![clear], ..Default::default() }).contains("cut-out 0"));
        // Refused settings leave the photos alone.
        let clean = ds.clone();
        assert!(occlude(&mut ds, &Occluders { share: -0.1, ..Default::default() }).is_err());
        assert!(ds.frames.iter().zip(&clean.frames).all(|(a, b)| a.image.rgba == b.image.rgba));
    }
}
