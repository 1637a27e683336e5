//! A textured mesh as the files the web and phones read: GLB (glTF 2.0,
//! what `<model-viewer>` and Android's Scene Viewer take) and USDZ (what
//! an iPhone's AR Quick Look takes). Both unlit, their colours the
//! model's: in the GLB `KHR_materials_unlit`, in the USDZ the texture as
//! emission over a black diffuse. The texture is a JPEG, sampled without
//! mipmaps (the atlas pads its triangles for bilinear reads only).

use std::io::{self, Cursor, Write};

use serde_json::json;

use crate::engine::mesh::{Placement, TexturedMesh};
use crate::engine::models::splats::export::glb::write_container;

/// JPEG quality of the texture.
const QUALITY: u8 = 90;

/// The texture as a JPEG.
pub fn texture_jpeg(mesh: &TexturedMesh) -> io::Result<Vec<u8>> {
    let rgb: Vec<u8> = mesh.texture.iter().flatten().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, QUALITY)
        .encode(&rgb, mesh.texture_size, mesh.texture_size, image::ExtendedColorType::Rgb8)
        .map_err(io::Error::other)?;
    Ok(out)
}

/// The mesh's corners where `place` puts them, and their bounds.
fn placed(mesh: &TexturedMesh, place: &Placement) -> (Vec<[f32; 3]>, [f32; 3], [f32; 3]) {
    let corners: Vec<[f32; 3]> =
        mesh.triangles.iter().flatten().map(|&v| place.apply(mesh.positions[v as usize])).collect();
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    for p in &corners {
        (0..3).for_each(|k| (lo[k], hi[k]) = (lo[k].min(p[k]), hi[k].max(p[k])));
    }
    if corners.is_empty() {
        (lo, hi) = ([0.0; 3], [0.0; 3]);
    }
    (corners, lo, hi)
}

/// The mesh as GLB. Three vertices a triangle (each corner its own texture
/// coordinates), quantised to 16 bits (`KHR_mesh_quantization`: positions
/// over the mesh's bounds, undone by the node's scale and translation;
/// texture coordinates normalised), which halves the file.
pub fn glb(mesh: &TexturedMesh, place: &Placement) -> io::Result<Vec<u8>> {
    let (corners, lo, hi) = placed(mesh, place);
    let step = [0, 1, 2].map(|k| if hi[k] > lo[k] { (hi[k] - lo[k]) / 65535.0 } else { 1.0 });
    let mut bin = Vec::with_capacity(corners.len() * 12);
    for p in &corners {
        for k in 0..3 {
            let q = ((p[k] - lo[k]) / step[k]).round().clamp(0.0, 65535.0) as u16;
            bin.extend(q.to_le_bytes());
        }
        bin.extend([0u8; 2]);
    }
    let uv_offset = bin.len();
    for uv in mesh.uvs.iter().flatten() {
        for v in uv {
            bin.extend(((v.clamp(0.0, 1.0) * 65535.0).round() as u16).to_le_bytes());
        }
    }
    let image_offset = bin.len();
    bin.extend(texture_jpeg(mesh)?);
    let image_len = bin.len() - image_offset;
    let n = corners.len();
    let q_max = [0, 1, 2].map(|k| ((hi[k] - lo[k]) / step[k]).round().clamp(0.0, 65535.0));
    let json = json!({
        "asset": {"version": "2.0", "generator": "radiance"},
        "extensionsUsed": ["KHR_mesh_quantization", "KHR_materials_unlit"],
        "extensionsRequired": ["KHR_mesh_quantization"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": lo, "scale": step}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "material": 0, "mode": 4}]}],
        "materials": [{
            "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "extensions": {"KHR_materials_unlit": {}}
        }],
        "textures": [{"sampler": 0, "source": 0}],
        "samplers": [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"bufferView": 2, "mimeType": "image/jpeg"}],
        "accessors": [
            {"bufferView": 0, "componentType": 5123, "count": n, "type": "VEC3", "min": [0, 0, 0], "max": q_max},
            {"bufferView": 1, "componentType": 5123, "normalized": true, "count": n, "type": "VEC2"}
        ],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": uv_offset, "byteStride": 8, "target": 34962},
            {"buffer": 0, "byteOffset": uv_offset, "byteLength": image_offset - uv_offset, "byteStride": 4, "target": 34962},
            {"buffer": 0, "byteOffset": image_offset, "byteLength": image_len}
        ],
        "buffers": [{"byteLength": bin.len()}]
    });
    let mut out = Vec::with_capacity(bin.len() + 4096);
    write_container(&json, &bin, &mut out)?;
    Ok(out)
}

/// A number for USDA text: six significant digits at most, no trailing zeros.
fn num(v: f32) -> String {
    let s = format!("{:.6}", v);
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" { "0".into() } else { s.into() }
}

/// The USD stage (text): the mesh (points shared, texture coordinates a
/// triangle corner each, USD's `st` with v up) bound to a material that
/// shows the texture unlit.
pub fn usda(mesh: &TexturedMesh, place: &Placement, texture: &str) -> String {
    let points: Vec<[f32; 3]> = mesh.positions.iter().map(|p| place.apply(*p)).collect();
    let (_, lo, hi) = placed(mesh, place);
    let mut s = String::with_capacity(64 * mesh.triangles.len() + 4096);
    let tuple = |v: &[f32]| format!("({})", v.iter().map(|x| num(*x)).collect::<Vec<_>>().join(", "));
    s.push_str("#usda 1.0\n(\n    defaultPrim = \"Model\"\n    metersPerUnit = 1\n    upAxis = \"Y\"\n)\n\n");
    s.push_str("def Xform \"Model\" (\n    kind = \"component\"\n)\n{\n");
    s.push_str("    def Mesh \"Mesh\" (\n        prepend apiSchemas = [\"MaterialBindingAPI\"]\n    )\n    {\n");
    s.push_str("        uniform token subdivisionScheme = \"none\"\n        uniform bool doubleSided = 0\n");
    s.push_str(&format!("        float3[] extent = [{}, {}]\n", tuple(&lo), tuple(&hi)));
    s.push_str("        int[] faceVertexCounts = [");
    s.push_str(&vec!["3"; mesh.triangles.len()].join(", "));
    s.push_str("]\n        int[] faceVertexIndices = [");
    s.push_str(&mesh.triangles.iter().flatten().map(|v| v.to_string()).collect::<Vec<_>>().join(", "));
    s.push_str("]\n        point3f[] points = [");
    s.push_str(&points.iter().map(|p| tuple(p)).collect::<Vec<_>>().join(", "));
    s.push_str("]\n        texCoord2f[] primvars:st = [");
    s.push_str(&mesh.uvs.iter().flatten().map(|uv| tuple(&[uv[0], 1.0 - uv[1]])).collect::<Vec<_>>().join(", "));
    s.push_str("] (\n            interpolation = \"faceVarying\"\n        )\n");
    s.push_str("        rel material:binding = </Model/Materials/Baked>\n    }\n\n");
    s.push_str(&MATERIAL.replace("TEXTURE", texture));
    s.push_str("}\n");
    s
}

/// The material: the texture as emission over a black, rough, non-metal
/// surface, so that AR Quick Look's lights leave its colours as they are.
const MATERIAL: &str = r#"    def Scope "Materials"
    {
        def Material "Baked"
        {
            token outputs:surface.connect = </Model/Materials/Baked/Surface.outputs:surface>

            def Shader "Surface"
            {
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor = (0, 0, 0)
                color3f inputs:emissiveColor.connect = </Model/Materials/Baked/Texture.outputs:rgb>
                float inputs:roughness = 1
                float inputs:metallic = 0
                token outputs:surface
            }

            def Shader "Texture"
            {
                uniform token info:id = "UsdUVTexture"
                asset inputs:file = @TEXTURE@
                float2 inputs:st.connect = </Model/Materials/Baked/StReader.outputs:result>
                token inputs:sourceColorSpace = "sRGB"
                token inputs:wrapS = "clamp"
                token inputs:wrapT = "clamp"
                float3 outputs:rgb
            }

            def Shader "StReader"
            {
                uniform token info:id = "UsdPrimvarReader_float2"
                string inputs:varname = "st"
                float2 outputs:result
            }
        }
    }
"#;

/// The mesh as USDZ: an uncompressed zip whose first file is the stage
/// and each file's data on a 64-byte boundary (the USDZ rules).
pub fn usdz(mesh: &TexturedMesh, place: &Placement) -> io::Result<Vec<u8>> {
    let stage = usda(mesh, place, "texture.jpg");
    let jpeg = texture_jpeg(mesh)?;
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .with_alignment(64)
        .large_file(false);
    for (name, bytes) in [("model.usda", stage.as_bytes()), ("texture.jpg", jpeg.as_slice())] {
        zip.start_file(name, options).map_err(io::Error::other)?;
        zip.write_all(bytes)?;
    }
    Ok(zip.finish().map_err(io::Error::other)?.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    /// Two triangles of a unit square in the world's x-z plane (z up), and
    /// a 64-texel texture with a gradient.
    fn square() -> (TexturedMesh, Placement) {
        let mesh = TexturedMesh {
            positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 2.0], [0.0, 0.0, 2.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            uvs: vec![[[0.1, 0.2], [0.3, 0.2], [0.1, 0.4]], [[0.9, 0.8], [0.7, 0.8], [0.9, 0.6]]],
            texture: (0..64 * 64).map(|i| [(i % 64) as f32 / 63.0, (i / 64) as f32 / 63.0, 0.5]).collect(),
            texture_size: 64,
        };
        let crop = crate::engine::models::splats::crop::CropBox {
            centre: [0.5, 0.0, 1.0],
            axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            half: [1.0; 3],
        };
        let place = Placement::new(&mesh, &crop, Some([0.0, -1.0, 0.0]), 0.5);
        (mesh, place)
    }

    #[test]
    fn placement_stands_the_mesh_upright_on_the_origin_at_its_size() {
        let (mesh, place) = square();
        let out: Vec<[f32; 3]> = mesh.positions.iter().map(|p| place.apply(*p)).collect();
        // World z (up) is y; the longest side (2 along z) is 0.5 m; it stands on y = 0.
        let ys: Vec<f32> = out.iter().map(|p| p[1]).collect();
        assert!(
            (ys.iter().cloned().fold(f32::MIN, f32::max) - 0.5).abs() < 1e-6
                && ys.iter().cloned().fold(f32::MAX, f32::min).abs() < 1e-6
        );
        // Front (world -y) is +z: the square lies in the plane z = 0, centred on x.
        assert!(out.iter().all(|p| p[2].abs() < 1e-6));
        assert!((out[0][0] + out[1][0]).abs() < 1e-6 && (out[0][0] - out[1][0]).abs() > 0.2);
    }

    #[test]
    fn the_glb_holds_the_mesh_quantised_and_the_texture() {
        let (mesh, place) = square();
        let bytes = glb(&mesh, &place).unwrap();
        assert_eq!(&bytes[..4], b"glTF");
        let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let json: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
        let bin = &bytes[20 + json_len + 8..];
        let (t, s) = (&json["nodes"][0]["translation"], &json["nodes"][0]["scale"]);
        let f = |v: &serde_json::Value, k: usize| v[k].as_f64().unwrap() as f32;
        for (c, &v) in mesh.triangles.iter().flatten().enumerate() {
            let want = place.apply(mesh.positions[v as usize]);
            for k in 0..3 {
                let q = u16::from_le_bytes(bin[c * 8 + 2 * k..c * 8 + 2 * k + 2].try_into().unwrap());
                let got = f(t, k) + q as f32 * f(s, k);
                assert!((got - want[k]).abs() < 1e-5, "corner {c} axis {k}: {got} against {}", want[k]);
            }
        }
        let uv_at = json["bufferViews"][1]["byteOffset"].as_u64().unwrap() as usize;
        for (c, uv) in mesh.uvs.iter().flatten().enumerate() {
            for k in 0..2 {
                let q = u16::from_le_bytes(bin[uv_at + c * 4 + 2 * k..uv_at + c * 4 + 2 * k + 2].try_into().unwrap());
                assert!((q as f32 / 65535.0 - uv[k]).abs() < 1e-4);
            }
        }
        let img = &json["bufferViews"][2];
        let (o, n) = (img["byteOffset"].as_u64().unwrap() as usize, img["byteLength"].as_u64().unwrap() as usize);
        let decoded = image::load_from_memory(&bin[o..o + n]).unwrap().to_rgb8();
        assert_eq!(decoded.dimensions(), (64, 64));
        assert!(
            (decoded.get_pixel(63, 0)[0] as i32 - 255).abs() < 8
                && (decoded.get_pixel(0, 63)[1] as i32 - 255).abs() < 8
        );
    }

    #[test]
    fn the_usdz_is_stored_aligned_and_starts_with_the_stage() {
        let (mesh, place) = square();
        let bytes = usdz(&mesh, &place).unwrap();
        let mut zip = zip::ZipArchive::new(Cursor::new(&bytes)).unwrap();
        assert_eq!(zip.len(), 2);
        let mut names = Vec::new();
        for i in 0..zip.len() {
            let mut f = zip.by_index(i).unwrap();
            assert_eq!(f.compression(), zip::CompressionMethod::Stored);
            let name = f.name().unwrap().to_string();
            assert_eq!(f.data_start().unwrap() % 64, 0, "{name} is not on 64 bytes");
            names.push(name);
            let mut body = Vec::new();
            f.read_to_end(&mut body).unwrap();
            if i == 0 {
                let text = String::from_utf8(body).unwrap();
                assert!(text.starts_with("#usda 1.0"));
                assert!(text.contains("int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]"));
                // st is v up: the first corner's (0.1, 0.2) is (0.1, 0.8).
                assert!(text.contains("texCoord2f[] primvars:st = [(0.1, 0.8), "), "{text}");
                assert!(text.contains("@texture.jpg@"));
            }
        }
        assert_eq!(names, ["model.usda", "texture.jpg"]);
        assert_eq!(num(0.1), "0.1");
        assert_eq!(num(-0.0000001), "0");
        assert_eq!(num(2.0), "2");
    }
}
