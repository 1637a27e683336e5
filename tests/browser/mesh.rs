//! The textured mesh through the API and in the web app: the demo scene
//! (generated) trained briefly, then
//! - `GET /v1/models/{id}/mesh` answers 202 with its progress while it
//!   makes the mesh (another mesh meanwhile: 503), then a GLB; a USDZ,
//!   named and typed, comes from the same mesh at once; bad options are
//!   refused by name;
//! - the viewer's mesh button shows it in `<model-viewer>` (vendored, on
//!   WebGL2: the software renderer here) with its AR button and both files
//!   to download; set to a known camera, its picture matches our own CPU
//!   render of the same mesh (`engine::mesh::raster`, the GLB read back)
//!   at that camera;
//! - the mesh's static site (`format=html`), unzipped and served by a plain
//!   static file server, shows it in model-viewer too.

use std::time::Instant;

use image::RgbImage;
use radiance::engine::front::{Camera, TexturedMesh, render_mesh};
use serde_json::{Value, json};

use crate::common::psnr::rgb8_psnr;
use crate::common::{Svc, assert_error, config};
use crate::realtime::look_at;
use crate::{runtime, screenshot};

/// Our GLB's mesh (`engine::mesh::export::glb`: three corners a triangle,
/// positions as 16-bit steps of the node's scale from its translation,
/// 16-bit normalised texture coordinates, a JPEG texture), read back
/// as a `TexturedMesh` in the file's coordinates.
fn read_glb(glb: &[u8]) -> TexturedMesh {
    let u32_at = |b: &[u8], i: usize| u32::from_le_bytes(b[i..i + 4].try_into().unwrap()) as usize;
    let json_len = u32_at(glb, 12);
    let json: Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let bin = &glb[20 + json_len + 8..];
    let view = |i: usize| {
        let v = &json["bufferViews"][i];
        let start = v["byteOffset"].as_u64().unwrap() as usize;
        &bin[start..start + v["byteLength"].as_u64().unwrap() as usize]
    };
    let floats = |v: &Value| [0, 1, 2].map(|k| v[k].as_f64().unwrap() as f32);
    let node = &json["nodes"][0];
    let (origin, step) = (floats(&node["translation"]), floats(&node["scale"]));
    let n = json["accessors"][0]["count"].as_u64().unwrap() as usize;
    let u16_at = |b: &[u8], i: usize| u16::from_le_bytes([b[i], b[i + 1]]) as f32;
    let (p, t) = (view(0), view(1));
    let positions: Vec<[f32; 3]> =
        (0..n).map(|i| [0, 1, 2].map(|k| origin[k] + step[k] * u16_at(p, 8 * i + 2 * k))).collect();
    let uv = |i: usize| [0, 1].map(|k| u16_at(t, 4 * i + 2 * k) / 65535.0);
    let image = image::load_from_memory_with_format(view(2), image::ImageFormat::Jpeg).unwrap().to_rgb8();
    assert_eq!(image.width(), image.height());
    TexturedMesh {
        triangles: (0..n as u32 / 3).map(|i| [3 * i, 3 * i + 1, 3 * i + 2]).collect(),
        uvs: (0..n / 3).map(|i| [uv(3 * i), uv(3 * i + 1), uv(3 * i + 2)]).collect(),
        texture: image.pixels().map(|p| p.0.map(|c| c as f32 / 255.0)).collect(),
        texture_size: image.width(),
        positions,
    }
}

#[test]
fn a_model_as_a_mesh_through_the_api_and_in_model_viewer_as_our_renderer_draws_it() {
    let _ = tracing_subscriber::fmt().with_env_filter("radiance=warn").with_test_writer().try_init();
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let t0 = Instant::now();
    let train = rt.block_on(svc.trained_demo(1200));
    let id = train["model_id"].as_str().unwrap().to_string();
    println!("trained {id} in {:.1} s", t0.elapsed().as_secs_f64());

    // Bad requests, refused by name before any work.
    rt.block_on(async {
        for (query, field) in [
            ("format=obj", "format"),
            ("texture=8192", "texture"),
            ("texture=16", "texture"),
            ("triangles=0", "triangles"),
            ("triangles=100000000", "triangles"),
        ] {
            let (s, v) = svc.get(&format!("/v1/models/{id}/mesh?{query}")).await;
            assert_eq!(s, 400, "{query}: {v}");
            assert_eq!(v["error"]["details"]["field"], field, "{query}: {v}");
        }
        let (s, v) = svc.get("/v1/models/mdl_none/mesh").await;
        assert_eq!(s, 404, "{v}");
        assert_error(&v, "not_found");
    });

    // A small GLB: being made (202, its progress, asked again as it says),
    // then the file; the USDZ, from the same mesh at once.
    let get = |format: &str, query: &str, probe: bool| {
        rt.block_on(async {
            let t = Instant::now();
            let url = svc.url(&format!("/v1/models/{id}/mesh?format={format}{query}"));
            let mut r = reqwest::get(&url).await.unwrap();
            let mut waits = 0;
            while r.status() == 202 {
                let retry: u64 = r.headers()["retry-after"].to_str().unwrap().parse().unwrap();
                let p: Value = r.json().await.unwrap();
                assert_eq!(p["status"], "making", "{p}");
                assert!((0.0..=1.0).contains(&p["progress"].as_f64().unwrap()) && p["stage"].is_string(), "{p}");
                if probe && waits == 0 {
                    // Another mesh meanwhile: refused until this one is made.
                    let (s, v) = svc.get(&format!("/v1/models/{id}/mesh?triangles=1000")).await;
                    assert_eq!(s, 503, "{v}");
                    assert!(v["error"]["message"].as_str().unwrap().contains("another mesh"), "{v}");
                }
                waits += 1;
                assert!(waits < 300, "the mesh is still being made");
                tokio::time::sleep(std::time::Duration::from_secs(retry.min(2))).await;
                r = reqwest::get(&url).await.unwrap();
            }
            if r.status() != 200 {
                let v: Value = r.json().await.unwrap();
                return Err(v);
            }
            let header = |h: &str| r.headers()[h].to_str().unwrap().to_string();
            assert!(header("content-disposition").ends_with(&format!("{id}.{format}\"")), "{format}");
            let (kind, triangles) = (header("content-type"), header("x-triangles").parse::<usize>().unwrap());
            Ok((kind, triangles, r.bytes().await.unwrap().to_vec(), t.elapsed().as_secs_f64(), waits))
        })
    };
    let small = "&triangles=20000&texture=1024";
    let (kind, triangles, glb, made, waits) = get("glb", small, true).unwrap();
    assert!(waits > 0, "the first request for a mesh did not answer 202 while making it");
    assert_eq!(kind, "model/gltf-binary");
    assert!(glb.starts_with(b"glTF") && (500..=20_000).contains(&triangles), "{triangles} triangles");
    let (kind, again, usdz, kept, waits) = get("usdz", small, false).unwrap();
    assert_eq!(waits, 0, "the USDZ was made again");
    assert_eq!((kind.as_str(), again), ("model/vnd.usdz+zip", triangles));
    assert!(usdz.starts_with(b"PK\x03\x04"), "a zip");
    println!(
        "mesh of {triangles} triangles: GLB {} bytes in {made:.1} s, then USDZ {} bytes in {kept:.1} s",
        glb.len(),
        usdz.len()
    );

    // Inside a crop that holds nothing: made in the background, then said.
    let far = json!({ "centre": [50, 50, 50], "axes": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "half": [0.1, 0.1, 0.1] });
    let (s, v) = rt.block_on(svc.put_json(&format!("/v1/models/{id}/crop"), far));
    assert_eq!(s, 200, "{v}");
    let e = get("glb", small, false).expect_err("a mesh of nothing");
    assert_error(&e, "conflict");
    assert!(e["error"]["message"].as_str().unwrap().contains("no surface inside the crop box"), "{e}");
    let (s, v) = rt.block_on(svc.delete(&format!("/v1/models/{id}/crop")));
    assert_eq!(s, 204, "{v}");

    // The web app: the viewer's mesh button, then model-viewer at a known
    // camera (its orbit: azimuth from +z towards +x, polar angle from +y).
    let browser = crate::common::cdp::Browser::launch(1200, 900);
    let mut page = browser.page();
    page.goto(&svc.url(&format!("/#/models/{id}")));
    page.wait_for("!document.getElementById('view-mesh').hidden", 60.0);
    page.click("#view-mesh");
    page.wait_for("document.getElementById('mesh-panel').dataset.state !== 'making'", 120.0);
    let state = page.eval("document.getElementById('mesh-state').textContent");
    assert_eq!(page.eval("document.getElementById('mesh-panel').dataset.state"), "shown", "{state}");
    page.wait_for("!document.getElementById('mesh-usdz').hidden", 60.0);
    let state = page.eval("document.getElementById('mesh-state').textContent");
    assert!(state.as_str().unwrap().contains("as USDZ"), "{state}");
    for (link, ext) in [("mesh-glb", "glb"), ("mesh-usdz", "usdz")] {
        let name = page.eval(&format!("document.getElementById('{link}').download"));
        assert_eq!(name.as_str(), Some(format!("{id}.{ext}").as_str()));
    }
    let ar = page.eval("document.getElementById('mesh-view').getAttribute('ios-src')");
    assert!(ar.as_str().is_some_and(|u| u.starts_with("blob:")), "the AR button's USDZ: {ar}");
    screenshot(&mut page, "mesh", false);

    // The page's mesh (the defaults), kept by the server: at once, as read
    // back for our own renderer.
    let (_, triangles, glb, _, waits) = get("glb", "", false).unwrap();
    assert_eq!(waits, 0, "the page's mesh was not kept");
    assert!((20_000..=200_000).contains(&triangles), "{triangles} triangles");
    let placed = read_glb(&glb);
    assert_eq!(placed.triangles.len(), triangles);
    let top = placed.positions.iter().map(|p| p[1]).fold(0.0f32, f32::max);

    let (theta, phi, radius, fov_y) = (35.0f32, 62.0f32, 1.3f32, 30.0f32);
    let target = [0.0, 0.5 * top, 0.0];
    let v = page.eval(&format!(
        "(async () => {{
           const mv = document.getElementById('mesh-view');
           mv.scrollIntoView();
           mv.constructor.minimumRenderScale = 1;
           mv.setAttribute('min-camera-orbit', 'auto 0deg 0m');
           mv.setAttribute('max-camera-orbit', 'auto 180deg 100m');
           mv.setAttribute('camera-target', '0m {ty}m 0m');
           mv.setAttribute('camera-orbit', '{theta}deg {phi}deg {radius}m');
           mv.setAttribute('field-of-view', '{fov_y}deg');
           await mv.updateComplete;
           mv.jumpCameraToGoal();
           for (let i = 0; i < 10; i++) await new Promise((r) => requestAnimationFrame(r));
           const o = mv.getCameraOrbit(), t = mv.getCameraTarget();
           window.meshCamera = {{ theta: o.theta, phi: o.phi, r: o.radius, fov: mv.getFieldOfView(), t: [t.x, t.y, t.z] }};
           return mv.toDataURL('image/png');
         }})()",
        ty = target[1]
    ));
    let png = crate::common::cdp::base64(v.as_str().unwrap().trim_start_matches("data:image/png;base64,"));
    let shot = image::load_from_memory(&png).unwrap().to_rgba8();
    let (w, h) = shot.dimensions();
    println!("model-viewer's camera: {}", page.eval("JSON.stringify(window.meshCamera)"));
    // Over white, as our render.
    let theirs = RgbImage::from_fn(w, h, |x, y| {
        let p = shot.get_pixel(x, y).0;
        let a = p[3] as f32 / 255.0;
        image::Rgb([0, 1, 2].map(|k| (p[k] as f32 * a + 255.0 * (1.0 - a)).round() as u8))
    });
    let (t, p) = (theta.to_radians(), phi.to_radians());
    let eye = [radius * p.sin() * t.sin(), target[1] + radius * p.cos(), radius * p.sin() * t.cos()];
    let fov_x = 2.0 * ((0.5 * fov_y.to_radians()).tan() * w as f32 / h as f32).atan();
    let c2w = look_at(eye.map(f64::from), target.map(f64::from), [0.0, 1.0, 0.0]).map(|r| r.map(|x| x as f32));
    let camera = Camera::from_fov(w, h, fov_x, c2w);
    let ours = render_mesh(&placed, &camera, [1.0; 3], 3);
    let ours = RgbImage::from_fn(w, h, |x, y| {
        let i = (y * w + x) as usize * 3;
        image::Rgb([0, 1, 2].map(|k| (ours.rgb[i + k].clamp(0.0, 1.0) * 255.0).round() as u8))
    });
    for (img, name) in [(&theirs, "mesh-model-viewer"), (&ours, "mesh-ours")] {
        for path in crate::screenshot_paths(name) {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            img.save(&path).unwrap();
        }
    }
    let covered = theirs.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    assert!(covered > (w * h / 50) as usize, "model-viewer drew almost nothing ({covered} pixels)");
    let psnr = rgb8_psnr(&theirs, &ours);
    println!("model-viewer {w}x{h} against our render of the mesh: {psnr:.2} dB");
    assert!(psnr >= 25.0, "model-viewer's picture differs from ours: {psnr:.2} dB");
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);

    // The panel's web-page download, then that site served by a plain
    // static file server: model-viewer draws the mesh there too.
    page.click("#mesh-site");
    page.wait_for(&format!("document.getElementById('mesh-site').dataset.file === '{id}-mesh.zip'"), 60.0);
    let zip = rt.block_on(async {
        let r = reqwest::get(svc.url(&format!("/v1/models/{id}/mesh?format=html"))).await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "application/zip");
        r.bytes().await.unwrap().to_vec()
    });
    let site = tempfile::tempdir().unwrap();
    zip::ZipArchive::new(std::io::Cursor::new(zip)).unwrap().extract(site.path()).unwrap();
    let root = site.path().join(format!("{id}-mesh"));
    for f in ["index.html", "model.glb", "model.usdz", "vendor/model-viewer/LICENSE"] {
        assert!(root.join(f).is_file(), "{f} missing from the site");
    }
    assert_eq!(std::fs::read(root.join("model.glb")).unwrap(), glb, "the site's GLB is the API's");
    let server = crate::realtime::StaticServer::start(&root);
    let mut page = browser.page();
    page.goto(&format!("{}/index.html", server.url));
    page.wait_for("document.querySelector('model-viewer').loaded", 60.0);
    let drawn = page.eval(
        "(async () => {
           const mv = document.querySelector('model-viewer');
           for (let i = 0; i < 10; i++) await new Promise((r) => requestAnimationFrame(r));
           const img = new Image(); img.src = mv.toDataURL('image/png'); await img.decode();
           const c = document.createElement('canvas'); c.width = img.width; c.height = img.height;
           const g = c.getContext('2d'); g.drawImage(img, 0, 0);
           const d = g.getImageData(0, 0, c.width, c.height).data;
           let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 128) n++;
           return n / (c.width * c.height);
         })()",
    );
    println!("the mesh's site: {:.1}% of the window drawn", 100.0 * drawn.as_f64().unwrap());
    assert!(drawn.as_f64().unwrap() > 0.02, "the site's model-viewer drew almost nothing: {drawn}");
    assert_eq!(page.eval("document.querySelector('model-viewer').getAttribute('ios-src')"), "model.usdz");
    screenshot(&mut page, "mesh-site", false);
    assert!(page.errors.is_empty(), "the site reported JavaScript errors: {:#?}", page.errors);
    rt.block_on(svc.stop());
}
