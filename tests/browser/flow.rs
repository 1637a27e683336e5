//! The whole flow through the page: upload, train, view, videos.

use std::time::Duration;

use radiance::engine::dataset::synthetic::BallScene;
use serde_json::Value;

use crate::common::cdp::{Browser, Page};
use crate::common::{Svc, config, files, zip_of};
use crate::{runtime, screenshot};

/// Text of an element, or "" when missing.
fn text(page: &mut Page, selector: &str) -> String {
    let s = serde_json::to_string(selector).unwrap();
    page.eval(&format!("(document.querySelector({s}) || {{}}).textContent || ''")).as_str().unwrap_or("").to_string()
}

fn img_hash(page: &mut Page) -> Value {
    page.eval("document.getElementById('view-img').dataset.hash || null")
}

#[test]
fn upload_train_view_and_make_videos_in_the_browser() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.scheduler.heldout_every = 0.5;
    let svc = rt.block_on(Svc::start(cfg));
    let browser = Browser::launch(1200, 1000);
    let mut page = browser.page();
    page.goto(&svc.url("/"));

    // No scenes: the page offers the demo scene.
    page.wait_for("!document.getElementById('demo-offer').hidden", 10.0);
    screenshot(&mut page, "empty", false);

    // Upload a generated scene as a zip through the file input.
    let scene_dir = tempfile::tempdir().unwrap();
    BallScene { size: 48, views: 16, ..Default::default() }.write_blender(scene_dir.path()).unwrap();
    let zip = tempfile::tempdir().unwrap();
    let zip_path = zip.path().join("ball.zip");
    std::fs::write(&zip_path, zip_of(&files(scene_dir.path()))).unwrap();
    page.set_files("#file-input", &[&zip_path]);
    page.wait_for("document.querySelectorAll('#scene-list li').length === 1", 30.0);
    let card = text(&mut page, "#scene-list li");
    assert!(card.contains("format blender") && card.contains("16 training") && card.contains("48x48"), "{card}");
    assert!(text(&mut page, "#upload-text").contains("stored as scn"), "{}", text(&mut page, "#upload-text"));
    assert_eq!(page.eval("document.getElementById('upload-progress').value"), 1.0);
    assert_eq!(page.eval("document.getElementById('demo-offer').hidden"), true);
    screenshot(&mut page, "scenes", false);

    // Train it: the job's step and the PSNR chart move while it runs.
    page.click("#scene-list li button");
    page.wait_for("!document.getElementById('training').hidden", 30.0);
    page.fill("#train-model", "instant-tiny");
    page.fill("#train-budget-kind", "seconds");
    page.fill("#train-budget", "8");
    // The NeRF viewer is what this test drives: no bake after training.
    page.eval("document.getElementById('train-bake').checked = false");
    page.click("#train-start");
    page.wait_for("document.getElementById('job-line').dataset.status === 'running'", 30.0);
    let mut steps = Vec::new();
    for _ in 0..600 {
        let line = page.eval(
            "[document.getElementById('job-line').dataset.status, +document.getElementById('job-line').dataset.step]",
        );
        let (status, step) = (line[0].as_str().unwrap().to_string(), line[1].as_u64().unwrap());
        if steps.last() != Some(&step) {
            steps.push(step);
        }
        if status != "running" && status != "queued" {
            assert_eq!(status, "succeeded", "{}", text(&mut page, "#job-line"));
            break;
        }
        page.pause(Duration::from_millis(50));
    }
    assert!(steps.len() >= 3 && steps.windows(2).all(|w| w[0] < w[1]), "steps seen: {steps:?}");
    page.wait_for("+document.getElementById('psnr-chart').dataset.points >= 2", 10.0);
    // The preview shown is the 240x240 render the page asked for (the last
    // one, once training has ended, may still be replacing an earlier one).
    page.wait_for(
        "(() => { const i = document.getElementById('preview'); return +i.dataset.count >= 1 && i.complete && i.naturalWidth === 240 && i.naturalHeight === 240; })()",
        20.0,
    );
    let line = text(&mut page, "#job-line");
    assert!(line.contains("held-out PSNR") && line.contains("ETA"), "{line}");
    screenshot(&mut page, "training", false);

    // The viewer: a full image, then a drag changes it, first at reduced
    // size, then at full resolution again.
    page.click("#job-view");
    page.wait_for("document.getElementById('view-img').dataset.full === 'true'", 30.0);
    let before = img_hash(&mut page);
    let centre = page.centre_of("#stage");
    page.drag(centre, (120.0, 40.0), 12, Duration::from_millis(30));
    page.wait_for(&format!("(() => {{ const i = document.getElementById('view-img'); return i.dataset.hash !== '{}' && i.dataset.full === 'true'; }})()", before.as_str().unwrap()), 30.0);
    let stats = page.eval("window.radianceStats");
    assert!(stats["firstImageMs"].as_array().is_some_and(|v| !v.is_empty()), "{stats}");
    assert!(
        stats["renders"].as_array().unwrap().iter().any(|r| r["full"] == false),
        "no reduced image while dragging: {stats}"
    );
    let alt = page.eval("document.getElementById('view-img').alt");
    assert!(alt.as_str().unwrap().contains("degrees azimuth"), "{alt}");
    // Keyboard: an arrow key turns the view too.
    let before = img_hash(&mut page);
    page.eval("document.getElementById('stage').focus()");
    page.call(
        "Input.dispatchKeyEvent",
        serde_json::json!({ "type": "keyDown", "key": "ArrowLeft", "code": "ArrowLeft", "windowsVirtualKeyCode": 37 }),
    );
    page.call(
        "Input.dispatchKeyEvent",
        serde_json::json!({ "type": "keyUp", "key": "ArrowLeft", "code": "ArrowLeft", "windowsVirtualKeyCode": 37 }),
    );
    page.wait_for(&format!("(() => {{ const i = document.getElementById('view-img'); return i.dataset.hash !== '{}' && i.dataset.full === 'true'; }})()", before.as_str().unwrap()), 30.0);
    screenshot(&mut page, "viewer", false);
    // Depth, then back to colour.
    let before = img_hash(&mut page);
    page.fill("#view-output", "depth");
    page.wait_for(&format!("document.getElementById('view-img').dataset.hash !== '{}' && document.getElementById('view-img').alt.includes('depth')", before.as_str().unwrap()), 30.0);
    page.fill("#view-output", "rgb");
    // Two views for a path.
    page.click("#view-add");
    page.drag(centre, (-150.0, 20.0), 6, Duration::from_millis(20));
    page.click("#view-add");
    assert_eq!(page.eval("document.querySelectorAll('#keyframes li').length"), 2);

    // A video along the path and an orbit video, played in the page.
    page.fill("#path-frames", "6");
    page.fill("#path-format", "gif");
    page.click("#path-make");
    page.wait_for("document.querySelector('#video-list li[data-status=\"succeeded\"]')", 60.0);
    let card = text(&mut page, "#video-list li");
    assert!(card.contains("path of 2 views") && card.contains("6 frames"), "{card}");
    page.fill("#video-frames", "8");
    page.fill("#video-width", "48");
    page.fill("#video-height", "48");
    page.fill("#video-format", "gif");
    page.click("#video-make");
    page.wait_for("document.querySelectorAll('#video-list li[data-status=\"succeeded\"]').length === 2", 60.0);
    page.click("#video-list li button");
    page.wait_for("(() => { const g = document.getElementById('player-gif'); return !g.hidden && g.complete && g.naturalWidth === 48; })()", 20.0);
    assert!(page.eval("document.getElementById('player-download').download").as_str().unwrap().ends_with(".gif"));
    screenshot(&mut page, "videos", true);

    page.pause(Duration::from_millis(300));
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}

#[test]
fn the_demo_scene_is_one_click_away() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let browser = Browser::launch(1000, 800);
    let mut page = browser.page();
    page.goto(&svc.url("/"));
    page.wait_for("!document.getElementById('demo-offer').hidden", 10.0);
    page.click("#demo-button");
    // The demo scene is stored and the training form is ready for it.
    page.wait_for(
        "!document.getElementById('training').hidden && document.getElementById('train-scene').value.startsWith('scn')",
        30.0,
    );
    assert_eq!(page.eval("document.getElementById('train-budget').value"), "20");
    let (_, scenes) = rt.block_on(svc.get("/v1/scenes"));
    assert_eq!(scenes.as_array().map(Vec::len), Some(1), "{scenes}");
    assert_eq!(
        (scenes[0]["images"]["train"].as_u64(), &scenes[0]["resolution"]),
        (Some(32), &serde_json::json!([96, 96]))
    );
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}
