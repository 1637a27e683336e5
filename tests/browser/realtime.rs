//! The real-time view end to end, through the API's jobs and the real
//! server: the demo scene (generated) is trained briefly (`instant-tiny`),
//! baked into splats by a bake job, then
//! - the web app opens the splats model from a link with the camera in it
//!   and draws it in the browser (Spark on WebGL2, the software renderer
//!   here) from the `.spz`, spherical-harmonic colours (degree 1) included;
//!   the canvas matches the server's CPU render of the same camera (PSNR >=
//!   35 dB); dragging changes the picture and the address, with
//!   no request to the server;
//! - the exported site (`export?format=html`), unzipped and served by a
//!   plain static file server (`python3 -m http.server`), shows the same
//!   picture as the CPU render of the model's default view.
//!
//! The frame rate of the splat canvas on the software renderer (frames
//! drawn, each a full redraw, in 3 s of requestAnimationFrame) is printed.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use image::RgbImage;
use serde_json::{Value, json};

use crate::common::cdp::{Browser, Page};
use crate::common::psnr::rgb8_psnr;
use crate::common::{Svc, config};
use crate::{runtime, screenshot};

/// The canvas `selector`'s pixels as an RGB image (its drawing buffer).
fn canvas_image(page: &mut Page, selector: &str) -> RgbImage {
    let v = page.eval(&format!(
        "(() => {{
           const c = document.querySelector({selector:?});
           const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
           const g = t.getContext('2d'); g.drawImage(c, 0, 0);
           const d = g.getImageData(0, 0, t.width, t.height).data;
           const rgb = [];
           for (let i = 0; i < d.length; i += 4) rgb.push(d[i], d[i + 1], d[i + 2]);
           return {{ width: t.width, height: t.height, rgb }};
         }})()"
    ));
    let (w, h) = (v["width"].as_u64().unwrap() as u32, v["height"].as_u64().unwrap() as u32);
    let rgb: Vec<u8> = v["rgb"].as_array().unwrap().iter().map(|x| x.as_u64().unwrap() as u8).collect();
    RgbImage::from_raw(w, h, rgb).expect("the canvas's pixels")
}

fn save(img: &RgbImage, name: &str) {
    for p in crate::screenshot_paths(name) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        img.save(&p).unwrap();
    }
}

/// Frames drawn (each a full redraw of the splats) in `secs` seconds of
/// requestAnimationFrame, per second.
fn frame_rate(page: &mut Page, view: &str, secs: f64) -> f64 {
    let v = page.eval(&format!(
        "new Promise((resolve) => {{
           const v = {view}; let n = 0; const t0 = performance.now();
           const tick = () => {{
             v.renderer.render(v.scene, v.camera); n++;
             const t = performance.now() - t0;
             if (t < {ms}) requestAnimationFrame(tick); else resolve(n / (t / 1000));
           }};
           requestAnimationFrame(tick);
         }})",
        ms = secs * 1000.0
    ));
    v.as_f64().unwrap()
}

/// `python3 -m http.server` over `dir` on a free port of 127.0.0.1.
pub(crate) struct StaticServer {
    child: Child,
    pub url: String,
}

impl StaticServer {
    pub fn start(dir: &std::path::Path) -> StaticServer {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new("python3")
            .args(["-m", "http.server", "--bind", "127.0.0.1", &port.to_string()])
            .current_dir(dir)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("python3 -m http.server");
        let t0 = Instant::now();
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(t0.elapsed() < Duration::from_secs(20), "the static file server did not start");
            std::thread::sleep(Duration::from_millis(50));
        }
        StaticServer { child, url: format!("http://127.0.0.1:{port}") }
    }
}

impl Drop for StaticServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Our camera: c2w rows looking from `eye` at `at` with world up `up`.
pub(crate) fn look_at(eye: [f64; 3], at: [f64; 3], up: [f64; 3]) -> [[f64; 4]; 3] {
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross =
        |a: [f64; 3], b: [f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let unit = |a: [f64; 3]| {
        let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        [a[0] / n, a[1] / n, a[2] / n]
    };
    let back = unit(sub(eye, at));
    let right = unit(cross(up, back));
    let up2 = cross(back, right);
    [0, 1, 2].map(|i| [right[i], up2[i], back[i], eye[i]])
}

#[test]
fn baked_splats_draw_in_the_browser_as_the_server_renders_them_and_the_exported_site_too() {
    let _ = tracing_subscriber::fmt().with_env_filter("radiance=warn").with_test_writer().try_init();
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let t0 = Instant::now();

    // A generated scene, a brief training, a small bake: all as jobs.
    let (model, splats_id) = rt.block_on(async {
        let train = svc.trained_demo(300).await;
        let done = |v: &Value| !matches!(v["status"].as_str(), Some("queued" | "running"));
        let source = train["model_id"].as_str().unwrap().to_string();

        // Not splats: no export, with a reason.
        let (s, v) = svc.get(&format!("/v1/models/{source}/export?format=splat")).await;
        assert_eq!(s, 409, "{v}");
        assert!(v["error"]["message"].as_str().unwrap().contains("bake"), "{v}");

        let body = json!({ "kind": "bake", "model_id": source, "steps": 150, "sh_degree": 1 });
        let (s, bake) = svc.post_json("/v1/jobs", body).await;
        assert_eq!(s, 202, "{bake}");
        assert_eq!((bake["kind"].as_str(), bake["source_model_id"].as_str()), (Some("bake"), Some(source.as_str())));
        assert!(bake["memory_estimate_bytes"].as_u64().unwrap() > 0, "{bake}");
        let bake = svc.wait_job(bake["id"].as_str().unwrap(), 300.0, done).await;
        assert_eq!(bake["status"], "succeeded", "{bake}");
        assert_eq!(bake["progress"]["step"], 150, "{bake}");
        assert!(bake["progress"]["gaussians"].as_u64().unwrap() > 100, "{bake}");
        let id = bake["model_id"].as_str().unwrap().to_string();
        let (s, model) = svc.get(&format!("/v1/models/{id}")).await;
        assert_eq!(s, 200);
        assert_eq!(model["model"].as_str(), Some("splats"), "{model}");
        assert_eq!(model["gaussians"], bake["progress"]["gaussians"], "the model record counts its Gaussians");
        // The compact formats through the API, named and typed.
        for (format, magic, kind) in
            [("spz", &[0x1f, 0x8b][..], "application/octet-stream"), ("glb", b"glTF", "model/gltf-binary")]
        {
            let r = reqwest::get(svc.url(&format!("/v1/models/{id}/export?format={format}"))).await.unwrap();
            assert_eq!(r.status(), 200);
            let header = |h: &str| r.headers()[h].to_str().unwrap().to_string();
            assert_eq!(header("content-type"), kind);
            assert!(header("content-disposition").ends_with(&format!("{id}.{format}\"")));
            let (kept, removed): (u64, u64) =
                (header("x-gaussians").parse().unwrap(), header("x-gaussians-removed").parse().unwrap());
            assert_eq!(kept + removed, model["gaussians"].as_u64().unwrap(), "every Gaussian kept or removed");
            assert!(r.bytes().await.unwrap().starts_with(magic), "{format}");
        }
        println!(
            "trained {source} ({} dB) and baked {id} ({} Gaussians, {} dB held out) in {:.1} s",
            train["progress"]["test_psnr"],
            bake["progress"]["gaussians"],
            model["test_psnr"],
            t0.elapsed().as_secs_f64()
        );
        (model, id)
    });

    let browser = Browser::launch(1000, 800);
    let mut page = browser.page();

    // The web app, opened by a link with the camera in it.
    let view = &model["view"];
    let vec = |v: &Value| [0, 1, 2].map(|i| v[i].as_f64().unwrap());
    let (centre, up) = (vec(&view["centre"]), vec(&view["up"]));
    let radius = view["radius"].as_f64().unwrap();
    let eye = [centre[0] + 0.8 * radius, centre[1] - 0.45 * radius, centre[2] + 0.5 * radius];
    let fov = 40.0;
    let link = format!(
        "/#/models/{splats_id}?eye={}&target={}&fov={fov}",
        eye.map(|x| format!("{x:.4}")).join(","),
        centre.map(|x| format!("{x:.4}")).join(",")
    );
    page.record_requests();
    page.goto(&svc.url(&link));
    page.wait_for(&format!("document.getElementById('view-splats').dataset.model === '{splats_id}'"), 60.0);
    page.eval("window.splatView.settled()");
    assert_eq!(page.eval("document.getElementById('viewer').hidden"), false);
    assert_eq!(page.eval("document.getElementById('view-img').hidden"), true);
    // The model list names the splats' Gaussian count.
    let count = model["gaussians"].as_u64().unwrap();
    let option = page.eval(&format!("document.querySelector('#view-model option[value=\"{splats_id}\"]').textContent"));
    let shown = format!(
        "{} Gaussians",
        count
            .to_string()
            .as_bytes()
            .rchunks(3)
            .rev()
            .map(|c| std::str::from_utf8(c).unwrap())
            .collect::<Vec<_>>()
            .join(",")
    );
    assert!(option.as_str().unwrap().contains(&shown), "{option} does not say {shown}");
    let drawn = canvas_image(&mut page, "#view-splats");
    screenshot(&mut page, "realtime-viewer", false);
    save(&drawn, "realtime-canvas");

    // The server's CPU render of the same camera (the link's eye and
    // target, rounded as the link rounds them).
    let eye4 = eye.map(|x| (x * 1e4).round() / 1e4);
    let centre4 = centre.map(|x| (x * 1e4).round() / 1e4);
    let c2w = look_at(eye4, centre4, up);
    let flat: Vec<String> = c2w.iter().flatten().map(|x| format!("{x:.7}")).collect();
    let (w, h) = drawn.dimensions();
    let path = format!("/v1/models/{splats_id}/render?c2w={}&width={w}&height={h}&fov={fov}", flat.join(","));
    let cpu = rt.block_on(svc.png(&path)).to_rgb8();
    save(&cpu, "realtime-cpu");
    let psnr = rgb8_psnr(&drawn, &cpu);
    println!("web app canvas {w}x{h} against the CPU render: {psnr:.2} dB");
    // Measured 52.81 dB from the .spz (the software renderer, 720x720).
    assert!(psnr >= 35.0, "the browser's splats differ from the CPU render: {psnr:.2} dB");

    let fps = frame_rate(&mut page, "window.splatView", 3.0);
    println!("frame rate of the splat canvas on the software renderer: {fps:.1} frames/s ({w}x{h})");
    assert!(fps > 0.0);

    // Dragging turns the view: a new picture, a new address, no request.
    let asked = page.requests.len();
    let hash = page.eval("location.hash");
    assert!(hash.as_str().unwrap().starts_with(&format!("#/models/{splats_id}?eye=")), "{hash}");
    let centre_px = page.centre_of("#view-splats");
    page.drag(centre_px, (60.0, 20.0), 10, Duration::from_millis(30));
    page.eval("window.splatView.settled()");
    let dragged = canvas_image(&mut page, "#view-splats");
    let moved = rgb8_psnr(&dragged, &drawn);
    assert!(moved < 40.0, "dragging did not change the picture ({moved:.1} dB from before)");
    let hash2 = page.eval("location.hash");
    assert_ne!(hash2, hash, "the address did not follow the camera");
    screenshot(&mut page, "realtime-viewer-moved", false);
    let later: Vec<&String> = page.requests[asked..].iter().filter(|u| u.starts_with("http")).collect();
    assert!(later.is_empty(), "requests after the splats were loaded: {later:?}");
    let renders: Vec<&String> = page.requests.iter().filter(|u| u.contains("/render")).collect();
    assert!(renders.is_empty(), "the page asked the server for renders of a splats model: {renders:?}");
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);

    // The splats taken away from the viewer: a .glb, named by the server,
    // with what the cleanup removed said.
    assert_eq!(page.eval("document.getElementById('view-export').hidden"), false);
    page.eval("document.getElementById('view-export-format').value = 'glb'; document.getElementById('view-export-go').click()");
    page.wait_for("(document.getElementById('view-export-go').dataset.file || '').endsWith('.glb')", 30.0);
    let said = page.eval("document.getElementById('status').textContent");
    assert_eq!(page.eval("document.getElementById('view-export-go').dataset.file"), format!("{splats_id}.glb"));
    assert!(said.as_str().unwrap().contains("floaters removed"), "{said}");
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);

    crop_in_the_viewer(&rt, &svc, &mut page, &splats_id, count);
    transparent_render_over_a_coloured_page(&rt, &svc, &mut page, &splats_id);

    // The exported site (of the cropped splats now) on a plain static file
    // server.
    let zip = rt.block_on(async {
        let r = reqwest::get(svc.url(&format!("/v1/models/{splats_id}/export?format=html"))).await.unwrap();
        assert_eq!(r.status(), 200);
        assert_eq!(r.headers()["content-type"], "application/zip");
        let disposition = r.headers()["content-disposition"].to_str().unwrap().to_string();
        assert_eq!(disposition, format!("attachment; filename=\"{splats_id}-site.zip\""));
        r.bytes().await.unwrap().to_vec()
    });
    let site = tempfile::tempdir().unwrap();
    zip::ZipArchive::new(std::io::Cursor::new(zip)).unwrap().extract(site.path()).unwrap();
    let folder = site.path().join(format!("{splats_id}-site"));
    for f in ["index.html", "splats.js", "scene.spz", "vendor/spark/LICENSE", "vendor/three/LICENSE"] {
        assert!(folder.join(f).is_file(), "{f} missing from the site");
    }
    let server = StaticServer::start(&folder);
    let mut site_page = browser.page();
    site_page.goto(&format!("{}/index.html", server.url));
    site_page.wait_for("document.body.dataset.ready === 'true'", 60.0);
    let shown = canvas_image(&mut site_page, "#splats");
    screenshot(&mut site_page, "realtime-site", false);
    save(&shown, "realtime-site-canvas");
    let (sw, sh) = shown.dimensions();
    let default = rt.block_on(svc.png(&format!("/v1/models/{splats_id}/render"))).to_rgb8();
    assert_eq!(default.dimensions(), (sw, sh), "the site's canvas is the default view's size");
    let site_psnr = rgb8_psnr(&shown, &default);
    println!("exported site canvas {sw}x{sh} against the CPU render of the default view: {site_psnr:.2} dB");
    // Measured 52.92 dB from the .spz (64x64).
    assert!(site_psnr >= 35.0, "the exported site differs from the CPU render: {site_psnr:.2} dB");
    // The browser asks any host for /favicon.ico; the site has none (a
    // plain static server answers 404), which is no error of the page.
    let errors: Vec<&String> = site_page.errors.iter().filter(|e| !e.contains("/favicon.ico")).collect();
    assert!(errors.is_empty(), "the site reported JavaScript errors: {errors:#?}");
    drop(server);
    drop(browser);
    rt.block_on(svc.stop());
}

/// The crop through the API (refusals naming the field, nothing stored),
/// then in the viewer: the handles move the box, the view follows (what
/// is outside is hidden), and the box kept is the model's crop, which the
/// views and the export honour.
fn crop_in_the_viewer(rt: &tokio::runtime::Runtime, svc: &Svc, page: &mut Page, id: &str, count: u64) {
    let crop_url = format!("/v1/models/{id}/crop");
    rt.block_on(async {
        let (s, v) = svc.get(&crop_url).await;
        assert_eq!(s, 404, "{v}");
        let unit = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]);
        for (body, field) in [
            (json!({ "centre": [0, 0, 0], "axes": unit, "half": [0.5, -1, 0.5] }), "half"),
            // Beyond f32: infinite, so not finite.
            (json!({ "centre": [1e39, 0, 0], "axes": unit, "half": [1, 1, 1] }), "centre"),
            (json!({ "centre": [0, 0, 0], "axes": unit, "half": [1, 1e39, 1] }), "half"),
            (json!({ "centre": [0, 0, 0], "axes": unit, "half": [0.5, 0, 0.5] }), "half"),
            (json!({ "centre": [0, 0, 0], "axes": [[1, 0, 0], [1, 0, 0], [0, 0, 1]], "half": [1, 1, 1] }), "axes"),
            (json!({ "centre": [0, 0, 0], "axes": unit }), "half"),
            (json!({ "centre": [0, 0, 0], "axes": unit, "half": [1, 1, 1], "radius": 2 }), "radius"),
            // Far from every Gaussian: it would keep nothing.
            (json!({ "centre": [50, 50, 50], "axes": unit, "half": [0.1, 0.1, 0.1] }), "crop"),
            (json!({ "auto": false }), "auto"),
        ] {
            let (s, v) = svc.put_json(&crop_url, body.clone()).await;
            assert_eq!(s, 422, "{body} -> {v}");
            assert_eq!(v["error"]["code"], "invalid_crop", "{v}");
            assert_eq!(v["error"]["details"]["field"], field, "{body} -> {v}");
        }
        // A NaN is no JSON number: the body is refused before it is read.
        let r = svc
            .client
            .put(svc.url(&crop_url))
            .header("content-type", "application/json")
            .body(r#"{"centre": [NaN, 0, 0], "axes": [[1,0,0],[0,1,0],[0,0,1]], "half": [1, 1, 1]}"#)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 400);
        let (s, v) = svc.get(&crop_url).await;
        assert_eq!(s, 404, "a refused crop was stored: {v}");
        let (s, v) = svc.delete(&crop_url).await;
        assert_eq!(s, 404, "{v}");

        // Found automatically: around the mug (radius 0.3 at the origin, on
        // the mat at z = -0.45, its handle reaching x = 0.58), not the rim of
        // the mat (radius 1.35), which some cameras do not frame; stored,
        // then removed.
        let (s, auto) = svc.put_json(&crop_url, json!({ "auto": true })).await;
        assert_eq!(s, 200, "{auto}");
        let (s, v) = svc.get(&crop_url).await;
        assert_eq!((s, &v), (reqwest::StatusCode::OK, &auto));
        let inside = |p: [f64; 3]| {
            (0..3).all(|a| {
                let d: f64 = (0..3)
                    .map(|i| (p[i] - auto["centre"][i].as_f64().unwrap()) * auto["axes"][a][i].as_f64().unwrap())
                    .sum();
                d.abs() <= auto["half"][a].as_f64().unwrap()
            })
        };
        for p in [[0.0, 0.0, -0.3], [0.25, 0.0, -0.1], [0.0, -0.25, -0.4], [0.5, 0.0, -0.13]] {
            assert!(inside(p), "the automatic crop misses the mug at {p:?}: {auto}");
        }
        for p in [[1.3, 0.0, -0.46], [0.0, -1.3, -0.46], [-0.92, 0.92, -0.46]] {
            assert!(!inside(p), "the automatic crop keeps the mat's rim at {p:?}: {auto}");
        }
        let (s, v) = svc.get(&format!("/v1/models/{id}")).await;
        assert_eq!((s, &v["crop"]), (reqwest::StatusCode::OK, &auto), "the model's record holds its crop");
        let (s, v) = svc.delete(&crop_url).await;
        assert_eq!(s, 204, "{v}");
        let (s, v) = svc.get(&format!("/v1/models/{id}")).await;
        assert!(s == 200 && v.get("crop").is_none(), "{v}");
    });

    // The editor: a box around every Gaussian to start with.
    page.click("#crop-edit");
    page.wait_for("!document.getElementById('crop-tools').hidden && !!window.cropEditor", 60.0);
    page.eval("window.splatView.settled()");
    let inside0 = page.eval("Number(document.getElementById('view-splats').dataset.cropInside)").as_u64().unwrap();
    assert_eq!(inside0, count, "the first box holds every Gaussian");
    let before = canvas_image(page, "#view-splats");
    screenshot(page, "crop-editor", false);

    // Drag the handle of the box's x axis by 150 px along the axis as
    // drawn: the gizmo's arrow runs from the centre along x, 0.5 of its
    // size (TransformControls: size / 4 of the camera distance times
    // 1.9 tan(fov / 2)), its picker from 0 to 0.6.
    let at = page.eval(
        "(() => {
           const v = window.splatView, e = window.cropEditor, b = e.box();
           const cam = v.camera, r = v.canvas.getBoundingClientRect();
           const c = e.object.position.clone();
           const factor = c.distanceTo(cam.position) * Math.min(1.9 * Math.tan(Math.PI * cam.fov / 360) / cam.zoom, 7);
           const p = c.clone().add(e.object.position.clone().set(...b.axes[0]).multiplyScalar(0.4 * factor / 4));
           const px = (q) => { const s = q.clone().project(cam); return [r.left + (s.x + 1) / 2 * r.width, r.top + (1 - s.y) / 2 * r.height]; };
           return { grab: px(p), centre: px(c), box: b };
         })()",
    );
    let xy = |v: &Value| (v[0].as_f64().unwrap(), v[1].as_f64().unwrap());
    let (grab, centre) = (xy(&at["grab"]), xy(&at["centre"]));
    let (dx, dy) = (grab.0 - centre.0, grab.1 - centre.1);
    let norm = (dx * dx + dy * dy).sqrt();
    assert!(norm > 5.0, "the x handle is not on the screen: {at}");
    page.drag(grab, (150.0 * dx / norm, 150.0 * dy / norm), 15, Duration::from_millis(30));
    page.eval("window.splatView.settled()");
    let moved = page.eval("window.cropEditor.box()");
    let centre0: Vec<f64> = at["box"]["centre"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    let centre1: Vec<f64> = moved["centre"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    let axis: Vec<f64> = at["box"]["axes"][0].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
    let along: f64 = (0..3).map(|i| (centre1[i] - centre0[i]) * axis[i]).sum();
    let across: f64 = (0..3).map(|i| (centre1[i] - centre0[i] - along * axis[i]).powi(2)).sum::<f64>().sqrt();
    assert!(along > 0.05 && across < 1e-6, "the handle did not move the box along x: {at} -> {moved}");
    let inside1 = page.eval("Number(document.getElementById('view-splats').dataset.cropInside)").as_u64().unwrap();
    assert!(inside1 < inside0, "the moved box holds {inside1} of {inside0} Gaussians");
    let followed = canvas_image(page, "#view-splats");
    let change = rgb8_psnr(&followed, &before);
    assert!(change < 40.0, "the view did not follow the box ({change:.1} dB from before)");
    screenshot(page, "crop-editor-moved", false);

    // Kept: the model's crop is the box, and the view shows what is inside.
    page.click("#crop-save");
    page.wait_for("document.getElementById('view-splats').dataset.cropDone === 'save'", 60.0);
    page.eval("window.splatView.settled()");
    let stored = rt.block_on(svc.get(&crop_url));
    assert_eq!(stored.0, 200, "{}", stored.1);
    for (k, v) in [("centre", &moved["centre"]), ("half", &moved["half"])] {
        for i in 0..3 {
            let (a, b) = (stored.1[k][i].as_f64().unwrap(), v[i].as_f64().unwrap());
            assert!((a - b).abs() < 1e-4, "{k}: stored {} and moved {v}", stored.1[k]);
        }
    }
    let shown = page.eval("Number(document.getElementById('view-splats').dataset.count)").as_u64().unwrap();
    assert!(shown <= inside1 && shown > 0, "the cropped view shows {shown} Gaussians, the box held {inside1}");
    let cropped = canvas_image(page, "#view-splats");
    screenshot(page, "crop-kept", false);
    save(&cropped, "crop-kept-canvas");
    // The server's render of the same camera honours the crop: the
    // canvas matches it, and not the uncropped render.
    let cam = page.eval("window.splatView.getCamera()");
    let flat: Vec<String> = (0..3)
        .flat_map(|r| (0..4).map(move |c| (r, c)))
        .map(|(r, c)| format!("{:.7}", cam["c2w"][r][c].as_f64().unwrap()))
        .collect();
    let (w, h) = cropped.dimensions();
    let fov = 2.0 * ((w as f64 / 2.0) / cam["fx"].as_f64().unwrap()).atan().to_degrees();
    let path = format!("/v1/models/{id}/render?c2w={}&width={w}&height={h}&fov={fov}", flat.join(","));
    let cpu = rt.block_on(svc.png(&path)).to_rgb8();
    let all = rt.block_on(svc.png(&format!("{path}&crop=false"))).to_rgb8();
    let (psnr, psnr_all) = (rgb8_psnr(&cropped, &cpu), rgb8_psnr(&cropped, &all));
    println!("cropped canvas against the CPU render: {psnr:.2} dB (uncropped render: {psnr_all:.2} dB)");
    assert!(psnr >= 35.0 && psnr > psnr_all + 3.0, "cropped {psnr:.2} dB, uncropped {psnr_all:.2} dB");
    // The export of the cropped model counts what the crop left out: as
    // many as the viewer counted outside (it counted the splats it had
    // loaded: after the floater cleanup, their positions quantised).
    rt.block_on(async {
        let r = reqwest::get(svc.url(&format!("/v1/models/{id}/export?format=spz&cleanup=false"))).await.unwrap();
        assert_eq!(r.status(), 200);
        let h = |k: &str| r.headers()[k].to_str().unwrap().parse::<u64>().unwrap();
        let (kept, cropped) = (h("x-gaussians"), h("x-gaussians-cropped"));
        assert_eq!((kept + cropped, h("x-gaussians-removed")), (count, 0));
        assert!(kept.abs_diff(inside1) <= count / 50, "the export keeps {kept}, the viewer's box held {inside1}");
    });
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
}

/// A view of the object on a transparent background, shown by an `<img>`
/// over a coloured page, is the colour render composited by its alpha
/// over that colour.
fn transparent_render_over_a_coloured_page(rt: &tokio::runtime::Runtime, svc: &Svc, page: &mut Page, id: &str) {
    let (w, h) = (96u32, 96u32);
    let view = format!("/v1/models/{id}/render?width={w}&height={h}&azimuth=30");
    let colour = [40.0, 110.0, 220.0];
    page.eval(&format!(
        "new Promise((resolve, reject) => {{
           const d = document.createElement('div');
           d.id = 'composite';
           d.style.cssText = 'position:fixed;left:0;top:0;padding:0;margin:0;z-index:99;background:rgb({},{},{})';
           const i = new Image(); i.style.display = 'block'; i.width = {w}; i.height = {h};
           i.onload = () => resolve(true); i.onerror = reject;
           i.src = '{view}&background=transparent';
           d.append(i); document.body.append(d);
         }})",
        colour[0], colour[1], colour[2]
    ));
    page.eval("new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))");
    // Where the image is on the page (a capture's clip is in page coordinates).
    let at = page.eval(
        "(() => { const r = document.querySelector('#composite img').getBoundingClientRect(); return [r.left + scrollX, r.top + scrollY]; })()",
    );
    let shown = page.capture(at[0].as_f64().unwrap(), at[1].as_f64().unwrap(), w as f64, h as f64);
    let rgba = rt.block_on(svc.png(&format!("{view}&background=transparent"))).to_rgba8();
    let alpha = rgba.pixels().filter(|p| p[3] < 250).count();
    assert!(alpha > (w * h / 4) as usize, "the transparent render has few clear pixels: {alpha}");
    // What the page should show: the colour by its alpha over the page's.
    let expected = image::RgbImage::from_fn(w, h, |x, y| {
        let p = rgba.get_pixel(x, y);
        let a = p[3] as f64 / 255.0;
        image::Rgb([0, 1, 2].map(|c| (p[c] as f64 * a + colour[c] * (1.0 - a)).round() as u8))
    });
    let shown = image::DynamicImage::ImageRgba8(shown).to_rgb8();
    save(&shown, "transparent-over-blue");
    let psnr = rgb8_psnr(&shown, &expected);
    println!("transparent render over a coloured page: {psnr:.2} dB against the expected composite");
    assert!(psnr >= 35.0, "the transparent render composites wrongly over the page: {psnr:.2} dB");
    // ... and it is not merely the white render.
    let white = rt.block_on(svc.png(&view)).to_rgb8();
    assert!(rgb8_psnr(&shown, &white) < 25.0, "the page shows the white background, not its own colour");
}

/// A training started on the page with "then bake a real-time view"
/// (the default) ends on the real-time view: the bake's line names its
/// time and what is left while it runs, then the viewer draws the splats
/// in the browser, asking the server for no render.
#[test]
fn training_on_the_page_ends_on_the_real_time_view() {
    let _ = tracing_subscriber::fmt().with_env_filter("radiance=warn").with_test_writer().try_init();
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let (s, scene) = rt.block_on(svc.post_json("/v1/demo", json!({})));
    assert_eq!(s, 201, "{scene}");
    let browser = Browser::launch(1200, 1000);
    let mut page = browser.page();
    page.record_requests();
    page.goto(&svc.url("/"));
    page.wait_for("document.querySelectorAll('#scene-list li').length === 1", 30.0);
    page.click("#scene-list li button");
    page.wait_for("!document.getElementById('training').hidden", 30.0);
    page.fill("#train-model", "instant-tiny");
    page.fill("#train-budget-kind", "steps");
    page.fill("#train-budget", "200");
    assert_eq!(page.eval("document.getElementById('train-bake').checked"), true, "baking is the default");
    page.fill("#train-bake-seconds", "6");
    // Every text the bake's line shows (each a new text node), recorded by
    // the page: the bake lasts 6 s, too short for polling from here to be
    // sure to see it running.
    page.eval(
        "(() => { window.bakeSeen = []; const l = document.getElementById('bake-line');
           new MutationObserver((records) => { for (const r of records) for (const n of r.addedNodes)
             window.bakeSeen.push([l.hidden, n.textContent]); }).observe(l, { childList: true });
           return true; })()",
    );
    page.click("#train-start");
    // Then the real-time view, drawn by the browser.
    page.wait_for(
        "!document.getElementById('viewer').hidden && !!document.getElementById('view-splats').dataset.model",
        120.0,
    );
    // The bake's line while it ran: its step, time baked and time left.
    let seen = page.eval("window.bakeSeen");
    let running = seen.as_array().unwrap().iter().find_map(|s| {
        let text = s[1].as_str().unwrap();
        (s[0] == false && text.contains(": running · ") && text.contains("ETA")).then_some(text)
    });
    let line = running.unwrap_or_else(|| panic!("the bake's line never showed it running with an ETA: {seen}"));
    assert!(line.contains("step ") && line.contains(" baked") && line.contains("Gaussians"), "{line}");
    page.eval("window.splatView.settled()");
    assert_eq!(page.eval("document.getElementById('view-img').hidden"), true);
    let n: u64 = page.eval("document.getElementById('view-splats').dataset.count").as_str().unwrap().parse().unwrap();
    assert!(n > 100, "{n} splats drawn");
    let jobs = rt.block_on(svc.get("/v1/jobs")).1;
    let bake = jobs.as_array().unwrap().iter().find(|j| j["kind"] == "bake").expect("a bake job").clone();
    assert_eq!(bake["status"], "succeeded", "{bake}");
    let train = jobs.as_array().unwrap().iter().find(|j| j["kind"] == "train").expect("the training job").clone();
    assert_eq!(train["bake"]["seconds"], 6.0, "the page's bake budget: {train}");
    screenshot(&mut page, "realtime-after-training", false);
    let splats_id = page.eval("document.getElementById('view-splats').dataset.model").as_str().unwrap().to_string();
    let renders: Vec<&String> =
        page.requests.iter().filter(|u| u.contains(&format!("/v1/models/{splats_id}/render"))).collect();
    assert!(renders.is_empty(), "renders of the splats model asked of the server: {renders:?}");
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
}
