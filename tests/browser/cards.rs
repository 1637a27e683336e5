//! The scenes page: each card shows the scene's name (the archive's file
//! name, or "demo scene") and a thumbnail of one of its photos; the
//! "Uploading" bar is shown only while an upload runs.

use std::time::Duration;

use radiance::engine::dataset::synthetic::BallScene;

use crate::common::cdp::Browser;
use crate::common::{Svc, config, files, zip_of};
use crate::{runtime, screenshot};

/// Whether the upload bar takes up room on the page now.
const BAR_SHOWN: &str = "getComputedStyle(document.getElementById('upload')).display !== 'none'";

/// The card of the scene named `name`: [name, id, thumbnail width, height
/// (as decoded), shown width, whether some pixel of it is not near white].
fn card_js(name: &str) -> String {
    format!(
        "(() => {{ const li = [...document.querySelectorAll('#scene-list li')]
             .find((l) => l.querySelector('.name') && l.querySelector('.name').textContent === {name:?});
           if (!li) return null;
           const img = li.querySelector('img.thumb');
           if (!img || !img.complete || !img.naturalWidth) return null;
           const c = document.createElement('canvas');
           c.width = img.naturalWidth; c.height = img.naturalHeight;
           const g = c.getContext('2d'); g.drawImage(img, 0, 0);
           const d = g.getImageData(0, 0, c.width, c.height).data;
           let coloured = false;
           for (let i = 0; i < d.length; i += 4) if (Math.min(d[i], d[i + 1], d[i + 2]) < 200) coloured = true;
           return [li.querySelector('.name').textContent, li.querySelector('.id').textContent,
                   img.naturalWidth, img.naturalHeight, img.getBoundingClientRect().width, coloured];
         }})()"
    )
}

#[test]
fn scene_cards_show_a_name_and_a_thumbnail_and_the_bar_only_while_uploading() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let svc = rt.block_on(Svc::start(config(data.path())));
    let browser = Browser::launch(1000, 800);
    let mut page = browser.page();
    page.goto(&svc.url("/"));
    page.wait_for("!document.getElementById('demo-offer').hidden", 10.0);
    assert_eq!(page.eval(BAR_SHOWN), false, "the upload bar shows before any upload");

    // Every change of the bar's visibility, as it happens.
    page.eval(
        "window.barSeen = []; new MutationObserver(() => window.barSeen.push(getComputedStyle(document.getElementById('upload')).display))
           .observe(document.getElementById('upload'), { attributes: true, attributeFilter: ['hidden'] }); true",
    );
    let scene_dir = tempfile::tempdir().unwrap();
    BallScene { size: 48, views: 8, ..Default::default() }.write_blender(scene_dir.path()).unwrap();
    let zip = tempfile::tempdir().unwrap();
    let zip_path = zip.path().join("red ball.zip");
    std::fs::write(&zip_path, zip_of(&files(scene_dir.path()))).unwrap();
    page.set_files("#file-input", &[&zip_path]);
    let card = page.wait_for(&card_js("red ball.zip"), 30.0);
    assert!(card[1].as_str().unwrap().starts_with("scn_"), "{card}");
    // The ball's photo at 48x48 (thumbnails are never enlarged), shown 96 px wide.
    assert_eq!((card[2].as_u64(), card[3].as_u64(), card[4].as_f64()), (Some(48), Some(48), Some(96.0)), "{card}");
    assert_eq!(card[5], true, "the thumbnail is blank: {card}");
    page.wait_for(&format!("!({BAR_SHOWN})"), 10.0);
    let seen = page.eval("window.barSeen");
    assert_eq!(seen, serde_json::json!(["flex", "none"]), "the bar showed, then hid: {seen}");
    assert!(
        page.eval("document.getElementById('upload-text').textContent").as_str().unwrap().contains("stored as scn")
    );
    // The API says the same.
    let (_, scenes) = rt.block_on(svc.get("/v1/scenes"));
    assert_eq!(scenes[0]["name"], "red ball.zip", "{scenes}");

    // The demo scene is named too.
    page.click("#demo-button");
    page.wait_for("!document.getElementById('training').hidden", 30.0);
    page.click("#tab-scenes");
    let demo = page.wait_for(&card_js("demo scene"), 30.0);
    assert_eq!(demo[5], true, "{demo}");
    assert_eq!(page.eval(BAR_SHOWN), false);
    page.pause(Duration::from_millis(200));
    screenshot(&mut page, "scene-cards", false);
    assert!(page.errors.is_empty(), "the page reported JavaScript errors: {:#?}", page.errors);
    drop(browser);
    rt.block_on(svc.stop());
}
