//! The by-hand trial of issue 15, as a new user would do it: a real dataset
//! uploaded through the page, trained for 60 s, then dragged in the viewer,
//! measuring the time from a drag to the first updated image and from the
//! end of a drag to the full-resolution image (the page's own
//! `window.radianceStats`). Ignored: it needs a dataset folder and a
//! built server binary, and takes two minutes.
//!
//!     TRIAL_DATA=/path/to/nerf_synthetic/lego TRIAL_BIN=target/release/radiance \
//!         cargo test --release --test browser trial -- --ignored --nocapture

use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common::cdp::Browser;
use crate::common::{files, zip_of};
use crate::screenshot;

fn percentile(v: &[f64], p: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * p).round() as usize]
}

#[test]
#[ignore = "needs TRIAL_DATA and TRIAL_BIN; run by hand"]
fn trial_on_a_real_dataset() {
    let dataset = std::env::var("TRIAL_DATA").expect("TRIAL_DATA: a dataset folder");
    let bin = std::env::var("TRIAL_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_radiance").into());
    let seconds: f64 = std::env::var("TRIAL_SECONDS").map_or(60.0, |s| s.parse().unwrap());
    let work = tempfile::tempdir().unwrap();
    let zip_path = work.path().join("dataset.zip");
    std::fs::write(&zip_path, zip_of(&files(std::path::Path::new(&dataset)))).unwrap();
    let mut server = std::process::Command::new(&bin)
        .args(["serve", "--addr", "127.0.0.1:0", "--threads", "2", "--data-dir"])
        .arg(work.path().join("data"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(&mut std::io::BufReader::new(server.stdout.take().unwrap()), &mut line).unwrap();
    let base = line.trim().strip_prefix("listening on ").unwrap().to_string();

    let browser = Browser::launch(1200, 1000);
    let mut page = browser.page();
    page.goto(&format!("{base}/"));
    let t0 = Instant::now();
    page.set_files("#file-input", &[&zip_path]);
    page.wait_for("document.querySelectorAll('#scene-list li').length === 1", 300.0);
    println!(
        "upload + check: {:.1} s; {}",
        t0.elapsed().as_secs_f64(),
        page.eval("document.querySelector('#scene-list li').textContent")
    );
    page.click("#scene-list li button");
    page.fill("#train-model", "instant");
    page.fill("#train-budget-kind", "seconds");
    page.fill("#train-budget", &seconds.to_string());
    page.click("#train-start");
    page.wait_for(
        "['succeeded', 'failed', 'canceled'].includes(document.getElementById('job-line').dataset.status)",
        seconds + 300.0,
    );
    println!("training: {}", page.eval("document.getElementById('job-line').textContent"));
    page.pause(Duration::from_secs(3)); // the last preview
    screenshot(&mut page, "trial-training", false);

    page.click("#job-view");
    page.wait_for("document.getElementById('view-img').dataset.full === 'true'", 60.0);
    page.pause(Duration::from_secs(1));
    page.eval("window.radianceStats.firstImageMs = []; window.radianceStats.fullImageMs = []; window.radianceStats.renders = []");
    let centre = page.centre_of("#stage");
    for k in 0..10 {
        let before = page.eval("document.getElementById('view-img').dataset.hash");
        let dir = if k % 2 == 0 { 1.0 } else { -1.0 };
        // A drag at 60 mouse events per second.
        page.drag(centre, (dir * 160.0, 30.0 * dir), 30, Duration::from_millis(16));
        page.wait_for(
            &format!(
                "(() => {{ const i = document.getElementById('view-img'); return i.dataset.hash !== {before} && i.dataset.full === 'true'; }})()"
            ),
            30.0,
        );
        page.pause(Duration::from_millis(300));
    }
    screenshot(&mut page, "trial-viewer", false);
    let stats: Value = page.eval("window.radianceStats");
    let ms = |k: &str| -> Vec<f64> { stats[k].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect() };
    let (first, full) = (ms("firstImageMs"), ms("fullImageMs"));
    let renders = stats["renders"].as_array().unwrap();
    let small: Vec<f64> = renders.iter().filter(|r| r["full"] == false).map(|r| r["ms"].as_f64().unwrap()).collect();
    let big: Vec<f64> = renders.iter().filter(|r| r["full"] == true).map(|r| r["ms"].as_f64().unwrap()).collect();
    let size =
        |full: bool| renders.iter().find(|r| r["full"] == full).map(|r| format!("{}x{}", r["width"], r["height"]));
    println!("drags: {}", first.len());
    println!(
        "drag -> first image (ms): median {:.0}, p90 {:.0}, max {:.0}",
        percentile(&first, 0.5),
        percentile(&first, 0.9),
        percentile(&first, 1.0)
    );
    println!(
        "still -> full image (ms): median {:.0}, p90 {:.0}, max {:.0}",
        percentile(&full, 0.5),
        percentile(&full, 0.9),
        percentile(&full, 1.0)
    );
    println!(
        "reduced renders {:?}: {} requests, median {:.0} ms round trip",
        size(false),
        small.len(),
        percentile(&small, 0.5)
    );
    println!(
        "full renders {:?}: {} requests, median {:.0} ms round trip",
        size(true),
        big.len(),
        percentile(&big, 0.5)
    );
    assert!(page.errors.is_empty(), "{:#?}", page.errors);
    drop(browser);
    let _ = server.kill();
    let _ = server.wait();
}
