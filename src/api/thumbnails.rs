//! `GET /v1/scenes/{id}/thumbnail`: a small JPEG of one of the scene's
//! photos (the first in path order, masks and depth maps left out), for the
//! web app's scene cards.
//!
//! The photo's header is read and checked first (`photos::read_header`: at
//! most `photos::MAX_PIXELS`), then it is decoded, composited on white (as
//! the engine composites transparent images), shrunk to at most
//! [`SIZE`] pixels on its long side (never enlarged) and encoded as JPEG. Thumbnails are
//! kept in memory (a scene's photos never change), at most [`KEPT`] of
//! them, and made two at a time, so a page of cards costs each photo's
//! decoding once.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use axum::body::Bytes;
use axum::extract::{Path as UrlPath, State};
use axum::http::header::{CACHE_CONTROL, CONTENT_TYPE};
use axum::response::IntoResponse;

use super::{ApiError, ApiResult, AppState, Code};
use crate::datadir::ScenePart;
use crate::poses::photos;
use crate::records::{SceneInfo, SceneStatus};

/// The long side of a thumbnail, in pixels.
pub const SIZE: u32 = 192;

/// Thumbnails kept in memory (about 10 KB each).
const KEPT: usize = 512;

fn kept() -> &'static Mutex<HashMap<String, Bytes>> {
    static KEPT_THUMBNAILS: OnceLock<Mutex<HashMap<String, Bytes>>> = OnceLock::new();
    KEPT_THUMBNAILS.get_or_init(Default::default)
}

fn making() -> &'static tokio::sync::Semaphore {
    static MAKING: OnceLock<tokio::sync::Semaphore> = OnceLock::new();
    MAKING.get_or_init(|| tokio::sync::Semaphore::new(2))
}

pub async fn get(State(s): State<AppState>, UrlPath(id): UrlPath<String>) -> ApiResult<impl IntoResponse> {
    let scene = s.jobs.get_scene(&id).await?.ok_or_else(|| ApiError::not_found("scene", &id))?;
    let cached = kept().lock().unwrap_or_else(|e| e.into_inner()).get(&id).cloned();
    let jpeg = match cached {
        Some(j) => j,
        None => {
            let _permit = making().acquire().await.map_err(ApiError::internal)?;
            let part = if scene.status == SceneStatus::Ready { ScenePart::Data } else { ScenePart::Upload };
            let local = s.artifacts.scene_files(&scene, part).await?;
            let folder = folder_of(&scene, part, &local.path);
            let jpeg = tokio::task::spawn_blocking(move || thumbnail_of(&folder)).await??;
            let jpeg = Bytes::from(jpeg);
            let mut k = kept().lock().unwrap_or_else(|e| e.into_inner());
            if k.len() >= KEPT {
                k.clear();
            }
            k.insert(id, jpeg.clone());
            jpeg
        }
    };
    Ok(([(CONTENT_TYPE, "image/jpeg"), (CACHE_CONTROL, "private, max-age=86400")], jpeg))
}

/// The folder whose photos are the scene's: a ready scene's dataset, else
/// what was uploaded.
fn folder_of(scene: &SceneInfo, part: ScenePart, local: &Path) -> PathBuf {
    match part {
        ScenePart::Data => local.join(&scene.root),
        ScenePart::Upload => local.join(part.dir_name()),
    }
}

/// A JPEG thumbnail of the first photo under `folder`.
pub fn thumbnail_of(folder: &Path) -> ApiResult<Vec<u8>> {
    let none = || ApiError::new(Code::NotFound, "the scene has no photo to show (a video upload has none)");
    let photo = first_photo(folder, 0).ok_or_else(none)?;
    let header = photos::read_header(&photo)
        .map_err(|e| ApiError::new(Code::InvalidDataset, format!("the scene's first photo is unreadable: it {e}")))?;
    header.check_pixels().map_err(|e| ApiError::new(Code::InvalidDataset, format!("the scene's first photo {e}")))?;
    let image = image::ImageReader::open(&photo)
        .and_then(|r| r.with_guessed_format())
        .map_err(ApiError::internal)?
        .decode()
        .map_err(|e| ApiError::new(Code::InvalidDataset, format!("the scene's first photo does not decode: {e}")))?;
    // Shrunk, never enlarged.
    let small = if image.width() > SIZE || image.height() > SIZE { image.thumbnail(SIZE, SIZE) } else { image };
    let small = small.into_rgba8();
    // Transparent pixels on white, as the engine composites them.
    let rgb = image::RgbImage::from_fn(small.width(), small.height(), |x, y| {
        let [r, g, b, a] = small.get_pixel(x, y).0;
        let over = |c: u8| ((c as u32 * a as u32 + 255 * (255 - a as u32) + 127) / 255) as u8;
        image::Rgb([over(r), over(g), over(b)])
    });
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 82).encode_image(&rgb).map_err(ApiError::internal)?;
    Ok(out)
}

/// The first photo under `dir` in path order (folders walked in name order,
/// a few levels deep), leaving out masks, depth and normal maps and hidden
/// files.
fn first_photo(dir: &Path, depth: usize) -> Option<PathBuf> {
    let mut entries: Vec<_> = std::fs::read_dir(dir).ok()?.filter_map(Result::ok).map(|e| e.path()).collect();
    entries.sort();
    let skipped = |p: &Path| {
        let name = p.file_name().map(|n| n.to_string_lossy().to_lowercase()).unwrap_or_default();
        name.starts_with('.') || name == "__macosx" || ["mask", "depth", "normal"].iter().any(|w| name.contains(w))
    };
    for p in entries.iter().filter(|p| !skipped(p)) {
        if p.is_file() && photos::has_extension(p, &photos::PHOTO_EXTENSIONS) {
            return Some(p.clone());
        }
    }
    if depth >= 4 {
        return None;
    }
    entries.iter().filter(|p| p.is_dir() && !skipped(p)).find_map(|p| first_photo(p, depth + 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_photo_is_shrunk_and_masks_are_skipped() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("masks")).unwrap();
        std::fs::create_dir_all(dir.path().join("train")).unwrap();
        image::RgbaImage::from_pixel(40, 20, image::Rgba([0, 0, 0, 255])).save(dir.path().join("masks/a.png")).unwrap();
        // Half transparent red: pink on white.
        image::RgbaImage::from_pixel(400, 200, image::Rgba([255, 0, 0, 128]))
            .save(dir.path().join("train/r_0.png"))
            .unwrap();
        image::RgbaImage::from_pixel(40, 20, image::Rgba([0, 0, 255, 255]))
            .save(dir.path().join("train/r_0_depth_0000.png"))
            .unwrap();
        let jpeg = thumbnail_of(dir.path()).unwrap();
        assert!(jpeg.starts_with(&[0xff, 0xd8]), "not a JPEG");
        let img = image::load_from_memory(&jpeg).unwrap().into_rgb8();
        assert_eq!(img.dimensions(), (SIZE, SIZE / 2));
        let [r, g, b] = img.get_pixel(SIZE / 2, SIZE / 4).0;
        assert!(r > 240 && (120..140).contains(&g) && (120..140).contains(&b), "{r} {g} {b}");
        std::fs::create_dir_all(dir.path().join("empty/masks")).unwrap();
        std::fs::copy(dir.path().join("masks/a.png"), dir.path().join("empty/masks/a.png")).unwrap();
        assert_eq!(thumbnail_of(&dir.path().join("empty")).unwrap_err().code, Code::NotFound);
    }
}
