//! A splats model as a static web site: a folder (or a zip of one) that
//! any static web host serves as it is, with no server of ours behind it.
//! `GET /v1/models/{id}/export?format=html` and `radiance export --format
//! html` write it:
//!
//! - `index.html`: a full-window canvas that opens at the model's default
//!   view (the orbit at azimuth 0, the training cameras' elevation,
//!   distance and field of view, as `GET /v1/models/{id}/render` without a
//!   camera), turned with the mouse, the wheel and touch;
//! - `splats.js` and `api.js` (the web app's viewer and the fetch helper
//!   it imports), `vendor/` (Spark and three.js, with their licences), as
//!   the server serves them (`api/web.rs`);
//! - `scene.spz`: the splats (Niantic's SPZ, the smallest file that keeps
//!   their spherical-harmonic colours, which the viewer draws).
//!
//! The default view's drawing buffer is the training cameras' size, so
//! what the page draws is what the server renders for the same camera.

use std::io::{self, Seek, Write};
use std::path::Path;

use serde_json::json;

use super::web::ASSETS;
use crate::engine::front::{Camera, write_atomic};
use crate::records::ViewDefaults;

/// The files of the site from the web app's: the viewer and what it imports.
const VIEWER_FILES: [&str; 2] = ["splats.js", "api.js"];

/// The splat file's name in the site.
pub const SPLAT_FILE: &str = "scene.spz";

/// The camera the page opens at: the model's default view.
pub fn default_camera(view: &ViewDefaults) -> Option<Camera> {
    let pose = view.orbit(view.elevation, view.radius).pose(0.0)?;
    let (width, height) = view.frame_size(None, None);
    Some(Camera::from_fov(width, height, view.fov.to_radians(), pose))
}

/// The page: the viewer on a canvas of the camera's size, at the camera,
/// turning around the scene's centre about its up axis.
pub fn index_html(title: &str, camera: &Camera, view: &ViewDefaults) -> String {
    let setup = json!({
        "c2w": camera.c2w,
        "intrinsics": {
            "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
            "width": camera.width, "height": camera.height,
        },
        "up": view.up,
        "target": view.centre,
        "near": view.near.filter(|n| *n > 0.0).unwrap_or((view.radius * 0.01).max(1e-4)),
        "far": (view.far * 4.0).max(view.radius * 10.0),
    });
    let title = escape(title);
    format!(
        r#"<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>{title}</title>
<script type="importmap">
{{ "imports": {{ "three": "./vendor/three/three.module.min.js", "three/addons/": "./vendor/three/addons/" }} }}
</script>
<style>
  html, body {{ margin: 0; height: 100%; background: #fff; font: 14px system-ui, sans-serif; }}
  main {{ display: flex; height: 100%; align-items: center; justify-content: center; }}
  canvas {{ max-width: 100vw; max-height: 100vh; touch-action: none; outline: none; }}
  p {{ position: fixed; bottom: 0; left: 0; margin: 0.5em; color: #555; }}
</style>
</head>
<body>
<main><canvas id="splats" tabindex="0" aria-label="{title}: drag to turn, wheel or pinch to zoom, right-drag to pan"></canvas></main>
<p id="status">Loading the splats...</p>
<script type="module">
import {{ SplatView }} from './splats.js';
const setup = {setup};
const canvas = document.getElementById('splats');
const k = setup.intrinsics;
canvas.style.aspectRatio = `${{k.width}} / ${{k.height}}`;
canvas.style.width = `${{k.width}}px`;
const view = new SplatView(canvas, {{ background: [1, 1, 1], up: setup.up }});
window.view = view;
view.setCamera(setup.c2w, k, {{ near: setup.near, far: setup.far, target: setup.target }});
try {{
  const res = await fetch('{SPLAT_FILE}');
  if (!res.ok) throw new Error(`{SPLAT_FILE}: ${{res.status}} ${{res.statusText}}`);
  const n = await view.show(new Uint8Array(await res.arrayBuffer()), 'spz');
  document.getElementById('status').textContent = `${{n}} Gaussians: drag to turn, wheel or pinch to zoom, right-drag to pan.`;
  await view.settled();
  document.body.dataset.ready = 'true';
}} catch (e) {{
  document.getElementById('status').textContent = `Cannot show the splats: ${{e.message}}`;
  document.body.dataset.ready = 'error';
}}
</script>
</body>
</html>
"#,
        setup = setup
    )
}

/// The site's files, path and bytes: the page, the viewer, the vendored
/// libraries and their licences, the splats (`spz`: their `.spz` bytes).
pub fn files(title: &str, view: &ViewDefaults, spz: Vec<u8>) -> io::Result<Vec<(String, Vec<u8>)>> {
    let camera = default_camera(view)
        .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidData, "the model's default view gives no camera"))?;
    let mut out = vec![("index.html".to_string(), index_html(title, &camera, view).into_bytes())];
    // The splat viewer's libraries (not `<model-viewer>`, which draws meshes).
    let splat_lib = |n: &str| n.starts_with("vendor/spark/") || n.starts_with("vendor/three/");
    for a in ASSETS.iter().filter(|a| VIEWER_FILES.contains(&a.name) || splat_lib(a.name)) {
        out.push((a.name.to_string(), a.body.as_bytes().to_vec()));
    }
    out.push((SPLAT_FILE.to_string(), spz));
    Ok(out)
}

/// `text` for HTML, in an element or a quoted attribute.
fn escape(text: &str) -> String {
    text.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// A mesh's site: `index.html` showing `model.glb` in `<model-viewer>`
/// (vendored, with its licence), the window filled, with its AR button
/// (`model.usdz` for AR Quick Look), as the web app's mesh panel shows it.
pub fn mesh_files(title: &str, glb: Vec<u8>, usdz: Vec<u8>) -> Vec<(String, Vec<u8>)> {
    let title = escape(title);
    let page = format!(
        r#"<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title>
<link rel="icon" href="data:,">
<script type="module" src="./vendor/model-viewer/model-viewer.min.js"></script>
<style>html, body {{ margin: 0; height: 100%; background: #fff; }} model-viewer {{ width: 100%; height: 100%; }}</style>
</head>
<body>
<model-viewer src="model.glb" ios-src="model.usdz" alt="{title}" camera-controls touch-action="pan-y"
              tone-mapping="none" shadow-intensity="0" ar ar-modes="webxr scene-viewer quick-look"></model-viewer>
<script>
// Says when the mesh is shown (or cannot be), for scripts that wait on it.
const viewer = document.querySelector('model-viewer');
viewer.addEventListener('load', () => {{ document.body.dataset.ready = 'true'; }});
viewer.addEventListener('error', () => {{ document.body.dataset.ready = 'error'; }});
</script>
</body>
</html>
"#
    );
    let mut out = vec![("index.html".to_string(), page.into_bytes())];
    for a in ASSETS.iter().filter(|a| a.name.starts_with("vendor/model-viewer/")) {
        out.push((a.name.to_string(), a.body.as_bytes().to_vec()));
    }
    out.push(("model.glb".to_string(), glb));
    out.push(("model.usdz".to_string(), usdz));
    out
}

/// The site as a zip of one folder, `folder/`.
pub fn write_zip(folder: &str, files: &[(String, Vec<u8>)], out: impl Write + Seek) -> io::Result<()> {
    let mut zip = zip::ZipWriter::new(out);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .unix_permissions(0o644);
    for (name, bytes) in files {
        // The splats and the GLB (its texture a JPEG) barely compress:
        // stored, they unzip faster.
        let options = match name.as_str() {
            SPLAT_FILE | "model.glb" => options.compression_method(zip::CompressionMethod::Stored),
            _ => options,
        };
        zip.start_file(format!("{folder}/{name}"), options).map_err(io::Error::other)?;
        zip.write_all(bytes)?;
    }
    zip.finish().map_err(io::Error::other)?;
    Ok(())
}

/// The site as a folder `dir` (made if missing): each file written
/// atomically.
pub fn write_dir(dir: &Path, files: &[(String, Vec<u8>)]) -> io::Result<()> {
    for (name, bytes) in files {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)?;
        }
        write_atomic(&path, bytes)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_site_has_the_page_the_viewer_its_libraries_with_licences_and_the_splats() {
        let view = crate::records::sample_view();
        let files = files("a <model>", &view, vec![1, 2, 3]).unwrap();
        let names: Vec<&str> = files.iter().map(|f| f.0.as_str()).collect();
        for want in ["index.html", "splats.js", "api.js", "vendor/spark/LICENSE", "vendor/three/LICENSE", SPLAT_FILE] {
            assert!(names.contains(&want), "{want} missing from {names:?}");
        }
        assert!(names.contains(&"vendor/spark/spark.module.min.js"));
        let page = String::from_utf8(files[0].1.clone()).unwrap();
        assert!(page.contains("a &lt;model&gt;") && page.contains("./vendor/three/three.module.min.js"));
        let mut zip = std::io::Cursor::new(Vec::new());
        write_zip("site", &files, &mut zip).unwrap();
        let mut read = zip::ZipArchive::new(std::io::Cursor::new(zip.into_inner())).unwrap();
        let mut splat = Vec::new();
        std::io::Read::read_to_end(&mut read.by_name("site/scene.spz").unwrap(), &mut splat).unwrap();
        assert_eq!(splat, [1, 2, 3]);
    }

    #[test]
    fn the_mesh_site_has_the_page_model_viewer_with_its_licence_and_both_files() {
        let files = mesh_files("a \"<mesh>\"", b"glTF".to_vec(), b"PK".to_vec());
        let names: Vec<&str> = files.iter().map(|f| f.0.as_str()).collect();
        assert_eq!(
            names,
            [
                "index.html",
                "vendor/model-viewer/model-viewer.min.js",
                "vendor/model-viewer/LICENSE",
                "model.glb",
                "model.usdz"
            ]
        );
        let page = String::from_utf8(files[0].1.clone()).unwrap();
        assert!(page.contains(r#"alt="a &quot;&lt;mesh&gt;&quot;""#), "{page}");
        assert!(page.contains(r#"src="model.glb" ios-src="model.usdz""#));
    }
}
