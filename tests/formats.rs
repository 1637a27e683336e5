//! The compact splat formats read back by readers that are not ours, run
//! with Node.js from `tools/readers` (installed by `scripts/setup`):
//! - the `.spz` by PlayCanvas's `splat-transform`, every value of every
//!   Gaussian within SPZ's quantisation of what the model holds;
//! - the `.glb` by Khronos' `gltf-validator`, and its values against the
//!   GLB `splat-transform` makes from our `.ply` (so the turn into glTF's
//!   axes is the one the rest of the world uses).

use std::path::{Path, PathBuf};
use std::process::Command;

use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::models::Model;
use radiance::engine::models::splats::SplatsModel;
use radiance::engine::models::splats::cleanup::{CleanupSettings, cleanup};
use radiance::engine::models::splats::export;

fn readers() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/readers/node_modules");
    assert!(dir.is_dir(), "{} is missing: run scripts/setup (npm ci in tools/readers)", dir.display());
    dir
}

fn node(args: &[&str]) -> String {
    let out = Command::new("node").args(args).output().expect("node (Node.js 20 or later)");
    assert!(out.status.success(), "node {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

fn splat_transform(args: &[&str]) {
    let cli = readers().join("@playcanvas/splat-transform/bin/cli.mjs");
    let mut all = vec![cli.to_str().unwrap(), "-q", "-w"];
    all.extend_from_slice(args);
    node(&all);
}

/// One Gaussian in world units, as the `.ply` holds it.
struct G {
    mean: [f32; 3],
    log_scale: [f32; 3],
    rot: [f32; 4],
    opacity: f32,
    dc: [f32; 3],
    /// `[(k-1) x 3]`, channels inner.
    rest: Vec<f32>,
}

fn gaussians(m: &SplatsModel) -> Vec<G> {
    let (l, s) = (m.layout(), m.scene());
    (0..l.n)
        .map(|i| {
            let g = l.get(m.params(), i);
            let n = g.rotation.iter().map(|v| v * v).sum::<f32>().sqrt();
            G {
                mean: [0, 1, 2].map(|c| g.mean[c] / s.scale + s.centre[c]),
                log_scale: g.log_scale.map(|v| v - s.scale.ln()),
                rot: g.rotation.map(|v| v / n),
                opacity: 1.0 / (1.0 + (-g.opacity_logit).exp()),
                dc: g.sh_dc,
                rest: g.sh_rest.to_vec(),
            }
        })
        .collect()
}

/// A baked model of SH degree 3 and its exports.
struct Baked {
    _dir: tempfile::TempDir,
    model: SplatsModel,
    ply: String,
    spz: String,
    glb: String,
    dir: PathBuf,
}

/// The ball scene written to `dir/scene` and an `instant-tiny` field trained
/// on it for `steps` steps as `dir/m.ckpt`: the scene's folder and the
/// checkpoint's path.
fn trained_ball(dir: &Path, steps: u32) -> (String, String) {
    let ds = dir.join("scene");
    BallScene { size: 32, views: 12, ..Default::default() }.write_blender(&ds).unwrap();
    let (data, ckpt) = (ds.to_string_lossy().into_owned(), dir.join("m.ckpt").to_string_lossy().into_owned());
    let steps = steps.to_string();
    let args =
        ["train", "--data", &data, "--model", "instant-tiny", "--steps", &steps, "--out", &ckpt, "--threads", "2"];
    let out = Command::new(env!("CARGO_BIN_EXE_radiance")).args(args).output().unwrap();
    assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    (data, ckpt)
}

fn baked() -> Baked {
    let dir = tempfile::tempdir().unwrap();
    let (data, _) = trained_ball(dir.path(), 200);
    let bin = env!("CARGO_BIN_EXE_radiance");
    let run = |args: &[&str]| {
        let out = Command::new(bin).args(args).output().unwrap();
        assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    };
    let p = |f: &str| dir.path().join(f).to_string_lossy().into_owned();
    run(&[
        "bake",
        "--model",
        &p("m.ckpt"),
        "--data",
        &data,
        "--out",
        &p("s.ckpt"),
        "--steps",
        "20",
        "--sh-degree",
        "3",
    ]);
    for f in ["ply", "spz", "glb"] {
        run(&["export", "--model", &p("s.ckpt"), "--format", f, "--out", &p(&format!("s.{f}"))]);
    }
    // The cleanup says what it removed; a bad threshold is refused by name
    // and writes nothing.
    let out = Command::new(bin)
        .args(["export", "--model", &p("s.ckpt"), "--format", "spz", "--out", &p("again.spz")])
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("cleanup: "), "{}", String::from_utf8_lossy(&out.stderr));
    let out = Command::new(bin)
        .args(["export", "--model", &p("s.ckpt"), "--format", "spz", "--out", &p("bad.spz"), "--min-opacity", "2"])
        .output()
        .unwrap();
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("--min-opacity"));
    assert!(!dir.path().join("bad.spz").exists());
    let restored = radiance::engine::train::persist::load(Path::new(&p("s.ckpt"))).unwrap();
    let s = export::splats_of(&*restored.model).expect("splats");
    // What export writes by default: the splats after the floater cleanup.
    let (model, _) = cleanup(s, &CleanupSettings::default()).unwrap();
    assert_eq!(model.config.sh_degree, 3);
    Baked { model, ply: p("s.ply"), spz: p("s.spz"), glb: p("s.glb"), dir: dir.path().to_path_buf(), _dir: dir }
}

/// `export --crop`: `auto` finds the box from the training cameras (the
/// ball's ring) and keeps the ball; a box file is checked by field, and a
/// box that keeps nothing is an error; neither writes a file.
#[test]
fn export_crops_to_the_automatic_box_or_a_given_one() {
    let b = baked();
    let bin = env!("CARGO_BIN_EXE_radiance");
    let (ckpt, data) = (b.dir.join("s.ckpt"), b.dir.join("scene"));
    let export = |extra: &[&str], out: &str| {
        let mut args = vec!["export", "--model", ckpt.to_str().unwrap(), "--format", "spz"];
        args.extend_from_slice(&["--out", out]);
        args.extend_from_slice(extra);
        Command::new(bin).args(&args).output().unwrap()
    };
    let out_path = b.dir.join("crop.spz");
    let o = export(&["--crop", "auto", "--data", data.to_str().unwrap()], out_path.to_str().unwrap());
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "{stderr}");
    // The box it printed, applied here, keeps what the file holds.
    let line = stderr.lines().find(|l| l.starts_with("crop: {")).expect("the box printed");
    let bx: radiance::engine::models::splats::crop::CropBox = serde_json::from_str(&line[6..]).unwrap();
    let (kept, _) = radiance::engine::models::splats::crop::crop(&b.model, &bx).unwrap();
    let read = export::spz::read_spz(&std::fs::read(&out_path).unwrap(), 1 << 20).unwrap();
    assert_eq!(read.means.len(), kept.layout().n);
    assert!(kept.layout().n > b.model.layout().n / 2, "the ball is most of the splats: {stderr}");
    let write = |name: &str, json: &str| {
        let p = b.dir.join(name);
        std::fs::write(&p, json).unwrap();
        p.to_string_lossy().into_owned()
    };
    let nothing =
        write("far.json", r#"{"centre": [100, 100, 100], "axes": [[1,0,0],[0,1,0],[0,0,1]], "half": [1, 1, 1]}"#);
    let flat = write("flat.json", r#"{"centre": [0, 0, 0], "axes": [[1,0,0],[0,1,0],[0,0,1]], "half": [1, 0, 1]}"#);
    for (json, says) in [(nothing, "keeps none"), (flat, "half")] {
        let out = b.dir.join("bad.spz");
        let o = export(&["--crop", &json], out.to_str().unwrap());
        assert!(
            !o.status.success() && String::from_utf8_lossy(&o.stderr).contains(says),
            "{}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(!out.exists());
    }
}

#[test]
fn the_spz_reads_back_in_splat_transform() {
    let b = baked();
    let want = gaussians(&b.model);
    let csv = b.dir.join("spz.csv");
    splat_transform(&[&b.spz, csv.to_str().unwrap()]);
    let text = std::fs::read_to_string(&csv).unwrap();
    let mut lines = text.lines();
    let names: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| names.iter().position(|&m| m == n).unwrap_or_else(|| panic!("no column {n} in {names:?}"));
    let rows: Vec<Vec<f32>> = lines.map(|l| l.split(',').map(|v| v.parse().unwrap()).collect()).collect();
    assert_eq!(rows.len(), want.len(), "every Gaussian");
    assert_eq!(names.iter().filter(|n| n.starts_with("f_rest_")).count(), 45, "SH degree 3");
    let reach = want.iter().flat_map(|g| g.mean).fold(0f32, |a, v| a.max(v.abs()));
    let step = reach / (1 << 16) as f32;
    let sig = |x: f32| 1.0 / (1.0 + (-x).exp());
    let mut used = vec![false; want.len()];
    for r in &rows {
        let p = [r[col("x")], r[col("y")], r[col("z")]];
        // The file is in its own order: the Gaussian nearest each row.
        let d2 = |g: &G| (0..3).map(|c| (g.mean[c] - p[c]).powi(2)).sum::<f32>();
        let (i, g) = want.iter().enumerate().min_by(|a, b| d2(a.1).total_cmp(&d2(b.1))).unwrap();
        assert!(!used[i], "two rows for Gaussian {i}");
        used[i] = true;
        for c in 0..3 {
            assert!((p[c] - g.mean[c]).abs() <= step, "position {c}: {} for {}", p[c], g.mean[c]);
            let s = g.log_scale[c].clamp(-10.0, 255.0 / 16.0 - 10.0);
            assert!((r[col(&format!("scale_{c}"))] - s).abs() <= 1.0 / 32.0 + 1e-5, "scale");
            let dc = g.dc[c].clamp(-0.5 / 0.15, 0.5 / 0.15);
            assert!((r[col(&format!("f_dc_{c}"))] - dc).abs() <= 0.5 / (255.0 * 0.15) + 1e-4, "colour");
            // f_rest is channel by channel in the reader's table.
            for j in 1..16 {
                let v = g.rest[3 * (j - 1) + c].clamp(-1.0, 127.0 / 128.0);
                let got = r[col(&format!("f_rest_{}", 15 * c + j - 1))];
                let bucket = if j < 4 { 8.0 } else { 16.0 };
                assert!((got - v).abs() <= bucket / 256.0 + 1.0 / 256.0, "SH {j} channel {c}: {got} for {v}");
            }
        }
        assert!((sig(r[col("opacity")]) - g.opacity).abs() <= 0.5 / 255.0 + 1e-5, "opacity");
        let q = [0, 1, 2, 3].map(|c| r[col(&format!("rot_{c}"))]);
        let dot: f32 = (0..4).map(|c| q[c] * g.rot[c]).sum();
        assert!(dot.abs() > 0.999, "rotation {q:?} for {:?}", g.rot);
    }
    let ply = std::fs::metadata(&b.ply).unwrap().len();
    let spz = std::fs::metadata(&b.spz).unwrap().len();
    assert!(spz * 5 < ply, "SPZ {spz} bytes, the .ply {ply}");
}

/// A GLB's attributes by name: (components, values as f32).
fn glb_attributes(path: &str) -> (serde_json::Value, Vec<(String, usize, Vec<f32>)>) {
    let b = std::fs::read(path).unwrap();
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap()) as usize;
    assert_eq!(&b[0..4], b"glTF");
    assert_eq!(u32_at(8), b.len(), "the header's length");
    let jl = u32_at(12);
    assert_eq!(&b[16..20], b"JSON");
    let json: serde_json::Value = serde_json::from_slice(&b[20..20 + jl]).unwrap();
    let bin = &b[20 + jl + 8..];
    assert_eq!(&b[20 + jl + 4..20 + jl + 8], b"BIN\0");
    let mut out = Vec::new();
    for (name, a) in json["meshes"][0]["primitives"][0]["attributes"].as_object().unwrap() {
        let acc = &json["accessors"][a.as_u64().unwrap() as usize];
        let view = &json["bufferViews"][acc["bufferView"].as_u64().unwrap() as usize];
        let (o, len) = (view["byteOffset"].as_u64().unwrap() as usize, view["byteLength"].as_u64().unwrap() as usize);
        let width = match acc["type"].as_str().unwrap() {
            "SCALAR" => 1,
            "VEC3" => 3,
            _ => 4,
        };
        let data = &bin[o..o + len];
        let values: Vec<f32> = match acc["componentType"].as_u64().unwrap() {
            5126 => data.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect(),
            5121 => data.iter().map(|&v| v as f32 / 255.0).collect(),
            t => panic!("component type {t}"),
        };
        assert_eq!(values.len(), width * acc["count"].as_u64().unwrap() as usize);
        out.push((name.clone(), width, values));
    }
    (json, out)
}

/// `R diag(s^2) R^T` of a quaternion `x y z w` and linear scales.
fn covariance(q: &[f32], s: &[f32]) -> [[f32; 3]; 3] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    let [x, y, z, w] = [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
    let r = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| r[i][k] * s[k] * s[k] * r[j][k]).sum();
        }
    }
    c
}

#[test]
fn the_glb_passes_the_khronos_validator_and_matches_splat_transform() {
    let b = baked();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/readers/validate-gltf.mjs");
    readers();
    let issues: serde_json::Value = serde_json::from_str(&node(&[script.to_str().unwrap(), &b.glb])).unwrap();
    // The validator (2.0.0-dev.3.10) predates the extension's ratification
    // and calls each of its attributes (`KHR_gaussian_splatting:...`) an
    // invalid name (KhronosGroup/glTF-Validator#252): those errors, and
    // only those, are expected; no other error and no warning.
    let messages = issues["messages"].as_array().unwrap();
    let (mut named, mut other) = (0, Vec::new());
    for m in messages {
        let (code, pointer, severity) =
            (m["code"].as_str().unwrap(), m["pointer"].as_str().unwrap_or(""), m["severity"].as_u64().unwrap());
        if code == "MESH_PRIMITIVE_INVALID_ATTRIBUTE"
            && pointer.starts_with("/meshes/0/primitives/0/attributes/KHR_gaussian_splatting:")
        {
            named += 1;
        } else if severity <= 1 {
            other.push(m.clone());
        }
    }
    assert!(other.is_empty(), "validator errors or warnings: {other:?}");
    assert_eq!(named, 4 + 15, "rotation, scale, opacity, the 16 SH coefficients less none: {messages:?}");
    assert_eq!(issues["numErrors"].as_u64().unwrap(), named);

    let theirs_path = b.dir.join("theirs.glb");
    splat_transform(&[&b.ply, theirs_path.to_str().unwrap()]);
    let (json, ours) = glb_attributes(&b.glb);
    let (_, theirs) = glb_attributes(theirs_path.to_str().unwrap());
    let prim = &json["meshes"][0]["primitives"][0];
    assert_eq!(prim["mode"], 0, "points");
    assert_eq!(prim["extensions"]["KHR_gaussian_splatting"]["kernel"], "ellipse");
    assert_eq!(json["extensionsUsed"][0], "KHR_gaussian_splatting");
    let get = |set: &[(String, usize, Vec<f32>)], n: &str| -> Vec<f32> {
        set.iter().find(|a| a.0 == n).unwrap_or_else(|| panic!("no attribute {n}")).2.clone()
    };
    let n = b.model.layout().n;
    // Every attribute theirs has, ours has, with the same values (the
    // rotation compared by the covariance it gives: a half turn can be
    // written as two quaternions that shape every Gaussian alike; COLOR_0
    // below, since theirs skips glTF's sRGB-to-linear step).
    for (name, width, t) in &theirs {
        let o = get(&ours, name);
        assert_eq!(o.len(), t.len(), "{name}");
        match name.as_str() {
            "COLOR_0" | "KHR_gaussian_splatting:ROTATION" => {}
            _ => {
                for (i, (a, b)) in o.iter().zip(t).enumerate() {
                    assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{name}[{}] ({width}): {a} for {b}", i / width);
                }
            }
        }
    }
    let (oq, tq, s) = (
        get(&ours, "KHR_gaussian_splatting:ROTATION"),
        get(&theirs, "KHR_gaussian_splatting:ROTATION"),
        get(&ours, "KHR_gaussian_splatting:SCALE"),
    );
    for i in 0..n {
        let (a, b) = (
            covariance(&oq[4 * i..4 * i + 4], &s[3 * i..3 * i + 3]),
            covariance(&tq[4 * i..4 * i + 4], &s[3 * i..3 * i + 3]),
        );
        let big = a.iter().flatten().fold(0f32, |m, v| m.max(v.abs()));
        for r in 0..3 {
            for c in 0..3 {
                assert!((a[r][c] - b[r][c]).abs() <= 1e-4 * big, "covariance of {i}: {a:?} against {b:?}");
            }
        }
    }
    // COLOR_0: the DC colour decoded to linear, and the opacity.
    let want = gaussians(&b.model);
    let colour = get(&ours, "COLOR_0");
    for (i, g) in want.iter().enumerate() {
        for c in 0..3 {
            let srgb = (0.5 + 0.282_094_8 * g.dc[c]).clamp(0.0, 1.0);
            let lin = if srgb <= 0.04045 { srgb / 12.92 } else { ((srgb + 0.055) / 1.055).powf(2.4) };
            assert!((colour[4 * i + c] - lin).abs() <= 0.5 / 255.0 + 1e-6, "COLOR_0");
        }
        assert!((colour[4 * i + 3] - g.opacity).abs() <= 0.5 / 255.0 + 1e-6, "COLOR_0's alpha");
    }
}

/// A field trained briefly on the ball scene, as a mesh through
/// `radiance mesh`: the GLB passes Khronos' validator with no error or
/// warning, the USDZ USD's own validators, and the mesh scores near the
/// model at the held-out views; bad options are refused by name and write
/// nothing.
#[test]
fn the_mesh_passes_gltf_validator_and_usd_and_looks_like_its_model() {
    let dir = tempfile::tempdir().unwrap();
    let (data, model) = trained_ball(dir.path(), 300);
    let bin = env!("CARGO_BIN_EXE_radiance");
    let p = |f: &str| dir.path().join(f).to_string_lossy().into_owned();
    let run = |args: &[&str]| Command::new(bin).args(args).output().unwrap();
    let small = ["--triangles", "4000", "--texture", "256", "--resolution", "48", "--views", "16", "--view-size", "64"];
    let mesh = |out: &str, extra: &[&str]| {
        let mut args = vec!["mesh", "--model", &model, "--threads", "2"];
        args.extend(["--out", out]);
        args.extend(small);
        args.extend(extra);
        run(&args)
    };
    let glb = p("m.glb");
    let out = mesh(&glb, &["--data", &data, "--eval"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report = String::from_utf8_lossy(&out.stdout);
    let last = report.lines().last().unwrap();
    let db =
        |what: &str| -> f64 { last.split(what).nth(1).unwrap().split_whitespace().next().unwrap().parse().unwrap() };
    let (ours, theirs) = (db("mesh "), db("model "));
    assert!(ours > theirs - 3.0 && ours > 18.0, "{report}");

    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/readers/validate-gltf.mjs");
    readers();
    let issues: serde_json::Value = serde_json::from_str(&node(&[script.to_str().unwrap(), &glb])).unwrap();
    let bad: Vec<_> =
        issues["messages"].as_array().unwrap().iter().filter(|m| m["severity"].as_u64().unwrap() <= 1).collect();
    assert!(bad.is_empty(), "validator errors or warnings: {bad:?}");
    assert_eq!(issues["numErrors"].as_u64(), Some(0));

    // This one inside the automatic crop: the box around what the field draws
    // solid in nearly every training camera's frame.
    let usdz = p("m.usdz");
    let out = mesh(&usdz, &["--crop", "auto", "--data", &data]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("crop: {\"centre\""), "{err}");
    let check = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/readers/check-usdz.py");
    let out = Command::new("python3").arg(&check).arg(&usdz).output().expect("python3 with usd-core (scripts/setup)");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|_| panic!("check-usdz.py: {}", String::from_utf8_lossy(&out.stderr)));
    assert!(out.status.success(), "USD finds problems: {report}");
    assert_eq!(report["files"], serde_json::json!(["model.usdc", "texture.jpg"]));
    assert_eq!((report["meshes"].as_u64(), report["textured"].as_u64()), (Some(1), Some(1)), "{report}");
    assert_eq!((report["up"].as_str(), report["metersPerUnit"].as_f64()), (Some("Y"), Some(1.0)));
    let tris = report["triangles"].as_u64().unwrap();
    assert!((200..=4000).contains(&tris), "{tris} triangles");

    // Bad options and a crop that keeps nothing: refused by name, nothing written.
    std::fs::write(
        p("far.json"),
        r#"{"centre": [50, 50, 50], "axes": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "half": [0.1, 0.1, 0.1]}"#,
    )
    .unwrap();
    for (extra, says) in [
        (vec!["--triangles", "0"], "triangles"),
        (vec!["--triangles", "100000000"], "triangles"),
        (vec!["--texture", "16"], "texture"),
        (vec!["--crop", &p("far.json")], "no surface inside the crop box"),
    ] {
        let out_path = p("bad.glb");
        let mut args = vec![
            "mesh",
            "--model",
            &model,
            "--out",
            &out_path,
            "--resolution",
            "32",
            "--views",
            "4",
            "--view-size",
            "32",
        ];
        args.extend(extra.iter().copied());
        let out = run(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(says), "{extra:?}: {err}");
        assert!(!Path::new(&out_path).exists(), "{extra:?} wrote a file");
    }
    let out = run(&["mesh", "--model", &p("m.ckpt"), "--out", &p("m.obj")]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains(".glb or a .usdz"));
}

/// A mesh of a few thousand triangles, odd coordinates and all, as USDZ:
/// USD itself reads back every point, index, count and texture
/// coordinate exactly as written (the stage is our own binary writer's).
#[test]
fn usd_reads_back_every_value_of_the_usdz() {
    use radiance::engine::front::{CropBox, Placement, TexturedMesh, mesh_usdz};
    let mut seed = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 40) as f32 / (1u64 << 24) as f32
    };
    let positions: Vec<[f32; 3]> = (0..2500).map(|_| [next() * 3.0 - 1.0, next() * 1e-3, next() * 7.0]).collect();
    // Indices of every size, so that each of the integer coding's widths is used.
    let triangles: Vec<[u32; 3]> =
        (0..4000u32).map(|t| [t % 2500, (t * 7919 + 13) % 2500, ((next() * 2499.0) as u32 + t) % 2500]).collect();
    let uvs: Vec<[[f32; 2]; 3]> =
        triangles.iter().map(|_| [[next(), next()], [next(), next()], [next(), next()]]).collect();
    let mesh = TexturedMesh { positions, triangles, uvs, texture: vec![[0.5, 0.2, 0.9]; 64 * 64], texture_size: 64 };
    let crop = CropBox {
        centre: [0.5, 0.0, 2.5],
        axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        half: [2.0, 1.0, 4.0],
    };
    let place = Placement::new(&mesh, &crop, Some([0.0, -1.0, 0.0]), 0.5);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.usdz");
    std::fs::write(&path, mesh_usdz(&mesh, &place).unwrap()).unwrap();

    let check = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/readers/check-usdz.py");
    let out = Command::new("python3").arg(&check).arg(&path).arg("--arrays").output().expect("python3 with usd-core");
    let report: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|_| panic!("check-usdz.py: {}", String::from_utf8_lossy(&out.stderr)));
    assert!(out.status.success(), "USD finds problems: {}", report["problems"]);
    assert_eq!(report["files"], serde_json::json!(["model.usdc", "texture.jpg"]));
    let a = &report["arrays"];
    let f32s = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array()
            .unwrap()
            .iter()
            .flat_map(|p| p.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32))
            .collect()
    };
    let ints =
        |v: &serde_json::Value| -> Vec<i64> { v.as_array().unwrap().iter().map(|x| x.as_i64().unwrap()).collect() };
    let want_points: Vec<f32> = mesh.positions.iter().flat_map(|p| place.apply(*p)).collect();
    assert_eq!(f32s(&a["points"]), want_points, "points");
    assert_eq!(ints(&a["faceVertexCounts"]), vec![3; 4000]);
    let want_indices: Vec<i64> = mesh.triangles.iter().flatten().map(|&v| v as i64).collect();
    assert_eq!(ints(&a["faceVertexIndices"]), want_indices, "faceVertexIndices");
    let want_st: Vec<f32> = mesh.uvs.iter().flatten().flat_map(|uv| [uv[0], 1.0 - uv[1]]).collect();
    assert_eq!(f32s(&a["st"]), want_st, "st (v up)");
    assert_eq!(a["interpolation"], "faceVarying");
    assert_eq!(a["texture"], serde_json::json!(["texture.jpg"]));
    let extent = f32s(&a["extent"]);
    for k in 0..3 {
        let axis = want_points.iter().skip(k).step_by(3);
        let (lo, hi) = axis.fold((f32::MAX, f32::MIN), |(l, h), &x| (l.min(x), h.max(x)));
        assert_eq!((extent[k], extent[3 + k]), (lo, hi), "extent along axis {k}");
    }
}
