//! Helpers for the loader tests: tiny images and hand-built poses.

use std::path::Path;

/// Writes a `w` x `h` PNG (RGBA when `alpha`), creating parent folders.
pub fn write_png(path: &Path, w: u32, h: u32, alpha: bool) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let fmt = image::ImageFormat::Png;
    if alpha {
        image::RgbaImage::from_fn(w, h, |i, j| {
            image::Rgba([(i as u8).wrapping_mul(40), (j as u8).wrapping_mul(60), 7, 128])
        })
        .save_with_format(path, fmt)
        .unwrap();
    } else {
        image::RgbImage::from_fn(w, h, |i, j| image::Rgb([(i as u8).wrapping_mul(40), (j as u8).wrapping_mul(60), 7]))
            .save_with_format(path, fmt)
            .unwrap();
    }
}

/// Writes a `w` x `h` JPEG, creating parent folders.
pub fn write_jpg(path: &Path, w: u32, h: u32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbImage::from_pixel(w, h, image::Rgb([90, 120, 150]))
        .save_with_format(path, image::ImageFormat::Jpeg)
        .unwrap();
}

/// An OpenGL camera-to-world pose on a circle of `radius` about the z axis
/// (at height 1), looking at the origin.
pub fn orbit_pose(angle: f64, radius: f64) -> [[f64; 4]; 3] {
    let eye = [radius * angle.cos(), radius * angle.sin(), 1.0];
    let n = |v: [f64; 3]| {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / l, v[1] / l, v[2] / l]
    };
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let back = n(eye);
    let right = n(cross([0.0, 0.0, 1.0], back));
    let up = cross(back, right);
    [[right[0], up[0], back[0], eye[0]], [right[1], up[1], back[1], eye[1]], [right[2], up[2], back[2], eye[2]]]
}

/// A 3x4 pose as the 4x4 JSON `transform_matrix`.
pub fn mat4(m: &[[f64; 4]; 3]) -> serde_json::Value {
    serde_json::json!([m[0], m[1], m[2], [0.0, 0.0, 0.0, 1.0]])
}

/// Writes a `w` x `h` greyscale mask with values `f(x, y)`, as PNG or JPEG
/// by the extension of `path`, creating parent folders.
pub fn write_mask(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32) -> u8) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let img = image::GrayImage::from_fn(w, h, |x, y| image::Luma([f(x, y)]));
    let fmt = image::ImageFormat::from_path(path).unwrap();
    img.save_with_format(path, fmt).unwrap();
}

/// A PNG of a few kilobytes whose header declares `w`x`h` 8-bit RGB
/// pixels; its compressed data (zeros) ends long before that.
pub fn bomb_png(w: u32, h: u32) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8], data: &[u8]) {
        out.extend((data.len() as u32).to_be_bytes());
        let start = out.len();
        out.extend(kind);
        out.extend(data);
        let crc = crc32fast::hash(&out[start..]);
        out.extend(crc.to_be_bytes());
    }
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    chunk(&mut png, b"IHDR", &ihdr);
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    std::io::Write::write_all(&mut z, &vec![0u8; 4 << 20]).unwrap();
    chunk(&mut png, b"IDAT", &z.finish().unwrap());
    chunk(&mut png, b"IEND", &[]);
    png
}
