//! A textured mesh as the files the web and phones read: GLB (glTF 2.0,
//! what `<model-viewer>` and Android's Scene Viewer take) and USDZ (what
//! an iPhone's AR Quick Look takes). Both unlit, their colours the
//! model's: in the GLB `KHR_materials_unlit`, in the USDZ the texture as
//! emission over a black diffuse. The texture is a JPEG, sampled without
//! mipmaps (the atlas pads its triangles for bilinear reads only).

use std::io::{self, Cursor, Write};

use serde_json::json;

use crate::engine::mesh::usdc::{self, Spec, SpecKind, Value};
use crate::engine::mesh::{Placement, TexturedMesh};
use crate::engine::models::splats::export::glb::write_container;

/// JPEG quality of the texture: low enough to keep a 200k-triangle mesh's
/// GLB under 10 MB, at a loss too small to see (docs/design/mesh.md).
const QUALITY: u8 = 85;

/// The texture as a JPEG.
pub fn texture_jpeg(mesh: &TexturedMesh) -> io::Result<Vec<u8>> {
    let rgb: Vec<u8> = mesh.texture.iter().flatten().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect();
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, QUALITY)
        .encode(&rgb, mesh.texture_size, mesh.texture_size, image::ExtendedColorType::Rgb8)
        .map_err(io::Error::other)?;
    Ok(out)
}

/// The mesh with its texture as the files hold it (the JPEG decoded), so
/// that a score of the mesh counts what the compression loses.
pub fn as_written(mesh: &TexturedMesh) -> io::Result<TexturedMesh> {
    let jpeg = texture_jpeg(mesh)?;
    let decoded = image::load_from_memory(&jpeg).map_err(io::Error::other)?.to_rgb8();
    let texture = decoded.pixels().map(|p| p.0.map(|v| v as f32 / 255.0)).collect();
    Ok(TexturedMesh { texture, ..mesh.clone() })
}

/// The bounds of `points` (zeros for none).
fn bounds(points: impl IntoIterator<Item = [f32; 3]>) -> ([f32; 3], [f32; 3]) {
    let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
    let mut any = false;
    for p in points {
        (0..3).for_each(|k| (lo[k], hi[k]) = (lo[k].min(p[k]), hi[k].max(p[k])));
        any = true;
    }
    if any { (lo, hi) } else { ([0.0; 3], [0.0; 3]) }
}

/// The mesh's corners where `place` puts them, and their bounds.
fn placed(mesh: &TexturedMesh, place: &Placement) -> (Vec<[f32; 3]>, [f32; 3], [f32; 3]) {
    let corners: Vec<[f32; 3]> =
        mesh.triangles.iter().flatten().map(|&v| place.apply(mesh.positions[v as usize])).collect();
    let (lo, hi) = bounds(corners.iter().copied());
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

/// A prim: `def`, its type, its fields, its children's names and its
/// properties' names.
fn prim(path: &str, type_name: &str, extra: Vec<(&'static str, Value)>, children: &[&str], props: &[&str]) -> Spec {
    let names = |v: &[&str]| Value::Tokens(v.iter().map(|s| s.to_string()).collect());
    let mut fields = vec![("specifier", Value::Def), ("typeName", Value::Token(type_name.into()))];
    fields.extend(extra);
    if !children.is_empty() {
        fields.push(("primChildren", names(children)));
    }
    if !props.is_empty() {
        fields.push(("properties", names(props)));
    }
    Spec { path: path.into(), kind: SpecKind::Prim, fields }
}

/// An attribute of type `type_name` (`uniform` or varying) and its fields
/// (a `default` value, a `connectionPaths` source, metadata).
fn attr(path: &str, type_name: &str, uniform: bool, extra: Vec<(&'static str, Value)>) -> Spec {
    let mut fields = vec![
        ("custom", Value::Bool(false)),
        ("typeName", Value::Token(type_name.into())),
        ("variability", Value::Uniform(uniform)),
    ];
    fields.extend(extra);
    Spec { path: path.into(), kind: SpecKind::Attribute, fields }
}

fn token(t: &str) -> Value {
    Value::Token(t.into())
}

/// A shader's (or material's) input or output: a value, a connection to
/// another's output, or neither (an output).
enum Port<'a> {
    Set(Value),
    From(&'a str),
    Out,
}

/// A shader (`id` its `info:id`) or a material, its children and ports
/// (name, type, port).
fn node(path: &str, type_name: &str, id: Option<&str>, children: &[&str], ports: Vec<(&str, &str, Port)>) -> Vec<Spec> {
    let mut names: Vec<&str> = id.map(|_| "info:id").into_iter().collect();
    names.extend(ports.iter().map(|p| p.0));
    let mut specs = vec![prim(path, type_name, vec![], children, &names)];
    if let Some(id) = id {
        specs.push(attr(&format!("{path}.info:id"), "token", true, vec![("default", token(id))]));
    }
    for (name, type_name, port) in ports {
        let fields = match port {
            Port::Set(v) => vec![("default", v)],
            Port::From(source) => vec![("connectionPaths", Value::Paths(vec![source.into()]))],
            Port::Out => vec![],
        };
        specs.push(attr(&format!("{path}.{name}"), type_name, false, fields));
    }
    specs
}

/// The USD stage: `/Model`, y up, in metres, holding the mesh bound to a
/// material that shows the texture `texture` unlit.
pub fn stage(mesh: &TexturedMesh, place: &Placement, texture: &str) -> Vec<Spec> {
    let mut specs = vec![
        Spec {
            path: "/".into(),
            kind: SpecKind::PseudoRoot,
            fields: vec![
                ("defaultPrim", token("Model")),
                ("metersPerUnit", Value::Double(1.0)),
                ("upAxis", token("Y")),
                ("primChildren", Value::Tokens(vec!["Model".into()])),
            ],
        },
        prim("/Model", "Xform", vec![("kind", token("component"))], &["Mesh", "Materials"], &[]),
    ];
    specs.extend(mesh_specs(mesh, place, "/Model/Materials/Baked"));
    specs.extend(material_specs("/Model/Materials/Baked", texture));
    specs
}

/// The mesh: points shared, texture coordinates a triangle corner each
/// (USD's `st`, v up), bound to `material`.
fn mesh_specs(mesh: &TexturedMesh, place: &Placement, material: &str) -> Vec<Spec> {
    let points: Vec<[f32; 3]> = mesh.positions.iter().map(|p| place.apply(*p)).collect();
    // The corners' bounds, as the GLB's.
    let (lo, hi) = bounds(mesh.triangles.iter().flatten().map(|&v| points[v as usize]));
    let m = "/Model/Mesh";
    let array =
        |name: &str, type_name: &str, v: Value| attr(&format!("{m}.{name}"), type_name, false, vec![("default", v)]);
    let props = [
        "subdivisionScheme",
        "doubleSided",
        "extent",
        "faceVertexCounts",
        "faceVertexIndices",
        "points",
        "primvars:st",
        "material:binding",
    ];
    let mut st = array(
        "primvars:st",
        "texCoord2f[]",
        Value::Vec2fs(mesh.uvs.iter().flatten().map(|uv| [uv[0], 1.0 - uv[1]]).collect()),
    );
    st.fields.push(("interpolation", token("faceVarying")));
    vec![
        prim(m, "Mesh", vec![("apiSchemas", Value::PrependTokens(vec!["MaterialBindingAPI".into()]))], &[], &props),
        attr(&format!("{m}.subdivisionScheme"), "token", true, vec![("default", token("none"))]),
        attr(&format!("{m}.doubleSided"), "bool", true, vec![("default", Value::Bool(false))]),
        array("extent", "float3[]", Value::Vec3fs(vec![lo, hi])),
        array("faceVertexCounts", "int[]", Value::Ints(vec![3; mesh.triangles.len()])),
        array("faceVertexIndices", "int[]", Value::Ints(mesh.triangles.iter().flatten().map(|&v| v as i32).collect())),
        array("points", "point3f[]", Value::Vec3fs(points)),
        st,
        Spec {
            path: format!("{m}.material:binding"),
            kind: SpecKind::Relationship,
            fields: vec![("variability", Value::Uniform(true)), ("targetPaths", Value::Paths(vec![material.into()]))],
        },
    ]
}

/// The material at `m`: the texture as emission over a black, rough,
/// non-metal surface, so that AR Quick Look's lights leave its colours as
/// they are.
fn material_specs(m: &str, texture: &str) -> Vec<Spec> {
    let (surface, tex, reader) = (format!("{m}/Surface"), format!("{m}/Texture"), format!("{m}/StReader"));
    let (surface_out, rgb, st) =
        (format!("{surface}.outputs:surface"), format!("{tex}.outputs:rgb"), format!("{reader}.outputs:result"));
    let mut specs = vec![prim("/Model/Materials", "Scope", vec![], &["Baked"], &[])];
    let ports = vec![("outputs:surface", "token", Port::From(&surface_out))];
    specs.extend(node(m, "Material", None, &["Surface", "Texture", "StReader"], ports));
    let ports = vec![
        ("inputs:diffuseColor", "color3f", Port::Set(Value::Vec3f([0.0; 3]))),
        ("inputs:emissiveColor", "color3f", Port::From(&rgb)),
        ("inputs:roughness", "float", Port::Set(Value::Float(1.0))),
        ("inputs:metallic", "float", Port::Set(Value::Float(0.0))),
        ("outputs:surface", "token", Port::Out),
    ];
    specs.extend(node(&surface, "Shader", Some("UsdPreviewSurface"), &[], ports));
    let ports = vec![
        ("inputs:file", "asset", Port::Set(Value::Asset(texture.into()))),
        ("inputs:st", "float2", Port::From(&st)),
        ("inputs:sourceColorSpace", "token", Port::Set(token("sRGB"))),
        ("inputs:wrapS", "token", Port::Set(token("clamp"))),
        ("inputs:wrapT", "token", Port::Set(token("clamp"))),
        ("outputs:rgb", "float3", Port::Out),
    ];
    specs.extend(node(&tex, "Shader", Some("UsdUVTexture"), &[], ports));
    let ports = vec![
        ("inputs:varname", "string", Port::Set(Value::String("st".into()))),
        ("outputs:result", "float2", Port::Out),
    ];
    specs.extend(node(&reader, "Shader", Some("UsdPrimvarReader_float2"), &[], ports));
    specs
}

/// The mesh as USDZ: an uncompressed zip whose first file is the stage
/// (binary USD) and each file's data on a 64-byte boundary (the USDZ rules).
pub fn usdz(mesh: &TexturedMesh, place: &Placement) -> io::Result<Vec<u8>> {
    let stage = usdc::write(&stage(mesh, place, "texture.jpg"));
    let jpeg = texture_jpeg(mesh)?;
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .with_alignment(64)
        .large_file(false);
    for (name, bytes) in [("model.usdc", stage.as_slice()), ("texture.jpg", jpeg.as_slice())] {
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
                assert_eq!(&body[..16], b"PXR-USDC\0\x08\0\0\0\0\0\0", "a crate file of version 0.8.0");
            }
        }
        assert_eq!(names, ["model.usdc", "texture.jpg"]);
    }
}
