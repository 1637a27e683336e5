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
struct StaticServer {
    child: Child,
    url: String,
}

impl StaticServer {
    fn start(dir: &std::path::Path) -> StaticServer {
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
fn look_at(eye: [f64; 3], at: [f64; 3], up: [f64; 3]) -> [[f64; 4]; 3] {
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
        let (s, scene) = svc.post_json("/v1/demo", json!({})).await;
        assert_eq!(s, 201, "{scene}");
        let body = json!({ "scene_id": scene["id"], "model": "instant-tiny", "budget": { "steps": 300 }, "seed": 1 });
        let (s, train) = svc.post_json("/v1/jobs", body).await;
        assert_eq!(s, 202, "{train}");
        let done = |v: &Value| !matches!(v["status"].as_str(), Some("queued" | "running"));
        let train = svc.wait_job(train["id"].as_str().unwrap(), 300.0, done).await;
        assert_eq!(train["status"], "succeeded", "{train}");
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

    // The exported site on a plain static file server.
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
