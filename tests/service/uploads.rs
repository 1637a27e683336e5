//! Uploading datasets: archives and multipart forms of every format, and what is refused.

use std::path::Path;

use reqwest::StatusCode;
use serde_json::{Value, json};

use crate::common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_zip_and_tar_gz_list_get_delete() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let (s, v) = svc.get("/healthz").await;
    assert_eq!((s, v["status"].as_str()), (StatusCode::OK, Some("ok")));

    let (s, v) = svc.upload("application/zip", zip_of(&ball_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["format"], "blender");
    assert_eq!(v["images"], json!({ "train": 8, "val": 0, "test": 4 }));
    assert_eq!(v["resolution"], json!([16, 16]));
    assert!(v["warnings"].is_array());
    let zip_id = v["id"].as_str().unwrap().to_string();

    // A tar.gz that wraps the dataset in a folder, as `tar czf lego.tgz lego` does.
    let wrapped: Vec<_> = ball_files().into_iter().map(|(n, d)| (format!("lego/{n}"), d)).collect();
    let (s, v) = svc.upload("application/gzip", tar_gz_of(&wrapped)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let tgz_id = v["id"].as_str().unwrap().to_string();

    let (_, list) = svc.get("/v1/scenes").await;
    let ids: Vec<&str> = list.as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap()).collect();
    assert_eq!(ids, [zip_id.as_str(), tgz_id.as_str()]);
    let (s, v) = svc.get(&format!("/v1/scenes/{tgz_id}")).await;
    assert_eq!((s, v["images"]["train"].as_u64()), (StatusCode::OK, Some(8)));

    let r = svc.client.delete(svc.url(&format!("/v1/scenes/{zip_id}"))).send().await.unwrap();
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let (s, v) = svc.get(&format!("/v1/scenes/{zip_id}")).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_error(&v, "not_found");
    assert!(!data.path().join("scenes").join(&zip_id).exists());
    let (s, v) = svc.get("/v1/nothing").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert_error(&v, "not_found");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_uploads_are_refused_and_leave_nothing() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.max_unpacked_bytes = 1 << 20;
    let svc = Svc::start(cfg).await;
    let good = ball_files();

    // `..` in a tar entry
    let mut evil = good.clone();
    evil.push(("../escaped.txt".into(), b"x".to_vec()));
    let (s, v) = svc.upload("application/gzip", tar_gz_of(&evil)).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert_error(&v, "bad_request");
    assert!(v["error"]["message"].as_str().unwrap().contains(".."), "{v}");
    assert!(!data.path().join("tmp").join("escaped.txt").exists());

    // an absolute path in a zip
    let mut abs = good.clone();
    abs.push(("/tmp/radiance-abs.txt".into(), b"x".to_vec()));
    let (s, v) = svc.upload("application/zip", zip_of(&abs)).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");

    // a symlink in a zip
    let mut w = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    w.add_symlink("link", "/etc/passwd", zip::write::SimpleFileOptions::default()).unwrap();
    let (s, v) = svc.upload("application/zip", w.finish().unwrap().into_inner()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains("link"), "{v}");

    // garbage and a truncated archive
    let (s, _) = svc.upload("application/zip", b"not a zip at all".to_vec()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    let tgz = tar_gz_of(&good);
    let (s, v) = svc.upload("application/gzip", tgz[..tgz.len() / 2].to_vec()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");

    // a decompression bomb: 8 MiB of zeros in a few KiB
    let (s, v) = svc.upload("application/zip", zip_of(&[("zeros.bin".into(), vec![0u8; 8 << 20])])).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE, "{v}");
    assert_error(&v, "payload_too_large");
    assert!(v["error"]["message"].as_str().unwrap().contains("declares 8388608 bytes"), "{v}");

    // wrong media type
    let (s, v) = svc.upload("text/plain", zip_of(&good)).await;
    assert_eq!(s, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{v}");

    // a valid archive of an invalid dataset: a missing image, then a NaN pose
    let missing: Vec<_> = good.iter().filter(|(n, _)| n != "train/r_3.png").cloned().collect();
    let (s, v) = svc.upload("application/zip", zip_of(&missing)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert_error(&v, "invalid_dataset");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("r_3") && !msg.contains(&*data.path().to_string_lossy()), "{msg}");
    let nan: Vec<_> = good
        .iter()
        .map(|(n, d)| {
            if n == "transforms_train.json" {
                let mut j: Value = serde_json::from_slice(d).unwrap();
                j["frames"][0]["transform_matrix"][0][3] = json!("NaN");
                (n.clone(), serde_json::to_vec(&j).unwrap())
            } else {
                (n.clone(), d.clone())
            }
        })
        .collect();
    let (s, v) = svc.upload("application/zip", zip_of(&nan)).await;
    assert!(s == StatusCode::UNPROCESSABLE_ENTITY, "{s} {v}");

    assert_no_scene_files(data.path());
    let (_, list) = svc.get("/v1/scenes").await;
    assert_eq!(list, json!([]));
    assert!(!Path::new("/tmp/radiance-abs.txt").exists());
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn archive_bombs_are_refused_from_their_declared_sizes() {
    let data = tempfile::tempdir().unwrap();
    let mut cfg = config(data.path());
    cfg.max_unpacked_bytes = 16 << 20;
    let svc = Svc::start(cfg).await;
    let limit = "16777216 bytes";

    // 64 MiB of zeros in a 64 KiB zip, beside a valid dataset: refused from
    // the central directory (the message gives the declared total), before
    // anything is written.
    let mut bomb = ball_files();
    bomb.push(("zeros.bin".into(), vec![0u8; 64 << 20]));
    let declared: usize = bomb.iter().map(|(_, d)| d.len()).sum();
    let zip = zip_of(&bomb);
    assert!(zip.len() < 1 << 20, "{} bytes", zip.len());
    let (s, v) = svc.upload("application/zip", zip).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE, "{v}");
    assert_error(&v, "payload_too_large");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains(&format!("archive declares {declared} bytes")) && msg.contains(limit), "{msg}");
    assert_no_scene_files(data.path());

    // Within the limit but packed over 100:1: refused by its ratio.
    let mut bomb = ball_files();
    bomb.push(("zeros.bin".into(), vec![0u8; 8 << 20]));
    let (s, v) = svc.upload("application/zip", zip_of(&bomb)).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("'zeros.bin' declares 8388608 bytes") && msg.contains("ratio over 100:1"), "{msg}");
    assert_no_scene_files(data.path());

    // A tar.gz: refused at the header of the entry that passes the limit.
    let mut bomb = ball_files();
    bomb.push(("zeros.bin".into(), vec![0u8; 32 << 20]));
    let (s, v) = svc.upload("application/gzip", tar_gz_of(&bomb)).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("'zeros.bin' declares 33554432 bytes") && msg.contains(limit), "{msg}");
    assert_no_scene_files(data.path());

    // The same dataset without the bomb is stored.
    let (s, v) = svc.upload("application/zip", zip_of(&ball_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upload_each_format_as_archive_and_as_multipart() {
    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    // instant-ngp transforms.json in a zip: every 8th frame held out
    let (s, v) = svc.upload("application/zip", zip_of(&ngp_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["format"], "ngp");
    assert_eq!(v["images"], json!({ "train": 10, "val": 2, "test": 2 }));
    // LLFF poses_bounds.npy in a tar.gz
    let (s, v) = svc.upload("application/gzip", tar_gz_of(&llff_files())).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["format"], "llff");
    assert_eq!(v["resolution"], json!([16, 16]));
    // multipart, paths as field names (Blender) and as file names (LLFF)
    let (s, v) = svc.upload_form(form_of(&ball_files(), false)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!((v["format"].as_str(), v["images"]["train"].as_u64()), (Some("blender"), Some(8)));
    let (s, v) = svc.upload_form(form_of(&llff_files(), true)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["format"], "llff");
    // COLMAP, a binary model in a zip and a text model as multipart
    let (s, v) = svc.upload("application/zip", zip_of(&colmap_files(true))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!(v["format"], "colmap");
    assert_eq!(v["images"], json!({ "train": 10, "val": 2, "test": 2 }));
    let (s, v) = svc.upload_form(form_of(&colmap_files(false), true)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert_eq!((v["format"].as_str(), v["resolution"].clone()), (Some("colmap"), json!([16, 16])));
    let (_, list) = svc.get("/v1/scenes").await;
    assert_eq!(list.as_array().unwrap().len(), 6);

    // Bad multipart uploads leave nothing behind.
    let mut evil = ball_files();
    evil.push(("../../escaped.txt".into(), b"x".to_vec()));
    let (s, v) = svc.upload_form(form_of(&evil, false)).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    assert!(v["error"]["message"].as_str().unwrap().contains(".."), "{v}");
    let missing: Vec<_> = ngp_files().into_iter().filter(|(n, _)| n != "transforms.json").collect();
    let (s, v) = svc.upload_form(form_of(&missing, true)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    let (s, v) = svc.upload_form(reqwest::multipart::Form::new()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST, "{v}");
    let left: Vec<_> = std::fs::read_dir(data.path().join("tmp")).unwrap().collect();
    assert!(left.is_empty(), "tmp/ holds {left:?}");
    let (_, list) = svc.get("/v1/scenes").await;
    assert_eq!(list.as_array().unwrap().len(), 6);
    svc.stop().await;
}

/// An LLFF scene with a `masks_8/` folder keeps it, as an archive and as
/// multipart files, and the loader finds the masks in the stored scene.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_keep_mask_folders_and_the_loader_finds_them() {
    use radiance::engine::dataset::{Dataset, LoadOptions, MaskUse};

    let data = tempfile::tempdir().unwrap();
    let svc = Svc::start(config(data.path())).await;
    let files = llff_masked_files();
    let masks: Vec<&(String, Vec<u8>)> = files.iter().filter(|(n, _)| n.starts_with("masks_8/")).collect();
    assert_eq!(masks.len(), 12);
    let wrapped: Vec<_> = files.iter().map(|(n, d)| (format!("head/{n}"), d.clone())).collect();
    let uploads = [
        svc.upload("application/zip", zip_of(&files)).await,
        svc.upload("application/gzip", tar_gz_of(&wrapped)).await,
        svc.upload_form(form_of(&files, true)).await,
        svc.upload_form(form_of(&files, false)).await,
    ];
    for (s, v) in uploads {
        assert_eq!(s, StatusCode::CREATED, "{v}");
        assert_eq!((v["format"].as_str(), v["mask_folder"].as_str()), (Some("llff"), Some("masks_8/")), "{v}");
        let warnings = v["warnings"].as_array().unwrap();
        assert!(warnings.iter().any(|w| w.as_str().unwrap().starts_with("masks_8/: per-image masks")), "{v}");
        // Every mask is stored as uploaded, and loads as the frames' masks.
        let root = data.path().join("scenes").join(v["id"].as_str().unwrap()).join(v["root"].as_str().unwrap());
        for (name, bytes) in &masks {
            assert_eq!(&std::fs::read(root.join(name)).unwrap(), bytes, "{name}");
        }
        let ds = Dataset::load(&root, &LoadOptions { masks: MaskUse::Ignore, ..Default::default() }).unwrap();
        assert_eq!((ds.masks, ds.mask_folder.clone()), (MaskUse::Ignore, Some(root.join("masks_8"))));
        let want = ball().dataset();
        for (f, w) in ds.frames.iter().zip(&want.frames) {
            let alpha: Vec<u8> = w.image.rgba.chunks(4).map(|p| p[3]).collect();
            assert_eq!(f.mask.as_ref(), Some(&alpha), "{}", f.name);
        }
    }
    // Without its masks the same scene has no mask folder and no warning.
    let plain: Vec<_> = files.iter().filter(|(n, _)| !n.starts_with("masks_8/")).cloned().collect();
    let (s, v) = svc.upload("application/zip", zip_of(&plain)).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    assert!(v["mask_folder"].is_null(), "{v}");
    // With one mask missing the upload is refused, naming its image.
    let short: Vec<_> = files.iter().filter(|(n, _)| n != "masks_8/img005.png").cloned().collect();
    let (s, v) = svc.upload("application/zip", zip_of(&short)).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("img005.png") && msg.contains("no mask"), "{msg}");
    svc.stop().await;
}
