//! Training with transient occluders dropped, through the page: the job
//! panel says what was dropped and shows every training photo's mask.

use std::time::Duration;

use crate::common::cdp::Browser;
use crate::common::{Svc, config, llff_files, zip_of};
use crate::{runtime, screenshot};

#[test]
fn the_training_page_shows_what_was_dropped_as_transient() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let browser = Browser::launch(1200, 1000);
    let mut page = browser.page();
    page.goto(&svc.url("/"));
    let zip = tempfile::tempdir().unwrap();
    let zip_path = zip.path().join("ball.zip");
    std::fs::write(&zip_path, zip_of(&llff_files())).unwrap();
    page.set_files("#file-input", &[&zip_path]);
    page.wait_for("document.querySelectorAll('#scene-list li').length === 1", 30.0);
    page.click("#scene-list li button");
    page.wait_for("!document.getElementById('training').hidden", 30.0);
    page.fill("#train-model", "capture-tiny");
    page.fill("#train-budget-kind", "steps");
    page.fill("#train-budget", "60");
    page.eval("document.getElementById('train-bake').checked = false");
    // Dropping transients is the default (capture models).
    assert_eq!(page.eval("document.getElementById('train-transients').checked"), true);
    page.click("#train-start");
    page.wait_for("!document.getElementById('transients').hidden", 60.0);
    let line = page.eval("document.getElementById('transients-line').textContent");
    let line = line.as_str().unwrap();
    assert!(line.contains("% of the training pixels dropped, in "), "{line}");
    // "... in K of N photos": N is the scene's training photos.
    let n: usize = line.rsplit(" of ").next().and_then(|r| r.split(' ').next()).and_then(|n| n.parse().ok()).unwrap();
    let (_, scene) = rt.block_on(svc.get("/v1/scenes"));
    assert_eq!(Some(n as u64), scene[0]["images"]["train"].as_u64(), "{line}: {scene}");
    page.click("#transients-show");
    // Every photo's mask, loaded at the photo's size.
    let loaded = format!(
        "(() => {{ const i = [...document.querySelectorAll('#transients-list img')]; \
         return i.length === {n} && i.every((m) => m.complete && m.naturalWidth === 16); }})()"
    );
    page.wait_for(&loaded, 30.0);
    let caption = page.eval("document.querySelector('#transients-list figcaption').textContent");
    assert!(caption.as_str().unwrap().contains("%"), "{caption}");
    screenshot(&mut page, "transients", false);
    page.pause(Duration::from_millis(300));
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}
