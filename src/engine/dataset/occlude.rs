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

/// The most occluders a photo may get.
pub const MOST_PER_PHOTO: u32 = 100;

/// Occluder settings that cannot be used.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum OccludeError {
    #[error("the share of occluded photos must be within 0 and 1 (got {0})")]
    Share(f32),
    #[error("an occluder's area must be within 0 and 1 of the frame, the least first (got {0} to {1})")]
    Area(f32, f32),
    #[error("occluders per photo must be from 1 to {MOST_PER_PHOTO}, the least first (got {0} to {1})")]
    PerPhoto(u32, u32),
    #[error("cut-out {0} has no pixel at least half opaque: its alpha channel must matte an object")]
    EmptyCutout(usize),
    #[error("cut-out {0}'s matte is too sparse: scaled to cover its area it would be {1} x {2} pixels")]
    SparseCutout(usize, u64, u64),
}

impl Occluders {
    /// Whether the settings can be used: every error [`occlude`] can give
    /// but [`OccludeError::SparseCutout`], which depends on the photos'
    /// sizes.
    pub fn check(&self) -> Result<(), OccludeError> {
        if !(0.0..=1.0).contains(&self.share) {
            return Err(OccludeError::Share(self.share));
        }
        let (a0, a1) = self.area;
        if !(a0 > 0.0 && a0 <= a1 && a1 <= 1.0) {
            return Err(OccludeError::Area(a0, a1));
        }
        let (n0, n1) = self.per_photo;
        if n0 == 0 || n0 > n1 || n1 > MOST_PER_PHOTO {
            return Err(OccludeError::PerPhoto(n0, n1));
        }
        if let Some(k) = self.cutouts.iter().position(|c| !has_matte(c)) {
            return Err(OccludeError::EmptyCutout(k));
        }
        Ok(())
    }
}

/// Pastes occluders into a share of `ds`'s training photos (module docs);
/// the masks of what was pasted, by frame, ascending. Nothing is touched
/// when the settings are refused.
pub fn occlude(ds: &mut Dataset, o: &Occluders) -> Result<Vec<Pasted>, OccludeError> {
    o.check()?;
    let cutouts: Vec<Image> = o.cutouts.iter().map(crop_to_matte).collect();
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
    // Each chosen photo's occluders, drawn first: a sparse cut-out is
    // refused before any photo changes.
    let mut plans = Vec::with_capacity(frames.len());
    for &f in &frames {
        let (w, h) = (ds.frames[f].image.width, ds.frames[f].image.height);
        let count = o.per_photo.0 + rng.below(u64::from(o.per_photo.1 - o.per_photo.0) + 1) as u32;
        let mut shapes = Vec::with_capacity(count as usize);
        for _ in 0..count {
            let area = o.area.0 + (o.area.1 - o.area.0) * rng.f32();
            let shape = if cutouts.is_empty() {
                Shape::ellipse(w, h, area, &mut rng)
            } else {
                let k = rng.below(cutouts.len() as u64) as usize;
                Shape::cutout(k, &cutouts[k], w, h, area)?
            };
            let centre = [rng.f32() * w as f32, rng.f32() * h as f32];
            shapes.push((shape, centre));
        }
        plans.push((f, shapes));
    }
    let mut pasted = Vec::with_capacity(plans.len());
    for (f, shapes) in plans {
        let image = &mut ds.frames[f].image;
        let mut mask = vec![0u8; image.width as usize * image.height as usize];
        for (shape, centre) in &shapes {
            paste(image, &mut mask, shape, *centre, &cutouts);
        }
        pasted.push(Pasted { frame: f, mask });
    }
    Ok(pasted)
}

/// The cut-outs in folder `dir`: its images (by name), each with an alpha
/// channel that mattes the object.
pub fn load_cutouts(dir: &std::path::Path) -> Result<Vec<Image>, super::DatasetError> {
    let paths = super::images::list_images(dir)?;
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
            if !img.has_alpha || !has_matte(&img) {
                return Err(bad(p, "a cut-out needs an alpha channel with pixels at least half opaque (the matte)"));
            }
            Ok(img)
        })
        .collect()
}

/// Whether some pixel of `img` is at least half opaque: a cut-out's
/// matte marks only those (`Pasted::mask`).
fn has_matte(img: &Image) -> bool {
    img.rgba.chunks_exact(4).any(|p| p[3] >= 128)
}

/// The sum of an image's alpha, in pixels.
fn alpha_area(img: &Image) -> f64 {
    img.rgba.chunks_exact(4).map(|p| f64::from(p[3]) / 255.0).sum()
}

/// `img` cropped to the box of its pixels with any alpha (a cut-out's
/// clear margins would otherwise be scaled with it).
fn crop_to_matte(img: &Image) -> Image {
    let w = img.width as usize;
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for (k, p) in img.rgba.chunks_exact(4).enumerate() {
        if p[3] > 0 {
            let (x, y) = (k % w, k / w);
            (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
        }
    }
    if x0 >= x1 {
        return img.clone();
    }
    let mut rgba = Vec::with_capacity((x1 - x0) * (y1 - y0) * 4);
    for y in y0..y1 {
        rgba.extend_from_slice(&img.rgba[4 * (y * w + x0)..4 * (y * w + x1)]);
    }
    Image { width: (x1 - x0) as u32, height: (y1 - y0) as u32, rgba, has_alpha: true }
}

/// One occluder, drawn pixel by pixel where it lands on the frame (it is
/// never made whole: a large one need not fit in memory).
enum Shape {
    /// An ellipse with half-axes `a` and `b` (pixels), turned by `turn`,
    /// banded in two colours every `band` pixels.
    Ellipse { a: f32, b: f32, turn: f32, colours: [[u8; 3]; 2], band: f32 },
    /// Cut-out `k`, scaled by `scale` to `size` pixels.
    Cutout { k: usize, scale: f32, size: [u32; 2] },
}

impl Shape {
    /// An ellipse of about `area` of a `w x h` frame, of random proportions,
    /// turn and colours.
    fn ellipse(w: u32, h: u32, area: f32, rng: &mut Rng) -> Self {
        let target = area * w as f32 * h as f32;
        let ratio = 0.5 + 1.5 * rng.f32();
        // pi a b = target, a = ratio b.
        let b = (target / (std::f32::consts::PI * ratio)).sqrt();
        let turn = std::f32::consts::PI * rng.f32();
        let colours = [0, 1].map(|_| [rng.f32(), rng.f32(), rng.f32()].map(|v| (v * 255.0) as u8));
        Shape::Ellipse { a: ratio * b, b, turn, colours, band: 4.0 + 12.0 * rng.f32() }
    }

    /// Cut-out `k` (`cut`) scaled so that its alpha covers about `area` of
    /// a `w x h` frame; refused when that is more than four frames of
    /// pixels.
    fn cutout(k: usize, cut: &Image, w: u32, h: u32, area: f32) -> Result<Self, OccludeError> {
        let scale = ((f64::from(area) * f64::from(w) * f64::from(h)) / alpha_area(cut)).sqrt();
        let (sw, sh) =
            ((f64::from(cut.width) * scale).round().max(1.0), (f64::from(cut.height) * scale).round().max(1.0));
        if sw * sh > 4.0 * f64::from(w) * f64::from(h) {
            return Err(OccludeError::SparseCutout(k, sw as u64, sh as u64));
        }
        Ok(Shape::Cutout { k, scale: scale as f32, size: [sw as u32, sh as u32] })
    }

    /// Width and height of the box the shape fills (pixels).
    fn size(&self) -> [f32; 2] {
        match self {
            // The bounding box of the turned ellipse, and a margin for its
            // soft edge.
            Shape::Ellipse { a, b, turn, .. } => {
                let (c, s) = (turn.cos(), turn.sin());
                [2.0 * (a * a * c * c + b * b * s * s).sqrt() + 4.0, 2.0 * (a * a * s * s + b * b * c * c).sqrt() + 4.0]
            }
            Shape::Cutout { size, .. } => [size[0] as f32, size[1] as f32],
        }
    }

    /// The shape's colour and alpha (0-1) at `(x, y)` pixels from its box's
    /// centre.
    fn at(&self, x: f32, y: f32, cutouts: &[Image]) -> ([f32; 3], f32) {
        match self {
            Shape::Ellipse { a, b, turn, colours, band } => {
                let (c, s) = (turn.cos(), turn.sin());
                let (u, v) = (c * x + s * y, -s * x + c * y);
                // Distance past the edge, in pixels (about); soft over one
                // and a half.
                let past = (((u / a).powi(2) + (v / b).powi(2)).sqrt() - 1.0) * a.min(*b);
                let alpha = (0.5 - past / 1.5).clamp(0.0, 1.0);
                let colour = colours[((u + a) / band).max(0.0) as usize % 2];
                (colour.map(f32::from), alpha)
            }
            Shape::Cutout { k, scale, size } => {
                let cut = &cutouts[*k];
                // Bilinear, premultiplied: the clear pixels' colour does not
                // bleed into the edge.
                let fx = (x + size[0] as f32 / 2.0) / scale - 0.5;
                let fy = (y + size[1] as f32 / 2.0) / scale - 0.5;
                let (x0, y0) = (fx.floor(), fy.floor());
                let (tx, ty) = (fx - x0, fy - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let px = |x: i64, y: i64| -> [f32; 4] {
                    let (x, y) =
                        (x.clamp(0, cut.width as i64 - 1) as usize, y.clamp(0, cut.height as i64 - 1) as usize);
                    let p = &cut.rgba[4 * (y * cut.width as usize + x)..][..4];
                    let a = f32::from(p[3]) / 255.0;
                    [f32::from(p[0]) * a, f32::from(p[1]) * a, f32::from(p[2]) * a, a]
                };
                let corners = [
                    (px(x0, y0), (1.0 - tx) * (1.0 - ty)),
                    (px(x0 + 1, y0), tx * (1.0 - ty)),
                    (px(x0, y0 + 1), (1.0 - tx) * ty),
                    (px(x0 + 1, y0 + 1), tx * ty),
                ];
                let mut sum = [0.0f32; 4];
                for (p, wt) in corners {
                    for c in 0..4 {
                        sum[c] += wt * p[c];
                    }
                }
                let alpha = sum[3];
                let colour = if alpha > 0.0 { [sum[0] / alpha, sum[1] / alpha, sum[2] / alpha] } else { [0.0; 3] };
                (colour.map(|c| c.min(255.0)), alpha.clamp(0.0, 1.0))
            }
        }
    }
}

/// Pastes `shape` over `image` (straight alpha, over), its box centred at
/// `centre` (pixels), and marks where it covers at least half in `mask`.
/// Only the pixels within the frame are visited.
fn paste(image: &mut Image, mask: &mut [u8], shape: &Shape, centre: [f32; 2], cutouts: &[Image]) {
    let (w, h) = (image.width as usize, image.height as usize);
    let [sw, sh] = shape.size();
    let x0 = (centre[0] - sw / 2.0).floor().max(0.0) as usize;
    let y0 = (centre[1] - sh / 2.0).floor().max(0.0) as usize;
    let x1 = ((centre[0] + sw / 2.0).ceil().max(0.0) as usize).min(w);
    let y1 = ((centre[1] + sh / 2.0).ceil().max(0.0) as usize).min(h);
    for y in y0..y1 {
        for x in x0..x1 {
            let (colour, alpha) = shape.at(x as f32 + 0.5 - centre[0], y as f32 + 0.5 - centre[1], cutouts);
            if alpha <= 0.0 {
                continue;
            }
            let k = y * w + x;
            let p = 4 * k;
            let under = f32::from(image.rgba[p + 3]) / 255.0 * (1.0 - alpha);
            let a = alpha + under;
            for c in 0..3 {
                let over = alpha * colour[c] + under * f32::from(image.rgba[p + c]);
                image.rgba[p + c] = (over / a).round().min(255.0) as u8;
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
                    // Every unmarked pixel that changed is on the soft edge
                    // (beside a marked one).
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

    /// A 10x10 cut-out: opaque red in its left half, clear green in its
    /// right (a colour that must not bleed into the edge).
    fn half_red() -> Image {
        let mut rgba = [0u8, 255, 0, 0].repeat(100);
        for k in (0..100).filter(|k| k % 10 < 5) {
            rgba[4 * k..4 * k + 4].copy_from_slice(&[255, 0, 0, 255]);
        }
        Image { width: 10, height: 10, rgba, has_alpha: true }
    }

    #[test]
    fn a_cutout_is_cropped_scaled_to_the_asked_area_and_pasted_through_its_matte() {
        let cut = crop_to_matte(&half_red());
        assert_eq!((cut.width, cut.height), (5, 10));
        // 800 px of alpha in a 100x100 frame: 50 x scale^2 = 800, scale 4.
        match Shape::cutout(0, &cut, 100, 100, 0.08).unwrap() {
            Shape::Cutout { scale, size, .. } => assert_eq!((scale, size), (4.0, [20, 40])),
            Shape::Ellipse { .. } => unreachable!(),
        }
        let mut ds = scene();
        let clean = ds.clone();
        let o = Occluders {
            share: 1.0,
            per_photo: (2, 2),
            area: (0.05, 0.05),
            cutouts: vec![half_red()],
            ..Default::default()
        };
        let pasted = occlude(&mut ds, &o).unwrap();
        assert_eq!(pasted.len(), ds.train.len());
        let mut over_clear = 0;
        for p in &pasted {
            let (img, was) = (&ds.frames[p.frame].image, &clean.frames[p.frame].image);
            assert!(p.share() > 0.0);
            for (k, _) in p.mask.iter().enumerate().filter(|(_, m)| **m == 255) {
                let px = &img.rgba[4 * k..4 * k + 4];
                assert!(px[0] >= 128 && px[1] <= 128 && px[2] <= 128, "frame {}: {px:?}", p.frame);
                // Over a clear pixel of the photo, the cut-out's own colour:
                // red, with no green from its clear half even at its edge.
                if was.rgba[4 * k + 3] == 0 {
                    assert_eq!(&px[..3], &[255, 0, 0], "frame {}: {px:?}", p.frame);
                    over_clear += 1;
                }
            }
        }
        assert!(over_clear > 0, "no cut-out fell on the ball scene's clear background");
    }

    #[test]
    fn a_sparse_or_clear_cutout_is_refused_and_leaves_the_photos_alone() {
        // Two opaque pixels in opposite corners of 100x100: a fifth of a
        // 48x48 frame would take a cut-out of thousands of pixels a side.
        let mut rgba = vec![0u8; 4 * 100 * 100];
        rgba[3] = 255;
        rgba[4 * 9999 + 3] = 255;
        let sparse = Image { width: 100, height: 100, rgba, has_alpha: true };
        let mut ds = scene();
        let clean = ds.clone();
        let o = Occluders { share: 1.0, cutouts: vec![half_red(), sparse], ..Default::default() };
        let e = occlude(&mut ds, &o).unwrap_err();
        assert!(matches!(e, OccludeError::SparseCutout(1, _, _)), "{e}");
        assert!(ds.frames.iter().zip(&clean.frames).all(|(a, b)| a.image.rgba == b.image.rgba));
        // A matte never half opaque marks nothing: refused too.
        let faint = Image { width: 2, height: 2, rgba: [9, 9, 9, 100].repeat(4), has_alpha: true };
        let e = occlude(&mut ds, &Occluders { cutouts: vec![faint], ..Default::default() }).unwrap_err();
        assert_eq!(e, OccludeError::EmptyCutout(0));
    }

    #[test]
    fn cutouts_are_read_from_a_folder_and_bad_ones_named() {
        let dir = tempfile::tempdir().unwrap();
        let save = |name: &str, img: &Image| {
            image::RgbaImage::from_raw(img.width, img.height, img.rgba.clone())
                .unwrap()
                .save(dir.path().join(name))
                .unwrap()
        };
        save("a.png", &half_red());
        std::fs::write(dir.path().join("notes.txt"), "not an image").unwrap();
        let read = load_cutouts(dir.path()).unwrap();
        assert_eq!(read, vec![half_red()]);
        // An image without alpha is named.
        image::RgbImage::new(4, 4).save(dir.path().join("b.png")).unwrap();
        let e = load_cutouts(dir.path()).unwrap_err().to_string();
        assert!(e.contains("b.png") && e.contains("alpha"), "{e}");
        // A broken PNG is named.
        std::fs::remove_file(dir.path().join("b.png")).unwrap();
        std::fs::write(dir.path().join("c.png"), b"\x89PNG broken").unwrap();
        let e = load_cutouts(dir.path()).unwrap_err().to_string();
        assert!(e.contains("c.png"), "{e}");
        // A folder without images, or none at all.
        let empty = tempfile::tempdir().unwrap();
        assert!(load_cutouts(empty.path()).unwrap_err().to_string().contains("no cut-out images"));
        assert!(load_cutouts(&empty.path().join("missing")).is_err());
    }

    #[test]
    fn settings_out_of_range_are_refused_by_name() {
        let mut ds = scene();
        let bad = |o: Occluders| occlude(&mut scene(), &o).unwrap_err().to_string();
        assert!(bad(Occluders { share: 1.5, ..Default::default() }).contains("share"));
        assert!(bad(Occluders { area: (0.3, 0.1), ..Default::default() }).contains("area"));
        assert!(bad(Occluders { area: (0.0, 0.1), ..Default::default() }).contains("area"));
        assert!(bad(Occluders { per_photo: (0, 2), ..Default::default() }).contains("per photo"));
        assert!(bad(Occluders { per_photo: (1, MOST_PER_PHOTO + 1), ..Default::default() }).contains("per photo"));
        let clear = Image { width: 2, height: 2, rgba: vec![0; 16], has_alpha: true };
        assert!(bad(Occluders { cutouts: vec![clear], ..Default::default() }).contains("cut-out 0"));
        // Refused settings leave the photos alone.
        let clean = ds.clone();
        assert!(occlude(&mut ds, &Occluders { share: -0.1, ..Default::default() }).is_err());
        assert!(ds.frames.iter().zip(&clean.frames).all(|(a, b)| a.image.rgba == b.image.rgba));
    }
}
