//! A photo-only upload through the page: the scene card shows the pose
//! estimation running (COLMAP, for real), then what it found, and the scene
//! becomes trainable.

use radiance::engine::dataset::textured::TexturedScene;

use crate::common::cdp::Browser;
use crate::common::{Svc, config, files, zip_of};
use crate::{runtime, screenshot};

#[test]
fn photos_without_poses_show_their_pose_estimation_in_the_page() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.scheduler.poses = Some(crate::common::poses::setup());
    let svc = rt.block_on(Svc::start(cfg));
    let browser = Browser::launch(1200, 900);
    let mut page = browser.page();
    page.goto(&svc.url("/"));
    page.wait_for("!document.getElementById('demo-offer').hidden", 10.0);

    let photos = tempfile::tempdir().unwrap();
    TexturedScene::default().write_photos(photos.path()).unwrap();
    let zip = tempfile::tempdir().unwrap();
    let zip_path = zip.path().join("photos.zip");
    std::fs::write(&zip_path, zip_of(&files(photos.path()))).unwrap();
    page.set_files("#file-input", &[&zip_path]);

    // While COLMAP runs: the card says so, and the scene cannot be trained
    // yet (read in the same evaluation: the posing may end just after).
    let seen = page.wait_for(
        "(() => { const li = document.querySelector('#scene-list li[data-status=\"posing\"]');
           const p = li && li.querySelector('[data-posing]');
           return p ? [p.textContent, li.querySelector('button').disabled] : null; })()",
        30.0,
    );
    assert!(seen[0].as_str().unwrap().contains("estimating the camera poses of 16 photos with COLMAP"), "{seen}");
    assert_eq!(seen[1], true, "Train is disabled while posing: {seen}");
    screenshot(&mut page, "posing", false);

    // Then the card shows what COLMAP found, and Train is enabled.
    page.wait_for("document.querySelector('#scene-list li[data-status=\"ready\"]') !== null", 120.0);
    let card = page.eval("document.querySelector('#scene-list li').textContent");
    let card = card.as_str().unwrap();
    assert!(card.contains("poses estimated: 16 of 16 photos registered") && card.contains("format colmap"), "{card}");
    assert_eq!(page.eval("document.querySelector('#scene-list li button').disabled"), false);
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}
