//! glTF 2.0 as one binary file (GLB), the splats as a point primitive of
//! Khronos' `KHR_gaussian_splatting`: `POSITION`, and per Gaussian
//! `KHR_gaussian_splatting:ROTATION` (unit quaternion `x y z w`), `:SCALE`
//! (linear), `:OPACITY` (linear, 0 to 1) and `:SH_DEGREE_l_COEF_n` (each an
//! RGB triple, the 3DGS basis), all as floats, plus `COLOR_0` (the DC
//! colour and opacity, linear, 8 bits) for readers that draw points only.
//!
//! glTF's axes are y up, +z the asset's front (left, up, forward); the
//! `.ply`'s, which our world is written in, are right, down, forward. The
//! half turn about z between them negates x and y of positions and of the
//! quaternion's vector part, and each SH coefficient whose basis function
//! is odd in x and y together. PlayCanvas's `splat-transform` turns a
//! `.ply` into a GLB the same way.

use std::io::{self, Write};

use super::world_all;
use crate::engine::models::splats::SplatsModel;
use crate::engine::models::splats::gaussians::{SH_C0, sigmoid, unit_quat};

/// The extension's name, and the prefix of its attributes.
pub const EXTENSION: &str = "KHR_gaussian_splatting";

/// The sign each SH coefficient (3DGS order, degree 0 to 3) takes under a
/// half turn about z.
const SH_TURN: [f32; 16] = [1., -1., 1., -1., 1., -1., 1., -1., 1., -1., 1., -1., 1., -1., 1., -1.];

/// One accessor's values: floats of `width` components, or `COLOR_0`'s
/// normalised bytes.
enum Column {
    Float { width: usize, values: Vec<f32> },
    Bytes(Vec<u8>),
}

/// Writes `model` as a GLB.
pub fn write_glb(model: &SplatsModel, mut out: impl Write) -> io::Result<()> {
    let l = model.layout();
    let all = world_all(model);
    if all.iter().any(|w| w.mean.iter().chain(&w.log_scale).any(|v| !v.is_finite())) {
        return Err(io::Error::new(io::ErrorKind::InvalidData, "a Gaussian's position or scale is not finite"));
    }
    let turn = |p: [f32; 3]| [-p[0], -p[1], p[2]];
    let mut columns: Vec<(String, Column)> = vec![
        ("POSITION".into(), Column::Float { width: 3, values: all.iter().flat_map(|w| turn(w.mean)).collect() }),
        (
            "COLOR_0".into(),
            Column::Bytes(
                all.iter()
                    .flat_map(|w| {
                        let c = w.sh_dc.map(|c| srgb_to_linear(0.5 + SH_C0 * c));
                        [c[0], c[1], c[2], sigmoid(w.opacity_logit)]
                            .map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                    })
                    .collect(),
            ),
        ),
        (
            format!("{EXTENSION}:ROTATION"),
            Column::Float {
                width: 4,
                values: all
                    .iter()
                    .flat_map(|w| {
                        let [qw, x, y, z] = unit_quat(w.rotation);
                        [-x, -y, z, qw]
                    })
                    .collect(),
            },
        ),
        (
            format!("{EXTENSION}:SCALE"),
            Column::Float { width: 3, values: all.iter().flat_map(|w| w.log_scale.map(f32::exp)).collect() },
        ),
        (
            format!("{EXTENSION}:OPACITY"),
            Column::Float { width: 1, values: all.iter().map(|w| sigmoid(w.opacity_logit)).collect() },
        ),
        (
            format!("{EXTENSION}:SH_DEGREE_0_COEF_0"),
            Column::Float { width: 3, values: all.iter().flat_map(|w| w.sh_dc).collect() },
        ),
    ];
    for j in 1..l.k {
        let degree = (j as f64).sqrt() as usize;
        let coef = j - degree * degree;
        let values = all.iter().flat_map(|w| [0, 1, 2].map(|c| SH_TURN[j] * w.sh_rest[3 * (j - 1) + c])).collect();
        columns.push((format!("{EXTENSION}:SH_DEGREE_{degree}_COEF_{coef}"), Column::Float { width: 3, values }));
    }
    let (json, bin) = document(&columns, l.n);
    write_container(&json, &bin, &mut out)?;
    out.flush()
}

/// glTF's `COLOR_0` is linear; the splats' colours are sRGB.
fn srgb_to_linear(c: f32) -> f32 {
    let c = c.clamp(0.0, 1.0);
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

/// The glTF JSON and its binary buffer for `columns` of `n` Gaussians.
fn document(columns: &[(String, Column)], n: usize) -> (serde_json::Value, Vec<u8>) {
    let mut bin = Vec::new();
    let (mut views, mut accessors) = (Vec::new(), Vec::new());
    let mut attributes = serde_json::Map::new();
    for (i, (name, column)) in columns.iter().enumerate() {
        let offset = bin.len();
        let mut accessor = match column {
            Column::Float { width, values } => {
                bin.extend(values.iter().flat_map(|v| v.to_le_bytes()));
                serde_json::json!({"componentType": 5126, "type": type_name(*width)})
            }
            Column::Bytes(values) => {
                bin.extend_from_slice(values);
                serde_json::json!({"componentType": 5121, "normalized": true, "type": "VEC4"})
            }
        };
        if name == "POSITION"
            && let Column::Float { values, .. } = column
        {
            let (lo, hi) = bounds(values);
            accessor["min"] = serde_json::json!(lo);
            accessor["max"] = serde_json::json!(hi);
        }
        accessor["bufferView"] = i.into();
        accessor["count"] = n.into();
        views.push(serde_json::json!({
            "buffer": 0, "byteOffset": offset, "byteLength": bin.len() - offset, "target": 34962
        }));
        accessors.push(accessor);
        attributes.insert(name.clone(), i.into());
        // Every view starts on 4 bytes, as glTF asks of float data.
        bin.resize(bin.len().next_multiple_of(4), 0);
    }
    let json = serde_json::json!({
        "asset": {"version": "2.0", "generator": concat!("radiance ", env!("CARGO_PKG_VERSION"))},
        "extensionsUsed": [EXTENSION],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": attributes,
            "mode": 0,
            "extensions": {EXTENSION: {
                "kernel": "ellipse",
                "colorSpace": "srgb_rec709_display",
                "projection": "perspective",
                "sortingMethod": "cameraDistance"
            }}
        }]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    (json, bin)
}

fn type_name(width: usize) -> &'static str {
    match width {
        1 => "SCALAR",
        3 => "VEC3",
        _ => "VEC4",
    }
}

fn bounds(xyz: &[f32]) -> ([f32; 3], [f32; 3]) {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in xyz.chunks_exact(3) {
        for c in 0..3 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    if xyz.is_empty() {
        return ([0.0; 3], [0.0; 3]);
    }
    (lo, hi)
}

/// The GLB container: a 12-byte header, the JSON chunk (padded with
/// spaces) and the binary chunk (padded with zeros), each on 4 bytes.
pub fn write_container(json: &serde_json::Value, bin: &[u8], out: &mut impl Write) -> io::Result<()> {
    let mut text = serde_json::to_vec(json).map_err(io::Error::other)?;
    text.resize(text.len().next_multiple_of(4), b' ');
    let pad = bin.len().next_multiple_of(4) - bin.len();
    let total = 12 + 8 + text.len() + 8 + bin.len() + pad;
    let total =
        u32::try_from(total).map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "a GLB holds at most 4 GiB"))?;
    out.write_all(b"glTF")?;
    out.write_all(&2u32.to_le_bytes())?;
    out.write_all(&total.to_le_bytes())?;
    out.write_all(&(text.len() as u32).to_le_bytes())?;
    out.write_all(b"JSON")?;
    out.write_all(&text)?;
    out.write_all(&((bin.len() + pad) as u32).to_le_bytes())?;
    out.write_all(b"BIN\0")?;
    out.write_all(bin)?;
    out.write_all(&vec![0u8; pad])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sh_signs_follow_the_half_turn() {
        // Each basis function of the 3DGS order evaluated at a direction
        // and at its half turn about z: the ratio is the sign.
        let d = [0.3f32, -0.5, 0.81];
        let t = [-d[0], -d[1], d[2]];
        let mut a = [0.0; crate::engine::nn::sh::WIDTH];
        let mut b = [0.0; crate::engine::nn::sh::WIDTH];
        crate::engine::nn::sh::encode_one(d, &mut a);
        crate::engine::nn::sh::encode_one(t, &mut b);
        for j in 0..16 {
            assert!((b[j] - SH_TURN[j] * a[j]).abs() < 1e-5, "{j}: {} {}", a[j], b[j]);
        }
    }

    #[test]
    fn srgb_decodes() {
        assert_eq!(srgb_to_linear(0.0), 0.0);
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(0.5) - 0.214).abs() < 1e-3);
    }
}
