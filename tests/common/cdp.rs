//! A headless Chromium driven over the DevTools protocol: launch it on
//! 127.0.0.1 with a throw-away profile, attach to its page, call methods,
//! evaluate JavaScript, send real mouse events, set file inputs, take
//! screenshots, and collect every JavaScript error the page reports
//! (exceptions, `console.error`, error log entries such as failed loads)
//! and, once asked (`record_requests`), the URL of every request it sends.
//!
//! Every wait is bounded. A missing browser is a failure, not a skip: the
//! browser tests exist to run it (CI installs the Debian package
//! `chromium`; `CHROMIUM_BIN` names another binary).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use tungstenite::{Message, WebSocket};

pub struct Browser {
    child: Child,
    port: u16,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts headless Chromium with a `width x height` window; panics,
    /// saying how to install it, when it cannot.
    pub fn launch(width: u32, height: u32) -> Browser {
        let bin = std::env::var("CHROMIUM_BIN").unwrap_or_else(|_| "chromium".into());
        let profile = tempfile::tempdir().unwrap();
        let mut child = Command::new(&bin)
            .args([
                "--headless=new",
                "--no-sandbox", // CI runs as root
                "--disable-gpu",
                // WebGL (the splat viewer) on the software renderer,
                // SwiftShader: asked for, as Chromium no longer falls back
                // to it by itself in future versions.
                "--enable-unsafe-swiftshader",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-extensions",
                "--hide-scrollbars",
                "--remote-debugging-address=127.0.0.1",
                "--remote-debugging-port=0",
                &format!("--window-size={width},{height}"),
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start '{bin}' ({e}): the browser tests need headless Chromium \
                     (apt-get install chromium, as scripts/setup does, or set CHROMIUM_BIN)"
                )
            });
        // Chromium prints `DevTools listening on ws://127.0.0.1:PORT/...`.
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(rest) = line.split("ws://127.0.0.1:").nth(1) {
                    let _ = tx.send(rest.split('/').next().unwrap_or("").to_string());
                }
            }
        });
        let port = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(p) => p.parse().unwrap(),
            Err(_) => {
                let _ = child.kill();
                panic!("'{bin}' did not open its DevTools port within 60 s");
            }
        };
        Browser { child, port, _profile: profile }
    }

    /// The browser's first page.
    pub fn page(&self) -> Page {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            let list: Value = serde_json::from_str(&http_get(self.port, "/json/list")).unwrap();
            if let Some(url) = list
                .as_array()
                .and_then(|l| l.iter().find(|t| t["type"] == "page"))
                .and_then(|t| t["webSocketDebuggerUrl"].as_str())
            {
                return Page::connect(url);
            }
            assert!(Instant::now() < deadline, "Chromium has no page target: {list}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A GET to the DevTools HTTP endpoint (HTTP/1.1: it ignores 1.0, and
/// keeps the connection open, so the body is read by its length).
fn http_get(port: u16, path: &str) -> String {
    let mut s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n").unwrap();
    let mut reader = BufReader::new(s);
    let mut length = 0usize;
    loop {
        let mut line = String::new();
        reader.read_line(&mut line).unwrap();
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':')
            && k.eq_ignore_ascii_case("content-length")
        {
            length = v.trim().parse().unwrap();
        }
    }
    let mut body = vec![0u8; length];
    reader.read_exact(&mut body).unwrap();
    String::from_utf8(body).unwrap()
}

pub struct Page {
    ws: WebSocket<TcpStream>,
    next_id: u64,
    /// JavaScript errors the page reported, in order.
    pub errors: Vec<String>,
    /// URLs of the requests the page sent since `record_requests` (its
    /// own, not its workers'), in order.
    pub requests: Vec<String>,
}

impl Page {
    fn connect(url: &str) -> Page {
        let addr = url.trim_start_matches("ws://").split('/').next().unwrap();
        let stream = TcpStream::connect(addr).unwrap();
        let (ws, _) = tungstenite::client(url, stream).unwrap();
        ws.get_ref().set_read_timeout(Some(Duration::from_millis(5))).unwrap();
        let mut page = Page { ws, next_id: 0, errors: Vec::new(), requests: Vec::new() };
        for domain in ["Page.enable", "Runtime.enable", "Log.enable", "DOM.enable"] {
            page.call(domain, json!({}));
        }
        page
    }

    /// Calls a DevTools method and returns its result (panics on an error
    /// answer, or after 120 s).
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        self.next_id += 1;
        let id = self.next_id;
        let text = json!({ "id": id, "method": method, "params": params }).to_string();
        self.ws.send(Message::text(text)).unwrap();
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            assert!(Instant::now() < deadline, "{method}: no answer within 120 s");
            if let Some(m) = self.read()
                && m["id"] == id
            {
                assert!(m.get("error").is_none(), "{method}: {}", m["error"]);
                return m["result"].clone();
            }
        }
    }

    /// One message, or `None` after the socket's read timeout. Events are
    /// checked for errors here.
    fn read(&mut self) -> Option<Value> {
        match self.ws.read() {
            Ok(Message::Text(t)) => {
                let m: Value = serde_json::from_str(t.as_str()).unwrap();
                self.note(&m);
                Some(m)
            }
            Ok(_) => None,
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) =>
            {
                None
            }
            Err(e) => panic!("DevTools connection: {e}"),
        }
    }

    fn note(&mut self, m: &Value) {
        let p = &m["params"];
        match m["method"].as_str() {
            Some("Runtime.exceptionThrown") => {
                let d = &p["exceptionDetails"];
                let text = d["exception"]["description"].as_str().or(d["text"].as_str()).unwrap_or("?");
                self.errors.push(format!("exception: {text} ({}:{})", d["url"], d["lineNumber"]));
            }
            Some("Runtime.consoleAPICalled") if p["type"] == "error" => {
                let args: Vec<String> =
                    p["args"].as_array().into_iter().flatten().map(|a| a["value"].to_string()).collect();
                self.errors.push(format!("console.error: {}", args.join(" ")));
            }
            Some("Log.entryAdded") if p["entry"]["level"] == "error" => {
                self.errors.push(format!("log: {} ({})", p["entry"]["text"], p["entry"]["url"]));
            }
            Some("Network.requestWillBeSent") => {
                self.requests.push(p["request"]["url"].as_str().unwrap_or("?").to_string());
            }
            _ => {}
        }
    }

    /// Records the URL of every request the page sends from now on (in
    /// `requests`).
    pub fn record_requests(&mut self) {
        self.call("Network.enable", json!({}));
    }

    /// Reads pending events for `d` (to collect errors while waiting).
    pub fn pause(&mut self, d: Duration) {
        let end = Instant::now() + d;
        while Instant::now() < end {
            self.read();
        }
    }

    pub fn goto(&mut self, url: &str) {
        self.call("Page.navigate", json!({ "url": url }));
        self.wait_for("document.body && document.body.dataset.ready === 'true'", 30.0);
    }

    /// Evaluates an expression (promises awaited) and returns its value.
    pub fn eval(&mut self, expr: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({ "expression": expr, "returnByValue": true, "awaitPromise": true, "userGesture": true }),
        );
        assert!(r.get("exceptionDetails").is_none(), "{expr}: {}", r["exceptionDetails"]);
        r["result"]["value"].clone()
    }

    /// Polls `expr` until it is truthy; panics after `secs` with its last
    /// value and `describe` evaluated.
    pub fn wait_for(&mut self, expr: &str, secs: f64) -> Value {
        let deadline = Instant::now() + Duration::from_secs_f64(secs);
        loop {
            let v = self.eval(expr);
            let truthy = !(v.is_null() || v == false || v == 0 || v == "");
            if truthy {
                return v;
            }
            assert!(
                Instant::now() < deadline,
                "waited {secs} s for `{expr}` (last {v}); status line: {}; errors: {:?}",
                self.eval("document.getElementById('status') && document.getElementById('status').textContent"),
                self.errors
            );
            self.pause(Duration::from_millis(100));
        }
    }

    pub fn click(&mut self, selector: &str) {
        let s = serde_json::to_string(selector).unwrap();
        let found = self.eval(&format!(
            "(() => {{ const e = document.querySelector({s}); if (!e) return false; e.click(); return true; }})()"
        ));
        assert_eq!(found, true, "no element {selector}");
    }

    /// Sets an input's value as a user would (an `input` and a `change` event).
    pub fn fill(&mut self, selector: &str, value: &str) {
        let (s, v) = (serde_json::to_string(selector).unwrap(), serde_json::to_string(value).unwrap());
        let found = self.eval(&format!(
            "(() => {{ const e = document.querySelector({s}); if (!e) return false; e.value = {v}; \
             e.dispatchEvent(new Event('input', {{bubbles: true}})); e.dispatchEvent(new Event('change', {{bubbles: true}})); return true; }})()"
        ));
        assert_eq!(found, true, "no element {selector}");
    }

    /// Gives a file input these files, as choosing them in a dialog would.
    pub fn set_files(&mut self, selector: &str, files: &[&Path]) {
        let root = self.call("DOM.getDocument", json!({}))["root"]["nodeId"].clone();
        let node = self.call("DOM.querySelector", json!({ "nodeId": root, "selector": selector }))["nodeId"].clone();
        assert!(node != 0, "no element {selector}");
        let files: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
        self.call("DOM.setFileInputFiles", json!({ "nodeId": node, "files": files }));
    }

    /// The centre of an element in page coordinates.
    pub fn centre_of(&mut self, selector: &str) -> (f64, f64) {
        let s = serde_json::to_string(selector).unwrap();
        let v = self.eval(&format!(
            "(() => {{ const r = document.querySelector({s}).getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; }})()"
        ));
        (v[0].as_f64().unwrap(), v[1].as_f64().unwrap())
    }

    fn mouse(&mut self, kind: &str, x: f64, y: f64, buttons: u32) {
        let button = if kind == "mouseMoved" && buttons == 0 { "none" } else { "left" };
        self.call(
            "Input.dispatchMouseEvent",
            json!({ "type": kind, "x": x, "y": y, "button": button, "buttons": buttons, "clickCount": 1 }),
        );
    }

    /// A real mouse drag from `from` by `(dx, dy)` in `steps` moves, `pause` apart.
    pub fn drag(&mut self, from: (f64, f64), by: (f64, f64), steps: u32, pause: Duration) {
        self.mouse("mousePressed", from.0, from.1, 1);
        for k in 1..=steps {
            let f = k as f64 / steps as f64;
            self.mouse("mouseMoved", from.0 + by.0 * f, from.1 + by.1 * f, 1);
            self.pause(pause);
        }
        self.mouse("mouseReleased", from.0 + by.0, from.1 + by.1, 0);
    }

    /// The page's pixels in a rectangle of CSS pixels (as composited on
    /// screen, at a scale of 1).
    pub fn capture(&mut self, x: f64, y: f64, width: f64, height: f64) -> image::RgbaImage {
        let clip = json!({ "x": x, "y": y, "width": width, "height": height, "scale": 1 });
        let r = self.call("Page.captureScreenshot", json!({ "format": "png", "clip": clip }));
        let png = base64(r["data"].as_str().unwrap());
        image::load_from_memory_with_format(&png, image::ImageFormat::Png).unwrap().to_rgba8()
    }

    /// Saves a PNG screenshot of the viewport (or of the whole page).
    pub fn screenshot(&mut self, path: &Path, full_page: bool) {
        let r = self.call("Page.captureScreenshot", json!({ "format": "png", "captureBeyondViewport": full_page }));
        let png = base64(r["data"].as_str().unwrap());
        assert!(png.starts_with(b"\x89PNG"), "not a PNG");
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).unwrap();
        }
        std::fs::write(path, png).unwrap();
    }
}

/// Standard base64 (with padding) to bytes.
pub fn base64(s: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s.bytes().filter(|c| *c != b'=' && !c.is_ascii_whitespace()).collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let v = chunk.iter().enumerate().fold(0u32, |acc, (i, c)| acc | (value(*c) as u32) << (18 - 6 * i));
        out.extend(&v.to_be_bytes()[1..chunk.len()]);
    }
    out
}
