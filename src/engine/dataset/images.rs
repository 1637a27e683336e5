//! Image decoding: any PNG or JPEG the `image` crate reads becomes 8-bit
//! RGBA (16-bit samples are scaled to 8 bits, images without alpha get alpha
//! 255 and `has_alpha = false`).

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::ImageDecoder;
use rayon::prelude::*;

use super::{DatasetError, Image};

/// Images declaring more pixels than this are refused from their header,
/// before decoding: a PNG of a few kilobytes can declare 30000x30000 pixels,
/// gigabytes once decoded. 50 megapixels holds the largest common phone
/// photos (48 MP, 8064x6048); decoded at up to 8 bytes a pixel (16-bit
/// RGBA), one such image stays under 400 MB. The service's uploads and pose
/// estimation refuse the same (`poses::photos::MAX_PIXELS` is this).
pub const MAX_PIXELS: u64 = 50_000_000;

/// File extensions (lower case) treated as images.
pub const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];

/// Whether `path` has one of [`IMAGE_EXTENSIONS`] (case-insensitive).
pub(super) fn has_image_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| IMAGE_EXTENSIONS.iter().any(|x| e.eq_ignore_ascii_case(x)))
}

/// The image files of folder `dir` (by [`has_image_extension`]), by name.
pub(super) fn list_images(dir: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let io = |e| DatasetError::Io { path: dir.to_path_buf(), source: e };
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let p = entry.map_err(io)?.path();
        if has_image_extension(&p) && p.is_file() {
            files.push(p);
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}

/// Reads and decodes one image. `referenced_by` is the file that named it
/// (for the error when it is missing).
pub(super) fn decode_image(path: &Path, referenced_by: &Path) -> Result<Image, DatasetError> {
    let bytes = std::fs::read(path).map_err(|e| match e.kind() {
        std::io::ErrorKind::NotFound => {
            DatasetError::MissingImage { path: path.to_path_buf(), referenced_by: referenced_by.to_path_buf() }
        }
        _ => DatasetError::Io { path: path.to_path_buf(), source: e },
    })?;
    decode_bytes(&bytes, path)
}

/// Decodes an in-memory image; `path` names it in errors.
pub(super) fn decode_bytes(bytes: &[u8], path: &Path) -> Result<Image, DatasetError> {
    let bad = |message: String| DatasetError::BadImage { path: path.to_path_buf(), message };
    let reader = image::ImageReader::new(Cursor::new(bytes)).with_guessed_format().map_err(|e| bad(e.to_string()))?;
    if reader.format().is_none() {
        return Err(bad("unrecognised image format (expected PNG or JPEG)".into()));
    }
    // The size the header declares is checked before a pixel is decoded,
    // and the decoder is held to it.
    let mut decoder = reader.into_decoder().map_err(|e| bad(e.to_string()))?;
    let (w, h) = decoder.dimensions();
    if w as u64 * h as u64 > MAX_PIXELS {
        return Err(DatasetError::TooManyPixels {
            path: path.to_path_buf(),
            width: w,
            height: h,
            limit_mp: MAX_PIXELS / 1_000_000,
        });
    }
    let decoded = w as u64 * h as u64 * decoder.color_type().bytes_per_pixel() as u64;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(decoded.max(1 << 20).saturating_mul(2));
    decoder.set_limits(limits).map_err(|e| bad(e.to_string()))?;
    let img = image::DynamicImage::from_decoder(decoder).map_err(|e| bad(e.to_string()))?;
    let has_alpha = img.color().has_alpha();
    let rgba = img.into_rgba8();
    let (width, height) = rgba.dimensions();
    if width == 0 || height == 0 {
        return Err(bad("image is empty".into()));
    }
    Ok(Image { width, height, rgba: rgba.into_raw(), has_alpha })
}

/// Decodes `(image, referenced_by)` pairs in parallel. The result is in input
/// order, and on failure the error is the one of the first failing image in
/// that order, so loading is deterministic.
pub(super) fn decode_all(paths: &[(PathBuf, PathBuf)]) -> Result<Vec<Image>, DatasetError> {
    let results: Vec<Result<Image, DatasetError>> = paths.par_iter().map(|(p, by)| decode_image(p, by)).collect();
    results.into_iter().collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::testutil::bomb_png;

    #[test]
    fn decodes_rgb_rgba_and_16_bit() {
        let dir = tempfile::tempdir().unwrap();
        let by = dir.path().join("t.json");
        let rgb = dir.path().join("rgb.png");
        image::RgbImage::from_pixel(4, 3, image::Rgb([10, 20, 30])).save(&rgb).unwrap();
        let rgba = dir.path().join("rgba.PNG");
        image::RgbaImage::from_pixel(4, 3, image::Rgba([1, 2, 3, 4]))
            .save_with_format(&rgba, image::ImageFormat::Png)
            .unwrap();
        let wide = dir.path().join("16.png");
        image::ImageBuffer::<image::Rgb<u16>, _>::from_pixel(2, 2, image::Rgb([65535u16, 0, 32896]))
            .save(&wide)
            .unwrap();
        let jpg = dir.path().join("a.jpg");
        image::RgbImage::from_pixel(4, 3, image::Rgb([200, 200, 200])).save(&jpg).unwrap();

        let imgs = decode_all(&[
            (rgb.clone(), by.clone()),
            (rgba.clone(), by.clone()),
            (wide.clone(), by.clone()),
            (jpg.clone(), by.clone()),
        ])
        .unwrap();
        assert_eq!((imgs[0].width, imgs[0].height, imgs[0].has_alpha), (4, 3, false));
        assert_eq!(&imgs[0].rgba[..4], &[10, 20, 30, 255]);
        assert_eq!(imgs[0].rgba.len(), 4 * 4 * 3);
        assert!(imgs[1].has_alpha);
        assert_eq!(&imgs[1].rgba[..4], &[1, 2, 3, 4]);
        assert_eq!(&imgs[2].rgba[..4], &[255, 0, 128, 255]);
        assert!(!imgs[3].has_alpha && (imgs[3].rgba[0] as i32 - 200).abs() <= 2);
        assert!(has_image_extension(&rgba) && has_image_extension(&jpg));
        assert!(!has_image_extension(Path::new("r_0")) && !has_image_extension(Path::new("a.gif")));
    }

    #[test]
    fn decode_errors_are_typed_and_ordered() {
        let dir = tempfile::tempdir().unwrap();
        let by = dir.path().join("t.json");
        let garbage = dir.path().join("g.png");
        std::fs::write(&garbage, b"not an image at all").unwrap();
        let truncated = dir.path().join("t.png");
        let ok = dir.path().join("ok.png");
        image::RgbImage::new(8, 8).save(&ok).unwrap();
        let bytes = std::fs::read(&ok).unwrap();
        std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
        let missing = dir.path().join("missing.png");
        for _ in 0..4 {
            let r =
                decode_all(&[(ok.clone(), by.clone()), (missing.clone(), by.clone()), (garbage.clone(), by.clone())]);
            assert!(
                matches!(&r, Err(DatasetError::MissingImage { path, referenced_by })
                    if path == &missing && referenced_by == &by),
                "{r:?}"
            );
        }
        assert!(matches!(decode_image(&garbage, &by), Err(DatasetError::BadImage { .. })));
        assert!(matches!(decode_image(&truncated, &by), Err(DatasetError::BadImage { .. })));
    }

    #[test]
    fn a_bomb_is_refused_from_its_header_naming_the_file_and_its_size() {
        let dir = tempfile::tempdir().unwrap();
        let by = dir.path().join("t.json");
        let bomb = dir.path().join("bomb.png");
        let bytes = bomb_png(30000, 30000);
        assert!(bytes.len() < 20_000, "{} bytes", bytes.len());
        std::fs::write(&bomb, &bytes).unwrap();
        let ok = dir.path().join("ok.png");
        image::RgbImage::new(8, 8).save(&ok).unwrap();
        let e = decode_all(&[(ok.clone(), by.clone()), (bomb.clone(), by.clone())]).unwrap_err();
        assert!(
            matches!(&e, DatasetError::TooManyPixels { path, width: 30000, height: 30000, limit_mp: 50 } if path == &bomb),
            "{e:?}"
        );
        let m = e.to_string();
        assert!(
            m.contains("bomb.png") && m.contains("30000x30000") && m.contains("more than the 50 megapixels"),
            "{m}"
        );
        // Under the limit the header passes, and the data cut short is a
        // decoding error.
        std::fs::write(&bomb, bomb_png(4000, 3000)).unwrap();
        assert!(matches!(decode_image(&bomb, &by), Err(DatasetError::BadImage { .. })));
    }
}
