//! PNG output, written atomically.

use std::io;
use std::path::Path;

use image::{ImageBuffer, ImageEncoder, Luma, Rgb, RgbImage, codecs::png::PngEncoder};

use crate::engine::io::fsio::write_atomic;
use crate::engine::view::View;

/// Quantises a value in [0, 1] to 8 bits (NaN becomes 0).
pub fn to_u8(v: f32) -> u8 {
    if v.is_nan() { 0 } else { (v.clamp(0.0, 1.0) * 255.0).round() as u8 }
}

/// 8-bit RGB of an `[h x w x 3]` float image.
pub fn quantise_rgb(rgb: &[f32]) -> Vec<u8> {
    rgb.iter().map(|&v| to_u8(v)).collect()
}

/// The colour of a view as an 8-bit RGB image (a PNG's pixels, a video's
/// frame).
pub fn rgb_image(view: &View) -> io::Result<RgbImage> {
    RgbImage::from_raw(view.width, view.height, quantise_rgb(&view.rgb))
        .ok_or_else(|| io::Error::other("a rendered view's colour buffer does not match its size"))
}

/// Which image of a rendered view a PNG holds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ViewImage {
    /// 8-bit colour, as composited on the view's background.
    Rgb,
    /// 8-bit colour and opacity, of a view rendered on black ([`encode_rgba`]).
    Rgba,
    /// 8-bit opacity ([`encode_alpha`]).
    Alpha,
    /// 16-bit depth, the far plane white ([`depth_u16`]).
    Depth { far: f32 },
}

/// Encodes one image of a rendered view as PNG bytes: the one place the
/// service's renders become files.
pub fn encode_view(view: &View, image: ViewImage) -> io::Result<Vec<u8>> {
    match image {
        ViewImage::Rgb => encode_rgb(view.width, view.height, rgb_image(view)?.as_raw()),
        ViewImage::Rgba => encode_rgba(view),
        ViewImage::Alpha => encode_alpha(view),
        ViewImage::Depth { far } => encode_depth(view, far),
    }
}

/// Encodes an 8-bit RGB image as PNG bytes.
pub fn encode_rgb(width: u32, height: u32, rgb8: &[u8]) -> io::Result<Vec<u8>> {
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(rgb8, width, height, image::ExtendedColorType::Rgb8)
        .map_err(io::Error::other)?;
    Ok(out)
}

/// Writes an `[h x w x 3]` float image in [0, 1] as an 8-bit PNG, atomically.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[f32]) -> io::Result<()> {
    let bytes = encode_rgb(width, height, &quantise_rgb(rgb))?;
    write_atomic(path, &bytes)
}

/// The 16-bit depth of each pixel of a view: the expected distance along
/// the ray composited over the far plane, scaled so the far plane is white,
/// `(D + (1 - A) far) / far * 65535` with `D = sum w_i t_i` the view's depth
/// and `A` its opacity. A ray that hits nothing reads 65535 ("at or beyond
/// the far plane"), a surface at distance `d` reads `d / far * 65535`, and
/// only the camera itself reads 0 (without compositing, empty pixels read 0
/// too and could not be told from surfaces at the camera).
pub fn depth_u16(view: &View, far: f32) -> io::Result<Vec<u16>> {
    if !(far.is_finite() && far > 0.0) {
        return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("the far plane must be positive, not {far}")));
    }
    let scale = 65535.0 / far;
    let px = view.depth.iter().zip(&view.opacity).map(|(&d, &a)| {
        let composited = d + (1.0 - a.clamp(0.0, 1.0)) * far;
        (composited * scale).round().clamp(0.0, 65535.0) as u16
    });
    Ok(px.collect())
}

/// Encodes a view's depth ([`depth_u16`]) as a 16-bit greyscale PNG.
pub fn encode_depth(view: &View, far: f32) -> io::Result<Vec<u8>> {
    let px = depth_u16(view, far)?;
    let img: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(view.width, view.height, px)
        .ok_or_else(|| io::Error::other("depth buffer size mismatch"))?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).map_err(io::Error::other)?;
    Ok(out.into_inner())
}

/// Writes a view's depth ([`depth_u16`]) as a 16-bit PNG, atomically.
pub fn write_depth(path: &Path, view: &View, far: f32) -> io::Result<()> {
    write_atomic(path, &encode_depth(view, far)?)
}

/// Encodes a view's opacity as an 8-bit greyscale PNG.
pub fn encode_alpha(view: &View) -> io::Result<Vec<u8>> {
    let a: Vec<u8> = view.opacity.iter().map(|&x| to_u8(x)).collect();
    encode_gray(view.width, view.height, &a)
}

/// Encodes an 8-bit greyscale image (a mask) as PNG bytes.
pub fn encode_gray(width: u32, height: u32, gray: &[u8]) -> io::Result<Vec<u8>> {
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(gray, width, height, image::ExtendedColorType::L8)
        .map_err(io::Error::other)?;
    Ok(out)
}

/// Encodes a view rendered on black as an 8-bit RGBA PNG: the colour,
/// premultiplied by the opacity on black, is divided by it again.
pub fn encode_rgba(view: &View) -> io::Result<Vec<u8>> {
    let mut rgba = Vec::with_capacity(view.opacity.len() * 4);
    for (c, &a) in view.rgb.chunks_exact(3).zip(&view.opacity) {
        let inv = if a > 1e-6 { 1.0 / a } else { 0.0 };
        rgba.extend(c.iter().map(|&x| to_u8(x * inv)));
        rgba.push(to_u8(a));
    }
    let mut out = Vec::new();
    PngEncoder::new(&mut out)
        .write_image(&rgba, view.width, view.height, image::ExtendedColorType::Rgba8)
        .map_err(io::Error::other)?;
    Ok(out)
}

/// Decodes a PNG into 8-bit RGB (tests and tools).
pub fn decode_rgb(bytes: &[u8]) -> Result<ImageBuffer<Rgb<u8>, Vec<u8>>, image::ImageError> {
    Ok(image::load_from_memory(bytes)?.to_rgb8())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::batch::BatchStats;

    /// A 3x1 view: nothing hit, a surface at 2 of a far plane at 8, and a
    /// half-transparent surface at 2 (half its weight, half the far plane).
    fn view() -> View {
        View {
            width: 3,
            height: 1,
            rgb: vec![0.0; 9],
            depth: vec![0.0, 2.0, 0.5 * 2.0],
            opacity: vec![0.0, 1.0, 0.5],
            stats: BatchStats::default(),
        }
    }

    #[test]
    fn depth_is_composited_over_the_far_plane() {
        let px = depth_u16(&view(), 8.0).unwrap();
        // 65535 for nothing; 2 / 8 of it for the surface; (1 + 0.5 * 8) / 8.
        assert_eq!(px, [65535, 16384, 40959]);
        let png = encode_depth(&view(), 8.0).unwrap();
        let decoded = image::load_from_memory(&png).unwrap().into_luma16();
        assert_eq!(decoded.as_raw(), &px);
        assert!(depth_u16(&view(), 0.0).is_err());
        assert!(depth_u16(&view(), f32::NAN).is_err());
    }

    #[test]
    fn alpha_and_rgba_keep_the_opacity() {
        let mut v = view();
        v.rgb = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.25, 0.0, 0.0];
        let a = image::load_from_memory(&encode_alpha(&v).unwrap()).unwrap().into_luma8();
        assert_eq!(a.as_raw(), &[0, 255, 128]);
        let rgba = image::load_from_memory(&encode_rgba(&v).unwrap()).unwrap().into_rgba8();
        assert_eq!(rgba.as_raw(), &[0, 0, 0, 0, 255, 0, 0, 255, 128, 0, 0, 128]);
    }

    #[test]
    fn encode_view_picks_each_image() {
        let mut v = view();
        v.rgb = vec![0.0, 0.0, 0.0, 1.0, 0.5, 0.0, 0.25, 0.0, 0.0];
        let rgb = image::load_from_memory(&encode_view(&v, ViewImage::Rgb).unwrap()).unwrap();
        assert_eq!(rgb.as_rgb8().unwrap().as_raw(), &[0, 0, 0, 255, 128, 0, 64, 0, 0]);
        let pairs = [
            (ViewImage::Rgba, encode_rgba(&v)),
            (ViewImage::Alpha, encode_alpha(&v)),
            (ViewImage::Depth { far: 8.0 }, encode_depth(&v, 8.0)),
        ];
        for (image, direct) in pairs {
            assert_eq!(encode_view(&v, image).unwrap(), direct.unwrap(), "{image:?}");
        }
        assert!(encode_view(&v, ViewImage::Depth { far: 0.0 }).is_err());
        v.rgb.pop();
        assert!(encode_view(&v, ViewImage::Rgb).is_err(), "a colour buffer of the wrong size");
    }
}
