//! The photos a pose estimation starts from: found in a folder (and its
//! subfolders), checked, turned upright (EXIF orientation), downscaled so
//! the longer side is at most `max_size`, and written into the dataset's
//! `images/` folder under flat names.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageDecoder, ImageFormat, ImageReader};
use rayon::prelude::*;

use super::PoseError;

/// Extensions (lower case) taken as photos: the ones the dataset loaders read.
pub const PHOTO_EXTENSIONS: [&str; 3] = crate::engine::dataset::IMAGE_EXTENSIONS;

/// Extensions taken as a video.
pub const VIDEO_EXTENSIONS: [&str; 4] = ["mp4", "mov", "m4v", "mkv"];

/// Fewer photos than this cannot be posed.
pub const MIN_PHOTOS: usize = 3;

/// More than this is refused (a pose estimation of thousands of photos on a
/// CPU takes days; a video gives its frames through [`super::video`]).
pub const MAX_PHOTOS: usize = 2000;

/// Folders deeper than this below the input are not searched.
const MAX_DEPTH: usize = 4;

/// Photos (and any image a client sends) declaring more pixels than this are
/// refused from their header, before decoding: the engine's own limit
/// (`engine::dataset::MAX_PIXELS`, which says why 50 megapixels).
pub const MAX_PIXELS: u64 = crate::engine::dataset::MAX_PIXELS;

/// Photos whose shorter side (after downscaling) is below this are refused:
/// COLMAP finds no features to match in them.
pub const MIN_SIDE: u32 = 32;

/// What an image's header tells, read without decoding its pixels.
#[derive(Debug, Clone, Copy)]
pub struct Header {
    pub format: ImageFormat,
    pub width: u32,
    pub height: u32,
    /// Bytes of a decoded pixel in the image's own colour type (3 for RGB
    /// 8-bit, 8 for 16-bit RGBA).
    pub bytes_per_pixel: u64,
    /// Whether EXIF turns it a quarter turn (width and height swap).
    pub transposed: bool,
}

impl Header {
    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    /// Bytes of the image decoded in its own colour type.
    pub fn decoded_bytes(&self) -> u64 {
        self.pixels() * self.bytes_per_pixel
    }

    /// Width and height once turned upright and downscaled so the longer
    /// side is at most `max_size`: the size [`prepare`] writes.
    pub fn prepared_size(&self, max_size: u32) -> (u32, u32) {
        let (w, h) = if self.transposed { (self.height, self.width) } else { (self.width, self.height) };
        downscaled(w, h, max_size)
    }

    /// Refuses an image that declares more than [`MAX_PIXELS`] (or none).
    pub fn check_pixels(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!("is empty ({}x{} pixels)", self.width, self.height));
        }
        if self.pixels() > MAX_PIXELS {
            return Err(format!(
                "declares {}x{} pixels ({:.0} megapixels), more than the {} megapixels an image may have; \
                 downscale it",
                self.width,
                self.height,
                self.pixels() as f64 / 1e6,
                MAX_PIXELS / 1_000_000
            ));
        }
        Ok(())
    }
}

/// The header of the JPEG or PNG at `path` (its pixels are not decoded);
/// the error says what is wrong with the file.
pub fn read_header(path: &Path) -> Result<Header, String> {
    let reader = ImageReader::open(path).map_err(|e| e.to_string())?;
    header_of(reader.with_guessed_format().map_err(|e| e.to_string())?)
}

fn header_of<R: std::io::BufRead + std::io::Seek>(reader: ImageReader<R>) -> Result<Header, String> {
    let format = match reader.format() {
        Some(f @ (ImageFormat::Jpeg | ImageFormat::Png)) => f,
        _ => return Err("is not a JPEG or PNG image".into()),
    };
    let mut decoder = reader.into_decoder().map_err(|e| format!("cannot be read: {e}"))?;
    header_from(format, &mut decoder)
}

fn header_from(format: ImageFormat, decoder: &mut impl ImageDecoder) -> Result<Header, String> {
    use image::metadata::Orientation::*;
    let (width, height) = decoder.dimensions();
    let orientation = decoder.orientation().map_err(|e| format!("has an unreadable orientation: {e}"))?;
    let transposed = matches!(orientation, Rotate90 | Rotate270 | Rotate90FlipH | Rotate270FlipH);
    Ok(Header { format, width, height, bytes_per_pixel: decoder.color_type().bytes_per_pixel() as u64, transposed })
}

/// `(w, h)` scaled so the longer side is at most `max_size` (never below 1).
fn downscaled(w: u32, h: u32, max_size: u32) -> (u32, u32) {
    let scale = max_size as f64 / w.max(h) as f64;
    if scale >= 1.0 {
        return (w, h);
    }
    (((w as f64 * scale).round() as u32).max(1), ((h as f64 * scale).round() as u32).max(1))
}

/// The peak memory of preparing photos whose largest decodes to
/// `largest_decoded` bytes on `workers` threads at once: each holds the
/// decoded photo, its upright copy and the converted or downscaled one.
pub fn prepare_memory(largest_decoded: u64, workers: usize) -> u64 {
    largest_decoded.saturating_mul(3).saturating_mul(workers.max(1) as u64)
}

/// What a folder holds.
#[derive(Debug, Default)]
pub struct Found {
    /// Photos, sorted by their path relative to the folder.
    pub photos: Vec<PathBuf>,
    pub videos: Vec<PathBuf>,
    /// Files that are neither (relative paths), reported as a warning.
    pub ignored: Vec<String>,
}

/// What a pose estimation starts from.
#[derive(Debug, Clone, Copy)]
pub enum Source<'a> {
    Photos(&'a [PathBuf]),
    Video(&'a Path),
}

impl Found {
    /// Photos, or one video: `None` when there is neither, an error when
    /// there are several videos or both photos and a video.
    pub fn source(&self) -> Result<Option<Source<'_>>, PoseError> {
        match (self.photos.len(), self.videos.len()) {
            (0, 0) => Ok(None),
            (0, 1) => Ok(Some(Source::Video(&self.videos[0]))),
            (0, n) => Err(PoseError::Input(format!(
                "{n} videos found ({}); send one video, or photos",
                super::outcome::list(&self.videos.iter().map(|v| file_name(v)).collect::<Vec<_>>())
            ))),
            (_, 0) => Ok(Some(Source::Photos(&self.photos))),
            (_, _) => Err(PoseError::Input(
                "found both photos and a video; send one or the other (a video's frames are taken from it)".into(),
            )),
        }
    }
}

/// Lists the photos and videos in `dir` and its subfolders (hidden files and
/// folders, like `.DS_Store` or `__MACOSX`, are skipped silently).
pub fn scan(dir: &Path) -> Result<Found, PoseError> {
    let mut found = Found::default();
    walk(dir, dir, 0, &mut found)?;
    found.photos.sort();
    found.videos.sort();
    found.ignored.sort();
    Ok(found)
}

fn walk(root: &Path, dir: &Path, depth: usize, found: &mut Found) -> Result<(), PoseError> {
    let entries = std::fs::read_dir(dir).map_err(|e| PoseError::io(dir, e))?;
    for entry in entries {
        let entry = entry.map_err(|e| PoseError::io(dir, e))?;
        let path = entry.path();
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') || name == "__MACOSX" {
            continue;
        }
        let kind = entry.file_type().map_err(|e| PoseError::io(&path, e))?;
        if kind.is_dir() {
            if depth < MAX_DEPTH {
                walk(root, &path, depth + 1, found)?;
            }
        } else if has_extension(&path, &PHOTO_EXTENSIONS) {
            found.photos.push(path);
        } else if has_extension(&path, &VIDEO_EXTENSIONS) {
            found.videos.push(path);
        } else {
            found.ignored.push(path.strip_prefix(root).unwrap_or(&path).display().to_string());
        }
        if found.photos.len() > MAX_PHOTOS {
            return Err(PoseError::Input(format!(
                "more than {MAX_PHOTOS} photos: pick fewer (every few frames of a sequence are enough)"
            )));
        }
    }
    Ok(())
}

fn file_name(p: &Path) -> String {
    p.file_name().map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into_owned())
}

pub fn has_extension(path: &Path, exts: &[&str]) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| exts.iter().any(|x| e.eq_ignore_ascii_case(x)))
}

/// One photo as written into the dataset.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The file name in `images/`.
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Whether it was resized (or turned upright) rather than copied.
    pub converted: bool,
}

/// Writes `photos` (found below `root`) into `out` (the dataset's image
/// folder), each upright and with its longer side at most `max_size`.
/// Photos keep their format (JPEG or PNG, so a PNG's alpha survives); names
/// are the paths relative to `root` with `/` turned into `_`. All photos must
/// end up the same size: one camera, one orientation.
pub fn prepare(root: &Path, photos: &[PathBuf], out: &Path, max_size: u32) -> Result<Vec<Prepared>, PoseError> {
    if photos.len() < MIN_PHOTOS {
        return Err(PoseError::Input(format!(
            "{} photo{} found; pose estimation needs at least {MIN_PHOTOS} overlapping photos of the scene",
            photos.len(),
            if photos.len() == 1 { "" } else { "s" }
        )));
    }
    std::fs::create_dir_all(out).map_err(|e| PoseError::io(out, e))?;
    let names = flat_names(root, photos)?;
    let results: Vec<Result<Prepared, PoseError>> =
        photos.par_iter().zip(&names).map(|(src, name)| prepare_one(src, &out.join(name), name, max_size)).collect();
    let prepared = results.into_iter().collect::<Result<Vec<_>, _>>()?;
    check_one_size(&prepared)?;
    Ok(prepared)
}

/// Names in the flat image folder, unique (`a/x.jpg` and `b/x.jpg` become
/// `a_x.jpg` and `b_x.jpg`).
fn flat_names(root: &Path, photos: &[PathBuf]) -> Result<Vec<String>, PoseError> {
    let mut seen = BTreeMap::new();
    let mut names = Vec::with_capacity(photos.len());
    for p in photos {
        let rel = p.strip_prefix(root).unwrap_or(p);
        let name: String = rel
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect::<Vec<_>>()
            .join("_")
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() || "._-".contains(c) { c } else { '_' })
            .collect();
        if let Some(other) = seen.insert(name.to_ascii_lowercase(), rel.display().to_string()) {
            return Err(PoseError::Input(format!(
                "photos '{other}' and '{}' would have the same name '{name}'; rename one",
                rel.display()
            )));
        }
        names.push(name);
    }
    Ok(names)
}

fn prepare_one(src: &Path, dst: &Path, name: &str, max_size: u32) -> Result<Prepared, PoseError> {
    let bad = |m: String| PoseError::Input(format!("photo '{}' {m}", src.display()));
    let bytes = std::fs::read(src).map_err(|e| PoseError::io(src, e))?;
    let reader = ImageReader::new(Cursor::new(&bytes)).with_guessed_format().map_err(|e| bad(e.to_string()))?;
    let format = match reader.format() {
        Some(f @ (ImageFormat::Jpeg | ImageFormat::Png)) => f,
        _ => return Err(bad("is not a JPEG or PNG image".into())),
    };
    let mut decoder = reader.into_decoder().map_err(|e| bad(format!("cannot be read: {e}")))?;
    // The size the header declares is checked before a pixel is decoded,
    // and the decoder is held to it.
    let header = header_from(format, &mut decoder).map_err(bad)?;
    header.check_pixels().map_err(bad)?;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(header.decoded_bytes().max(1 << 20).saturating_mul(2));
    decoder.set_limits(limits).map_err(|e| bad(format!("cannot be decoded: {e}")))?;
    let orientation = decoder.orientation().map_err(|e| bad(format!("has an unreadable orientation: {e}")))?;
    let mut img = DynamicImage::from_decoder(decoder).map_err(|e| bad(format!("cannot be decoded: {e}")))?;
    if img.width() == 0 || img.height() == 0 {
        return Err(bad("is empty".into()));
    }
    let upright = orientation == image::metadata::Orientation::NoTransforms;
    img.apply_orientation(orientation);
    let (w, h) = (img.width(), img.height());
    let write_err = |e: image::ImageError| PoseError::Io { path: dst.to_path_buf(), message: e.to_string() };
    let (nw, nh) = downscaled(w, h, max_size);
    if (nw, nh) == (w, h) && upright {
        std::fs::write(dst, &bytes).map_err(|e| PoseError::io(dst, e))?;
        return Ok(Prepared { name: name.to_string(), width: w, height: h, converted: false });
    }
    if (nw, nh) != (w, h) {
        img = img.resize_exact(nw, nh, image::imageops::FilterType::CatmullRom);
    }
    match format {
        ImageFormat::Jpeg => {
            let file = std::fs::File::create(dst).map_err(|e| PoseError::io(dst, e))?;
            let mut w = std::io::BufWriter::new(file);
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut w, 95)
                .encode_image(&img.to_rgb8())
                .map_err(write_err)?;
        }
        _ => img.save_with_format(dst, ImageFormat::Png).map_err(write_err)?,
    }
    Ok(Prepared { name: name.to_string(), width: img.width(), height: img.height(), converted: true })
}

/// All photos one size, or an error that counts each size and names a photo
/// of each.
fn check_one_size(prepared: &[Prepared]) -> Result<(), PoseError> {
    let sizes: Vec<(&str, u32, u32)> = prepared.iter().map(|p| (p.name.as_str(), p.width, p.height)).collect();
    check_sizes(&sizes).map_err(PoseError::Input)
}

/// Photos as `(name, width, height)` after downscaling: all one size and
/// none too small, or an error that counts each size and names a photo of
/// each (what [`prepare`] would find, told before it runs).
pub fn check_sizes(sizes: &[(&str, u32, u32)]) -> Result<(), String> {
    if let Some((name, w, h)) = sizes.iter().find(|(_, w, h)| (*w).min(*h) < MIN_SIDE) {
        return Err(format!(
            "photo '{name}' is {w}x{h} pixels; pose estimation needs photos at least {MIN_SIDE} pixels on each side"
        ));
    }
    let mut by_size: BTreeMap<(u32, u32), Vec<&str>> = BTreeMap::new();
    for (name, w, h) in sizes {
        by_size.entry((*w, *h)).or_default().push(name);
    }
    if by_size.len() <= 1 {
        return Ok(());
    }
    let mut groups: Vec<_> = by_size.into_iter().collect();
    groups.sort_by_key(|(_, names)| std::cmp::Reverse(names.len()));
    let list: Vec<String> =
        groups.iter().map(|((w, h), names)| format!("{} at {w}x{h} (e.g. {})", names.len(), names[0])).collect();
    Err(format!(
        "the photos come in {} different sizes: {}; a scene needs photos from one camera at one orientation \
         (same size after downscaling): leave the others out",
        groups.len(),
        list.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::testutil::bomb_png;

    fn write_png(path: &Path, w: u32, h: u32) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 7) as u8, (y * 5) as u8, 90]));
        img.save(path).unwrap();
    }

    fn write_jpeg(path: &Path, w: u32, h: u32) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 3) as u8, (y * 2) as u8, 40]));
        img.save_with_format(path, ImageFormat::Jpeg).unwrap();
    }

    #[test]
    fn scan_finds_photos_and_videos_below_and_lists_the_rest() {
        let d = tempfile::tempdir().unwrap();
        write_png(&d.path().join("b.png"), 4, 4);
        write_jpeg(&d.path().join("sub/a.JPG"), 4, 4);
        std::fs::write(d.path().join("clip.MOV"), b"x").unwrap();
        std::fs::write(d.path().join("notes.txt"), b"x").unwrap();
        std::fs::write(d.path().join(".DS_Store"), b"x").unwrap();
        std::fs::create_dir_all(d.path().join("__MACOSX")).unwrap();
        std::fs::write(d.path().join("__MACOSX/b.png"), b"x").unwrap();
        let f = scan(d.path()).unwrap();
        let rel: Vec<_> = f.photos.iter().map(|p| p.strip_prefix(d.path()).unwrap().display().to_string()).collect();
        assert_eq!(rel, ["b.png", "sub/a.JPG"]);
        assert_eq!(f.videos.len(), 1);
        assert_eq!(f.ignored, ["notes.txt"]);
    }

    #[test]
    fn prepare_downscales_keeps_small_photos_and_flattens_names() {
        let d = tempfile::tempdir().unwrap();
        let (src, out) = (d.path().join("in"), d.path().join("out"));
        write_jpeg(&src.join("x/big.jpg"), 400, 300);
        write_jpeg(&src.join("y/big.jpg"), 400, 300);
        write_png(&src.join("small.png"), 400, 300);
        let photos = scan(&src).unwrap().photos;
        let p = prepare(&src, &photos, &out, 200).unwrap();
        let names: Vec<_> = p.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["small.png", "x_big.jpg", "y_big.jpg"]);
        for q in &p {
            assert_eq!((q.width, q.height), (200, 150));
            let img = image::open(out.join(&q.name)).unwrap();
            assert_eq!((img.width(), img.height()), (200, 150), "{}", q.name);
        }
        // Without downscaling a photo is copied byte for byte.
        let out2 = d.path().join("out2");
        let p = prepare(&src, &photos, &out2, 800).unwrap();
        assert!(p.iter().all(|q| !q.converted));
        assert_eq!(std::fs::read(out2.join("small.png")).unwrap(), std::fs::read(src.join("small.png")).unwrap());
    }

    #[test]
    fn bad_photo_sets_are_refused_by_name() {
        let d = tempfile::tempdir().unwrap();
        let src = d.path().join("in");
        write_png(&src.join("only.png"), 40, 40);
        let photos = scan(&src).unwrap().photos;
        let e = prepare(&src, &photos, &d.path().join("o1"), 800).unwrap_err().to_string();
        assert!(e.contains("1 photo found") && e.contains("at least 3"), "{e}");

        write_png(&src.join("b.png"), 40, 40);
        std::fs::write(src.join("c.jpg"), b"this is not a jpeg").unwrap();
        let photos = scan(&src).unwrap().photos;
        let e = prepare(&src, &photos, &d.path().join("o2"), 800).unwrap_err().to_string();
        assert!(e.contains("c.jpg") && e.contains("not a JPEG or PNG"), "{e}");

        std::fs::remove_file(src.join("c.jpg")).unwrap();
        write_png(&src.join("tall.png"), 40, 60);
        write_png(&src.join("tall2.png"), 40, 60);
        write_png(&src.join("tall3.png"), 40, 60);
        let photos = scan(&src).unwrap().photos;
        let e = prepare(&src, &photos, &d.path().join("o3"), 800).unwrap_err().to_string();
        assert!(e.contains("2 different sizes") && e.contains("3 at 40x60 (e.g. tall.png)"), "{e}");
        assert!(e.contains("2 at 40x40 (e.g. b.png)"), "{e}");
    }

    #[test]
    fn a_source_is_photos_or_one_video() {
        let p = |n: &str| PathBuf::from(format!("/up/{n}"));
        let found = |photos: &[&str], videos: &[&str]| Found {
            photos: photos.iter().map(|n| p(n)).collect(),
            videos: videos.iter().map(|n| p(n)).collect(),
            ignored: Vec::new(),
        };
        assert!(found(&[], &[]).source().unwrap().is_none());
        assert!(matches!(found(&["a.jpg"], &[]).source().unwrap(), Some(Source::Photos([_]))));
        assert!(matches!(found(&[], &["v.mp4"]).source().unwrap(), Some(Source::Video(v)) if v == p("v.mp4")));
        let e = found(&[], &["a.mp4", "b.mov"]).source().unwrap_err().to_string();
        assert_eq!(e, "2 videos found (a.mp4, b.mov); send one video, or photos");
        let e = found(&["a.jpg"], &["v.mp4"]).source().unwrap_err().to_string();
        assert!(e.starts_with("found both photos and a video"), "{e}");
    }

    #[test]
    fn a_header_declaring_too_many_pixels_is_refused_before_decoding() {
        let d = tempfile::tempdir().unwrap();
        let src = d.path().join("in");
        for k in 0..3 {
            write_jpeg(&src.join(format!("p{k}.jpg")), 64, 48);
        }
        let bomb = bomb_png(30000, 30000);
        assert!(bomb.len() < 10_000, "{} bytes", bomb.len());
        std::fs::write(src.join("bomb.png"), &bomb).unwrap();
        let h = read_header(&src.join("bomb.png")).unwrap();
        assert_eq!((h.width, h.height, h.bytes_per_pixel, h.decoded_bytes()), (30000, 30000, 3, 2_700_000_000));
        let e = h.check_pixels().unwrap_err();
        assert!(e.contains("30000x30000") && e.contains("900 megapixels"), "{e}");
        // Prepared as the poses job does: refused by name and declared size
        // before decoding (a decode fails only later, as truncated).
        let photos = scan(&src).unwrap().photos;
        let err = prepare(&src, &photos, &d.path().join("out"), 800).unwrap_err().to_string();
        assert!(err.contains("bomb.png") && err.contains("30000x30000"), "{err}");
        // Just under the limit passes the header check.
        let h = Header { width: 8000, height: 6250, ..h };
        assert!(h.check_pixels().is_ok());
        assert!(Header { width: 8001, ..h }.check_pixels().is_err());
    }

    #[test]
    fn sizes_are_told_from_headers_upright_and_downscaled() {
        let d = tempfile::tempdir().unwrap();
        write_jpeg(&d.path().join("a.jpg"), 1600, 1200);
        let h = read_header(&d.path().join("a.jpg")).unwrap();
        assert_eq!(
            (h.format, h.prepared_size(800), h.prepared_size(2000)),
            (ImageFormat::Jpeg, (800, 600), (1600, 1200))
        );
        assert_eq!(Header { transposed: true, ..h }.prepared_size(800), (600, 800));
        std::fs::write(d.path().join("t.png"), b"not an image").unwrap();
        let e = read_header(&d.path().join("t.png")).unwrap_err();
        assert!(e.starts_with("cannot be read"), "{e}");
        let e = check_sizes(&[("a.jpg", 800, 600), ("b.jpg", 1, 1), ("c.jpg", 800, 600)]).unwrap_err();
        assert!(e.contains("'b.jpg' is 1x1 pixels") && e.contains("at least 32"), "{e}");
        let e = check_sizes(&[("a.jpg", 800, 600), ("b.jpg", 600, 800), ("c.jpg", 800, 600)]).unwrap_err();
        assert!(e.contains("2 different sizes: 2 at 800x600 (e.g. a.jpg), 1 at 600x800 (e.g. b.jpg)"), "{e}");
        assert!(check_sizes(&[("a.jpg", 800, 600), ("c.jpg", 800, 600)]).is_ok());
    }

    #[test]
    fn names_that_collide_are_refused() {
        let d = tempfile::tempdir().unwrap();
        let photos = vec![d.path().join("a_b.png"), d.path().join("a/b.png")];
        let e = flat_names(d.path(), &photos).unwrap_err().to_string();
        assert!(e.contains("same name 'a_b.png'"), "{e}");
    }
}
