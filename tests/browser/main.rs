//! The web app in a real browser: headless Chromium (DevTools protocol,
//! `common::cdp`) against the real server on 127.0.0.1. The tests upload a
//! generated scene through the page, train it and watch the progress, drag
//! the model in the viewer and see the image change, make videos, and fail
//! on any JavaScript error the page reports; the splat viewer draws a
//! generated `.splat` file where its camera says. Screenshots go to
//! `target/tmp/screenshots/` (and to `$RADIANCE_SCREENSHOTS` when set: the
//! README's come from there, `RADIANCE_SCREENSHOTS=docs`).

#[path = "../common/mod.rs"]
mod common;

mod cards;
mod flow;
mod key;
mod mesh;
mod posing;
mod realtime;
mod splats;
mod transients;
mod trial;

use std::path::PathBuf;

/// Where a screenshot is saved (and copied).
pub fn screenshot_paths(name: &str) -> Vec<PathBuf> {
    let mut out = vec![PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("screenshots").join(format!("{name}.png"))];
    if let Ok(dir) = std::env::var("RADIANCE_SCREENSHOTS") {
        out.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(dir).join(format!("web-{name}.png")));
    }
    out
}

pub fn screenshot(page: &mut common::cdp::Page, name: &str, full_page: bool) {
    for p in screenshot_paths(name) {
        page.screenshot(&p, full_page);
    }
}

/// A runtime whose worker threads serve while the test drives the browser
/// from its own thread.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}
