//! Splats in the files other tools read:
//! - the 3DGS paper's `.ply` (binary little-endian; per Gaussian `x y z`,
//!   `nx ny nz` (zero), `f_dc_0..2`, `f_rest_*` channel by channel,
//!   `opacity` as a logit, `scale_0..2` as logarithms, `rot_0..3` as a
//!   quaternion `w x y z`), which SuperSplat, Spark, GaussianSplats3D and
//!   the paper's own viewer open;
//! - antimatter15's 32-byte `.splat` (position and linear scale as f32,
//!   colour and opacity as 4 bytes, the unit quaternion `w x y z` as 4 bytes
//!   `q * 128 + 128`), largest and most opaque Gaussians first;
//! - Niantic's SPZ (`spz`): every value quantised, gzipped, a fifth to a
//!   tenth of the `.ply`;
//! - glTF 2.0 binary with `KHR_gaussian_splatting` (`glb`).
//!
//! Both are in the world units and axes of the capture's cameras (the
//! model's space is undone: positions `p / scale + centre`, log scales
//! minus `ln scale`; rotations and colours are unchanged, since the model's
//! space is the world shifted and scaled, never turned).

use std::io::{self, Write};

use super::SplatsModel;
use super::gaussians::{SH_C0, sigmoid, unit_quat};
use crate::engine::models::Model;

/// The file formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Ply,
    Splat,
    Spz,
    Glb,
}

impl Format {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "ply" => Some(Format::Ply),
            "splat" => Some(Format::Splat),
            "spz" => Some(Format::Spz),
            "glb" => Some(Format::Glb),
            _ => None,
        }
    }
    pub fn extension(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::Splat => "splat",
            Format::Spz => "spz",
            Format::Glb => "glb",
        }
    }
    pub fn content_type(self) -> &'static str {
        match self {
            Format::Glb => "model/gltf-binary",
            _ => "application/octet-stream",
        }
    }
}

pub mod glb;
pub mod spz;

/// One Gaussian in world units.
struct World<'a> {
    mean: [f32; 3],
    log_scale: [f32; 3],
    /// As the model holds it: `w x y z`, not necessarily of unit length.
    rotation: [f32; 4],
    opacity_logit: f32,
    sh_dc: [f32; 3],
    /// `[(k-1) x 3]`: coefficient by coefficient, the channels inner.
    sh_rest: &'a [f32],
}

fn world_all(model: &SplatsModel) -> Vec<World<'_>> {
    (0..model.layout().n).map(|i| world(model, i)).collect()
}

fn world(model: &SplatsModel, i: usize) -> World<'_> {
    let scene = model.scene();
    let g = model.layout().get(model.params(), i);
    let ln = scene.scale.ln();
    World {
        mean: scene.point_to_world(g.mean),
        log_scale: g.log_scale.map(|s| s - ln),
        rotation: g.rotation,
        opacity_logit: g.opacity_logit,
        sh_dc: g.sh_dc,
        sh_rest: g.sh_rest,
    }
}

/// The `.ply` header for `n` Gaussians with `k` SH coefficients per channel.
pub fn ply_header(n: usize, k: usize) -> String {
    let mut h = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    let mut props: Vec<String> =
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].map(String::from).to_vec();
    props.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
    props.push("opacity".into());
    props.extend((0..3).map(|i| format!("scale_{i}")));
    props.extend((0..4).map(|i| format!("rot_{i}")));
    for p in props {
        h.push_str(&format!("property float {p}\n"));
    }
    h.push_str("end_header\n");
    h
}

/// Writes the 3DGS `.ply`.
pub fn write_ply(model: &SplatsModel, mut out: impl Write) -> io::Result<()> {
    let l = model.layout();
    out.write_all(ply_header(l.n, l.k).as_bytes())?;
    let mut row: Vec<f32> = Vec::with_capacity(14 + 3 * l.k);
    for i in 0..l.n {
        let w = world(model, i);
        let g = l.get(model.params(), i);
        row.clear();
        row.extend_from_slice(&w.mean);
        row.extend_from_slice(&[0.0; 3]);
        row.extend_from_slice(&g.sh_dc);
        for c in 0..3 {
            row.extend((1..l.k).map(|j| g.sh_rest[3 * (j - 1) + c]));
        }
        row.push(w.opacity_logit);
        row.extend_from_slice(&w.log_scale);
        row.extend_from_slice(&w.rotation);
        let bytes: Vec<u8> = row.iter().flat_map(|v| v.to_le_bytes()).collect();
        out.write_all(&bytes)?;
    }
    out.flush()
}

/// The bytes of a `.ply` file's size for `n` Gaussians of `k` coefficients.
pub fn ply_len(n: usize, k: usize) -> u64 {
    ply_header(n, k).len() as u64 + (n * (14 + 3 * k) * 4) as u64
}

/// Writes antimatter15's `.splat`.
pub fn write_splat(model: &SplatsModel, mut out: impl Write) -> io::Result<()> {
    let l = model.layout();
    let all = world_all(model);
    // The order antimatter15's converter writes: largest volume times
    // opacity first (a viewer streaming the file draws the big ones first).
    let mut order: Vec<usize> = (0..l.n).collect();
    let weight = |w: &World| (w.log_scale[0] + w.log_scale[1] + w.log_scale[2]).exp() * sigmoid(w.opacity_logit);
    order.sort_by(|&a, &b| weight(&all[b]).total_cmp(&weight(&all[a])).then(a.cmp(&b)));
    let byte = |v: f32| (v * 255.0).round().clamp(0.0, 255.0) as u8;
    let mut buf = Vec::with_capacity(32 * 4096);
    for i in order {
        let w = &all[i];
        let dc = w.sh_dc;
        for v in w.mean.iter().chain(&w.log_scale.map(f32::exp)) {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        for c in 0..3 {
            buf.push(byte(0.5 + SH_C0 * dc[c]));
        }
        buf.push(byte(sigmoid(w.opacity_logit)));
        for q in unit_quat(w.rotation) {
            buf.push((q * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8);
        }
        if buf.len() >= 32 * 4096 {
            out.write_all(&buf)?;
            buf.clear();
        }
    }
    out.write_all(&buf)?;
    out.flush()
}

/// The splats of a model that is splats (`None` for other kinds).
pub fn splats_of(model: &dyn Model) -> Option<&SplatsModel> {
    model.as_any().downcast_ref::<SplatsModel>()
}

/// Writes `model` as `format`.
pub fn write(model: &SplatsModel, format: Format, out: impl Write) -> io::Result<()> {
    match format {
        Format::Ply => write_ply(model, out),
        Format::Splat => write_splat(model, out),
        Format::Spz => spz::write_spz(model, out),
        Format::Glb => glb::write_glb(model, out),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::math::{Aabb, Vec3};
    use crate::engine::geometry::scene::Scene;
    use crate::engine::models::splats::SplatsConfig;
    use crate::engine::models::splats::gaussians::Layout;

    fn model() -> SplatsModel {
        let scene =
            Scene::from_bounds(Aabb { min: Vec3::new(-2.0, 0.0, 1.0), max: Vec3::new(2.0, 4.0, 3.0) }, 0.0, 10.0);
        let l = Layout::new(3, 1);
        let params: Vec<f32> = (0..l.len()).map(|i| (i as f32 * 0.37).sin()).collect();
        SplatsModel::from_parts(SplatsConfig { sh_degree: 1, ..Default::default() }, scene, params).unwrap()
    }

    #[test]
    fn ply_holds_every_value_in_world_units() {
        let m = model();
        let mut bytes = Vec::new();
        write_ply(&m, &mut bytes).unwrap();
        assert_eq!(bytes.len() as u64, ply_len(3, 4));
        let header = ply_header(3, 4);
        assert!(header.contains("property float f_rest_8\nproperty float opacity\n"), "{header}");
        let floats: Vec<f32> =
            bytes[header.len()..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        let row = 14 + 12;
        let s = m.scene();
        for i in 0..3 {
            let g = m.layout().get(m.params(), i);
            let r = &floats[row * i..row * (i + 1)];
            for c in 0..3 {
                assert!((r[c] - (g.mean[c] / s.scale + s.centre[c])).abs() < 1e-6);
                assert!((r[19 + c] - (g.log_scale[c] - s.scale.ln())).abs() < 1e-6);
                assert_eq!(r[6 + c], g.sh_dc[c]);
                // f_rest: channel c's three coefficients of degree 1.
                for j in 1..4 {
                    assert_eq!(r[9 + 3 * c + (j - 1)], g.sh_rest[3 * (j - 1) + c]);
                }
            }
            assert_eq!(r[18], g.opacity_logit);
            assert_eq!(&r[22..26], &g.rotation);
        }
    }

    #[test]
    fn splat_rows_are_32_bytes_largest_first() {
        let m = model();
        let mut bytes = Vec::new();
        write_splat(&m, &mut bytes).unwrap();
        assert_eq!(bytes.len(), 3 * 32);
        let vol = |r: &[u8]| -> f32 {
            let f = |o: usize| f32::from_le_bytes(r[o..o + 4].try_into().unwrap());
            f(12) * f(16) * f(20) * r[27] as f32
        };
        let rows: Vec<&[u8]> = bytes.chunks(32).collect();
        assert!(vol(rows[0]) >= vol(rows[1]) && vol(rows[1]) >= vol(rows[2]));
        for r in rows {
            let q: Vec<f32> = r[28..32].iter().map(|&b| (b as f32 - 128.0) / 128.0).collect();
            let n: f32 = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((n - 1.0).abs() < 0.03, "{q:?}");
        }
    }
}
