//! The splat viewer (`web/splats.js`, Spark on WebGL2) in headless Chromium
//! on the software renderer: a `.splat` file written here (four clusters of
//! small Gaussians, red, green, blue and yellow, at known points) is
//! fetched once from a plain file server, drawn from a camera given in our
//! convention (c2w rows, OpenGL axes; pinhole fx, fy, cx, cy in pixels),
//! and each cluster's colour lands where our own projection of its centre
//! says, within a pixel or two. Dragging and the wheel then change the
//! picture with no further request from the page.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde_json::Value;

use crate::common::cdp::Browser;
use crate::common::{Svc, config};
use crate::realtime::look_at;
use crate::{runtime, screenshot};

/// One Gaussian: position, scale (linear), colour RGBA, rotation (w, x, y, z).
struct Gaussian {
    pos: [f32; 3],
    scale: [f32; 3],
    rgba: [u8; 4],
    rot: [f32; 4],
}

/// The 32-byte antimatter15 `.splat` layout: position 3 x f32 LE, scale
/// 3 x f32 LE, colour RGBA 4 x u8, rotation w, x, y, z as round(q * 128 +
/// 128) clamped to 0..255.
fn splat_bytes(gaussians: &[Gaussian]) -> Vec<u8> {
    let mut out = Vec::with_capacity(32 * gaussians.len());
    for g in gaussians {
        for v in g.pos.iter().chain(&g.scale) {
            out.extend(v.to_le_bytes());
        }
        out.extend(g.rgba);
        let norm = g.rot.iter().map(|q| q * q).sum::<f32>().sqrt();
        out.extend(g.rot.map(|q| (q / norm * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8));
    }
    out
}

/// The clusters: name, centre, colour.
const CLUSTERS: [(&str, [f32; 3], [u8; 3]); 4] = [
    ("red", [0.6, 0.0, 0.0], [220, 30, 30]),
    ("green", [0.0, 0.6, 0.0], [30, 170, 30]),
    ("blue", [0.0, 0.0, 0.6], [30, 30, 220]),
    ("yellow", [-0.5, -0.3, 0.0], [230, 210, 20]),
];

/// 125 Gaussians per cluster, on a 5x5x5 grid 0.02 apart around its centre,
/// each a little flattened and turned (a rotation about z), nearly opaque.
fn scene() -> Vec<Gaussian> {
    let mut out = Vec::new();
    for (_, c, rgb) in CLUSTERS {
        for i in 0..125 {
            let o = [(i % 5) as f32 - 2.0, ((i / 5) % 5) as f32 - 2.0, (i / 25) as f32 - 2.0];
            let half = 0.3f32;
            out.push(Gaussian {
                pos: [c[0] + 0.02 * o[0], c[1] + 0.02 * o[1], c[2] + 0.02 * o[2]],
                scale: [0.018, 0.012, 0.015],
                rgba: [rgb[0], rgb[1], rgb[2], 240],
                rot: [half.cos(), 0.0, 0.0, half.sin()],
            });
        }
    }
    out
}

/// Where our pinhole camera sees world point `p`: pixel coordinates
/// (x right, y down; pixel (i, j) centred at (i + 0.5, j + 0.5)).
fn project(c2w: &[[f64; 4]; 3], k: [f64; 4], p: [f32; 3]) -> (f64, f64) {
    let d = [0, 1, 2].map(|i| p[i] as f64 - c2w[i][3]);
    // Camera coordinates: R^T d.
    let cam = [0, 1, 2].map(|j| (0..3).map(|i| c2w[i][j] * d[i]).sum::<f64>());
    let [fx, fy, cx, cy] = k;
    (cx + fx * cam[0] / -cam[2], cy - fy * cam[1] / -cam[2])
}

/// Serves `body` at any path with CORS allowed, counting the requests.
fn file_server(body: Vec<u8>) -> (String, Arc<Mutex<Vec<String>>>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}/models/test/export.splat", listener.local_addr().unwrap());
    let seen = Arc::new(Mutex::new(Vec::new()));
    let log = seen.clone();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { continue };
            let mut reader = BufReader::new(stream.try_clone().unwrap());
            let mut first = String::new();
            let _ = reader.read_line(&mut first);
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 || line.trim().is_empty() {
                    break;
                }
            }
            log.lock().unwrap().push(first.trim().to_string());
            let head = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\
                 Access-Control-Allow-Origin: *\r\nConnection: close\r\n\r\n",
                body.len()
            );
            let _ = stream.write_all(head.as_bytes());
            let _ = stream.write_all(&body);
        }
    });
    (url, seen)
}

/// The canvas's pixels summed up in the page: for each colour, how many
/// pixels are of it and their centroid (pixel centres), and a hash of all.
const MEASURE: &str = "(() => {
  const v = window.view, c = v.canvas;
  const t = document.createElement('canvas'); t.width = c.width; t.height = c.height;
  const g = t.getContext('2d'); g.drawImage(c, 0, 0);
  const d = g.getImageData(0, 0, t.width, t.height).data;
  const kinds = { red: [0, 0, 0], green: [0, 0, 0], blue: [0, 0, 0], yellow: [0, 0, 0] };
  let white = 0, h = 2166136261;
  for (let i = 0; i < d.length; i += 4) {
    const [r, gg, b] = [d[i], d[i + 1], d[i + 2]];
    h = Math.imul(h ^ r ^ (gg << 8) ^ (b << 16), 16777619) >>> 0;
    const p = i / 4, x = (p % t.width) + 0.5, y = Math.floor(p / t.width) + 0.5;
    let k = null;
    if (r > 150 && gg < 110 && b < 110) k = 'red';
    else if (gg > 120 && r < 110 && b < 110) k = 'green';
    else if (b > 150 && r < 110 && gg < 110) k = 'blue';
    else if (r > 150 && gg > 140 && b < 110) k = 'yellow';
    else if (r > 245 && gg > 245 && b > 245) white++;
    if (k) { kinds[k][0]++; kinds[k][1] += x; kinds[k][2] += y; }
  }
  const out = { width: t.width, height: t.height, white, hash: h, frames: v.stats.frames };
  for (const [k, [n, sx, sy]] of Object.entries(kinds)) out[k] = [n, n ? sx / n : null, n ? sy / n : null];
  return out;
})()";

#[test]
fn the_splat_viewer_draws_where_our_camera_says_and_moves_without_the_server() {
    let gaussians = scene();
    let (url, served) = file_server(splat_bytes(&gaussians));
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let browser = Browser::launch(900, 700);
    let mut page = browser.page();
    page.goto(&svc.url("/"));

    // An off-centre principal point, to check that it is honoured.
    let (width, height) = (320u32, 240u32);
    let k = [290.0, 290.0, 150.0, 130.0];
    let c2w = look_at([0.9, 1.1, 2.6], [0.05, 0.1, 0.1], [0.0, 1.0, 0.0]);
    let setup = format!(
        "(async () => {{
           const m = await import('/assets/splats.js');
           const c = document.createElement('canvas');
           c.id = 'splats'; c.tabIndex = 0; c.style.width = '{width}px'; c.style.height = '{height}px';
           document.querySelector('main').replaceChildren(c);
           window.view = new m.SplatView(c, {{ background: [1, 1, 1] }});
           const n = await view.load({url:?});
           view.setCamera({c2w}, {{ fx: {}, fy: {}, cx: {}, cy: {}, width: {width}, height: {height} }}, {{ near: 0.05, far: 50 }});
           await view.settled();
           return n;
         }})()",
        k[0],
        k[1],
        k[2],
        k[3],
        c2w = serde_json::to_string(&c2w).unwrap(),
    );
    page.record_requests();
    let count = page.eval(&setup);
    assert_eq!(count.as_u64(), Some(gaussians.len() as u64), "splats loaded");
    let camera = page.eval("view.getCamera()");
    for (r, row) in c2w.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            let got = camera["c2w"][r][c].as_f64().unwrap();
            assert!((got - v).abs() < 1e-5, "c2w[{r}][{c}]: {got} != {v}");
        }
    }
    assert!(
        (camera["cx"].as_f64().unwrap() - k[2]).abs() < 1e-6 && (camera["cy"].as_f64().unwrap() - k[3]).abs() < 1e-6
    );

    // Spark sorts the splats in a worker: under load, its first sorted
    // frame can come after `settled()`'s quiet spell. Wait for it (20 s at
    // most); the checks below then judge the picture.
    let names = serde_json::to_string(&CLUSTERS.iter().map(|(n, ..)| *n).collect::<Vec<_>>()).unwrap();
    let drawn = format!("(() => {{ const m = {MEASURE}; return {names}.every((k) => m[k][0] >= 30) && m; }})()");
    let before: Value = page.wait_for(&drawn, 20.0);
    screenshot(&mut page, "splats", false);
    assert_eq!((before["width"].as_u64(), before["height"].as_u64()), (Some(width as u64), Some(height as u64)));
    // Background where there are no splats, each cluster where our
    // projection puts its centre.
    assert!(before["white"].as_u64().unwrap() > (width * height) as u64 / 2, "{before}");
    for (name, centre, _) in CLUSTERS {
        let (u, v) = project(&c2w, k, centre);
        let [n, x, y] = [&before[name][0], &before[name][1], &before[name][2]];
        assert!(n.as_u64().unwrap() >= 30, "{name}: {n} pixels of its colour: {before}");
        let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
        assert!(
            (x - u).abs() < 2.0 && (y - v).abs() < 2.0,
            "{name}: drawn around ({x:.2}, {y:.2}), projected at ({u:.2}, {v:.2})"
        );
    }

    // Drag to orbit, then the wheel to zoom: the picture changes each time,
    // and the page asks nothing more of any server.
    let asked = page.requests.len();
    let centre = page.centre_of("#splats");
    page.drag(centre, (80.0, 30.0), 10, Duration::from_millis(30));
    page.eval("view.settled()");
    let dragged = page.eval(MEASURE);
    assert_ne!(dragged["hash"], before["hash"], "dragging did not change the picture");
    assert!(dragged["frames"].as_u64() > before["frames"].as_u64());
    page.call(
        "Input.dispatchMouseEvent",
        serde_json::json!({ "type": "mouseWheel", "x": centre.0, "y": centre.1, "deltaX": 0, "deltaY": -300 }),
    );
    page.eval("view.settled()");
    let zoomed = page.eval(MEASURE);
    assert_ne!(zoomed["hash"], dragged["hash"], "the wheel did not change the picture");
    let coloured = |m: &Value| CLUSTERS.iter().map(|(n, ..)| m[n][0].as_u64().unwrap()).sum::<u64>();
    assert!(coloured(&zoomed) > coloured(&dragged), "zooming in did not enlarge the splats");
    screenshot(&mut page, "splats-moved", false);
    let later: Vec<&String> = page.requests[asked..].iter().filter(|u| u.starts_with("http")).collect();
    assert!(later.is_empty(), "requests after the file was loaded: {later:?}");
    let fetched: Vec<&String> = page.requests.iter().filter(|u| u.contains("export.splat")).collect();
    assert_eq!(fetched, [&url], "the splat file is fetched once");
    assert_eq!(served.lock().unwrap().len(), 1, "file server saw {:?}", served.lock().unwrap());

    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}
