//! A server with an API key: the page asks for it once and keeps it for the
//! browser session (the tab), and sends it with every request.

use crate::common::cdp::Browser;
use crate::common::{Svc, config};
use crate::runtime;

#[test]
fn the_page_asks_for_the_api_key_once_per_session() {
    let rt = runtime();
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.api_key = Some("s3cret".into());
    let svc = rt.block_on(Svc::start(cfg));
    let browser = Browser::launch(1000, 800);
    let mut page = browser.page();
    page.goto(&svc.url("/"));
    page.wait_for("document.getElementById('key-dialog').open", 10.0);
    page.fill("#key-input", "s3cret");
    page.eval("document.getElementById('key-form').requestSubmit()");
    // Once the key is in, the scenes load: none, so the demo is offered.
    page.wait_for("!document.getElementById('key-dialog').open && !document.getElementById('demo-offer').hidden", 10.0);
    assert_eq!(page.eval("sessionStorage.getItem('radiance-api-key')"), "s3cret");
    // Reloaded in the same tab: no question asked.
    page.goto(&svc.url("/"));
    page.wait_for("!document.getElementById('demo-offer').hidden", 10.0);
    assert_eq!(page.eval("document.getElementById('key-dialog').open"), false);
    // The 401s before the key was given are network errors the browser
    // logs; nothing else may be.
    let unexpected: Vec<&String> = page.errors.iter().filter(|e| !e.contains("status of 401")).collect();
    assert!(unexpected.is_empty(), "the page reported JavaScript errors: {unexpected:#?}");
    drop(browser);
    rt.block_on(svc.stop());
}
