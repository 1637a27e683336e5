//! PNG output, written atomically.

use std::io;
use std::path::Path;

use image::{ImageBuffer, ImageEncoder, Luma, Rgb, codecs::png::PngEncoder};

use crate::engine::fsio::write_atomic;

/// Quantises a value in [0, 1] to 8 bits (NaN becomes 0).
pub fn to_u8(v: f32) -> u8 {
    if v.is_nan() { 0 } else { (v.clamp(0.0, 1.0) * 255.0).round() as u8 }
}

/// 8-bit RGB of an `[h x w x 3]` float image.
pub fn quantise_rgb(rgb: &[f32]) -> Vec<u8> {
    rgb.iter().map(|&v| to_u8(v)).collect()
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

/// Writes a depth map as a 16-bit greyscale PNG, `max_depth` mapping to white.
pub fn write_depth(path: &Path, width: u32, height: u32, depth: &[f32], max_depth: f32) -> io::Result<()> {
    let scale = if max_depth > 0.0 { 65535.0 / max_depth } else { 0.0 };
    let px: Vec<u16> = depth.iter().map(|&d| (d * scale).clamp(0.0, 65535.0) as u16).collect();
    let img: ImageBuffer<Luma<u16>, Vec<u16>> =
        ImageBuffer::from_raw(width, height, px).ok_or_else(|| io::Error::other("depth buffer size mismatch"))?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).map_err(io::Error::other)?;
    write_atomic(path, out.get_ref())
}

/// Decodes a PNG into 8-bit RGB (tests and tools).
pub fn decode_rgb(bytes: &[u8]) -> Result<ImageBuffer<Rgb<u8>, Vec<u8>>, image::ImageError> {
    Ok(image::load_from_memory(bytes)?.to_rgb8())
}
