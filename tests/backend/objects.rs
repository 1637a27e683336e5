//! What `ObjectArtifacts` does beyond the contract, each check run on a
//! `file://` store (`objects::file::…`) and on a real S3 server
//! (`objects::s3::…`): scenes through their tar and the cache, uploads
//! over two parts as multipart uploads that appear only once complete,
//! interrupted uploads that leave nothing visible and can be repeated,
//! content-addressed checkpoints, videos, usage and readiness.

use std::io;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use object_store::path::Path as Key;
use object_store::{ObjectStore, ObjectStoreExt};
use radiance::backend::object::{ObjectArtifacts, Stored, scene_key, upload};
use radiance::backend::{Artifact, ArtifactStore};
use radiance::datadir::ScenePart;
use radiance::records::{ModelInfo, VideoInfo};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use crate::bucket::{Backend, Bucket};
use crate::contract::sample_view_scene;

/// One `#[tokio::test]` per check and backend.
macro_rules! on_both_backends {
    ($($check:ident),* $(,)?) => {
        mod file {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $check() {
                    super::$check(super::Backend::File).await
                }
            )*
        }
        mod s3 {
            $(
                #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
                async fn $check() {
                    super::$check(super::Backend::S3).await
                }
            )*
        }
    };
}

on_both_backends!(
    a_staged_scene_round_trips_through_its_tar_and_the_cache,
    photo_uploads_are_their_own_object_and_bad_ids_are_refused,
    an_upload_over_two_parts_is_multipart_and_appears_only_when_complete,
    a_writer_dropped_midway_leaves_no_listed_object,
    an_upload_abandoned_midway_leaves_nothing_visible_and_can_be_repeated,
    a_failed_tar_is_aborted_and_names_the_key,
    checkpoints_are_content_addressed,
    videos_usage_and_readiness,
    removing_a_deleted_records_bytes_takes_its_objects_and_no_others,
);

fn model(id: &str) -> ModelInfo {
    serde_json::from_value(serde_json::json!({
        "id": id, "scene_id": "scn_a", "job_id": "job_a", "model": "nerf-tiny", "config": {},
        "steps": 1, "training_seconds": 0.0, "test_psnr": null, "test_views": 0, "size_bytes": 0,
        "created_at": 0, "updated_at": 0, "complete": true,
        "view": serde_json::to_value(sample_view_scene("scn_a").view).unwrap(),
    }))
    .unwrap()
}

/// Every key in the store, sorted.
async fn keys(store: &dyn ObjectStore) -> Vec<String> {
    let mut keys: Vec<String> = store.list(None).map(|m| m.unwrap().location.to_string()).collect().await;
    keys.sort();
    keys
}

/// `n` bytes that no two parts share.
fn bytes(n: usize, seed: u32) -> Vec<u8> {
    (0..n as u32).map(|i| (i.wrapping_mul(2654435761).wrapping_add(seed) >> 13) as u8).collect()
}

/// Evidence that a completed object was stored as a multipart upload of
/// `parts` parts: on S3 its ETag is `"<md5 of the parts' md5s>-<parts>"`;
/// a folder keeps no trace once complete (its staging file is checked
/// while the upload is under way instead).
async fn assert_multipart(bucket: &Bucket, key: &Key, parts: usize) {
    let meta = bucket.store().head(key).await.unwrap();
    if bucket.backend == Backend::S3 {
        let etag = meta.e_tag.unwrap_or_default();
        assert!(etag.trim_matches('"').ends_with(&format!("-{parts}")), "{key}: ETag {etag}, not {parts} parts");
    }
}

/// An object stored in one PUT: on S3, a plain MD5 ETag.
async fn assert_single_put(bucket: &Bucket, key: &Key) {
    let meta = bucket.store().head(key).await.unwrap();
    if bucket.backend == Backend::S3 {
        let etag = meta.e_tag.unwrap_or_default();
        assert!(!etag.contains('-'), "{key}: ETag {etag} is a multipart upload's");
    }
}

async fn a_staged_scene_round_trips_through_its_tar_and_the_cache(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.open(&dir.path().join("data"));
    let staged = store.staging_dir("scn_a").join("data");
    std::fs::create_dir_all(staged.join("lego/train/deeper")).unwrap();
    std::fs::create_dir_all(staged.join("empty")).unwrap();
    std::fs::write(staged.join("lego/transforms_train.json"), b"{\"frames\": []}").unwrap();
    // Over two parts: the tar goes up as a multipart upload of three.
    let big = bytes(2 * bucket.part_size() + 5000, 1);
    std::fs::write(staged.join("lego/train/r_0.png"), &big).unwrap();
    std::fs::write(staged.join("lego/train/deeper/r_1.png"), b"png").unwrap();

    store.put_scene_files("scn_a", ScenePart::Data, &staged).await.unwrap();
    assert!(!staged.exists(), "the local copy goes once stored");
    assert_eq!(keys(&**store.store()).await, vec!["scenes/scn_a/dataset.tar"]);
    assert_multipart(&bucket, &scene_key("scn_a", ScenePart::Data), 3).await;

    let scene = sample_view_scene("scn_a");
    let files = store.scene_files(&scene, ScenePart::Data).await.unwrap();
    let data = files.path.join("data");
    assert_eq!(std::fs::read(data.join("lego/transforms_train.json")).unwrap(), b"{\"frames\": []}");
    assert!(std::fs::read(data.join("lego/train/r_0.png")).unwrap() == big, "the big file round trips");
    assert_eq!(std::fs::read(data.join("lego/train/deeper/r_1.png")).unwrap(), b"png");
    assert!(data.join("empty").is_dir());
    assert!(!files.path.join(".download.tar").exists());
    assert!(files.path.starts_with(dir.path().join("data/cache/scenes")));

    // The second read is the cached folder: it needs the store no more.
    store.store().delete(&scene_key("scn_a", ScenePart::Data)).await.unwrap();
    let again = store.scene_files(&scene, ScenePart::Data).await.unwrap();
    assert_eq!(again.path, files.path);
    // The other part was never stored.
    let e = store.scene_files(&scene, ScenePart::Upload).await.err().unwrap();
    assert_eq!(e.kind(), io::ErrorKind::NotFound, "{e}");
    assert!(!store.cache().contains("scenes/scn_a-upload"));
}

async fn photo_uploads_are_their_own_object_and_bad_ids_are_refused(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.open(&dir.path().join("data"));
    let staged = store.staging_dir("scn_b").join("data");
    std::fs::create_dir_all(&staged).unwrap();
    std::fs::write(staged.join("a.jpg"), b"jpeg").unwrap();
    store.put_scene_files("scn_b", ScenePart::Upload, &staged).await.unwrap();
    assert_eq!(keys(&**store.store()).await, vec!["scenes/scn_b/upload.tar"]);
    assert_single_put(&bucket, &scene_key("scn_b", ScenePart::Upload)).await;
    let files = store.scene_files(&sample_view_scene("scn_b"), ScenePart::Upload).await.unwrap();
    assert_eq!(std::fs::read(files.path.join("upload/a.jpg")).unwrap(), b"jpeg");

    std::fs::create_dir_all(&staged).unwrap();
    let e = store.put_scene_files("../x", ScenePart::Data, &staged).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    assert!(e.to_string().contains("'../x'"), "{e}");
    assert!(store.scene_files(&sample_view_scene("../x"), ScenePart::Data).await.is_err());
    // Only a staged upload is stored (and removed): not another scene's, not any folder.
    let e = store.put_scene_files("scn_c", ScenePart::Data, &staged).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    assert!(e.to_string().contains("staging folder"), "{e}");
    assert!(staged.is_dir(), "left in place");
    assert!(store.put_video("a/b", vec![1]).await.is_err());
    assert_eq!(keys(&**store.store()).await, vec!["scenes/scn_b/upload.tar"]);
}

async fn an_upload_over_two_parts_is_multipart_and_appears_only_when_complete(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.store();
    let part = bucket.part_size();
    let key = Key::from("scenes/scn_a/dataset.tar");
    let all = bytes(2 * part + part / 2, 2);
    let mut w = upload::writer(&store, &key, part);
    w.write_all(&all).await.unwrap();
    // Over two parts in: a multipart upload is under way, nothing is listed.
    let staged = wait_for_staged_bytes(&bucket, part as u64).await;
    assert!(staged >= part as u64, "a part is stored while the upload is under way ({staged} bytes)");
    assert!(keys(&*store).await.is_empty());
    assert!(matches!(store.head(&key).await, Err(object_store::Error::NotFound { .. })));
    w.shutdown().await.unwrap();
    assert_eq!(keys(&*store).await, vec![key.to_string()]);
    assert!(store.get(&key).await.unwrap().bytes().await.unwrap() == all, "the bytes read back");
    assert_multipart(&bucket, &key, 3).await;

    // Below the part size: one put at the end, nothing staged before.
    let small = Key::from("videos/vid_a.bin");
    let mut w = upload::writer(&store, &small, part);
    w.write_all(&all[..500]).await.unwrap();
    assert!(!keys(&*store).await.contains(&small.to_string()));
    w.shutdown().await.unwrap();
    assert_eq!(store.get(&small).await.unwrap().bytes().await.unwrap(), all[..500]);
    assert_single_put(&bucket, &small).await;
}

async fn a_writer_dropped_midway_leaves_no_listed_object(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.store();
    let part = bucket.part_size();
    let key = Key::from("models/mdl_a/x.ckpt");
    let mut w = upload::writer(&store, &key, part);
    w.write_all(&bytes(3 * part, 3)).await.unwrap();
    wait_for_staged_bytes(&bucket, part as u64).await;
    drop(w);
    assert!(keys(&*store).await.is_empty());
    assert!(matches!(store.head(&key).await, Err(object_store::Error::NotFound { .. })));

    // The same key again, whole this time.
    let again = bytes(part + 10, 4);
    let mut w = upload::writer(&store, &key, part);
    w.write_all(&again).await.unwrap();
    w.shutdown().await.unwrap();
    assert_eq!(keys(&*store).await, vec![key.to_string()]);
    assert!(store.get(&key).await.unwrap().bytes().await.unwrap() == again);
}

async fn an_upload_abandoned_midway_leaves_nothing_visible_and_can_be_repeated(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.store();
    let part = bucket.part_size();
    let key = Key::from("models/mdl_a/big.ckpt");
    // The rest, after two and a half parts, is more than a pipe holds.
    let content = bytes(6 * part + (2 << 20) + 77, 5);
    // The upload reads a pipe, so the test decides how far it gets.
    let fifo = dir.path().join("big.fifo");
    let c_path = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid C string.
    assert_eq!(unsafe { libc::mkfifo(c_path.as_ptr(), 0o600) }, 0, "{}", io::Error::last_os_error());
    let uploading = tokio::spawn({
        let (store, key, fifo) = (store.clone(), key.clone(), fifo.clone());
        async move { upload::put_file(&store, &key, fifo, part).await }
    });
    let (fed, feeding) = std::sync::mpsc::channel();
    let (head, rest) = content.split_at(2 * part + part / 2);
    let (head, rest) = (head.to_vec(), rest.to_vec());
    let (go_on, rest_wanted) = std::sync::mpsc::channel::<()>();
    std::thread::spawn(move || {
        use std::io::Write;
        let mut pipe = std::fs::OpenOptions::new().write(true).open(&fifo).unwrap();
        fed.send(pipe.write_all(&head)).unwrap();
        if rest_wanted.recv().is_ok() {
            fed.send(pipe.write_all(&rest)).unwrap();
        }
    });
    let wait = Duration::from_secs(30);
    feeding.recv_timeout(wait).expect("the upload read two and a half parts within 30 s").unwrap();
    // Two parts stored: the task storing the file is dropped (as a request
    // handler is when its client goes).
    wait_for_staged_bytes(&bucket, 2 * part as u64).await;
    uploading.abort();
    assert!(uploading.await.unwrap_err().is_cancelled(), "aborted before it completed");
    // What was under way stops reading at its next write: the rest of the
    // pipe finds no reader.
    go_on.send(()).unwrap();
    let rest_fed = tokio::task::spawn_blocking(move || feeding.recv_timeout(wait)).await.unwrap();
    let e = rest_fed.expect("the abandoned upload stopped within 30 s").unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::BrokenPipe, "{e}");
    // ...and is aborted: its stored parts go.
    wait_for_staged_bytes_at_most(&bucket, 0).await;
    assert!(keys(&*store).await.is_empty(), "nothing is visible");
    assert!(matches!(store.head(&key).await, Err(object_store::Error::NotFound { .. })));

    let file = dir.path().join("big.ckpt");
    std::fs::write(&file, &content).unwrap();
    let size = upload::put_file(&store, &key, file, part).await.unwrap();
    assert_eq!(size, content.len() as u64);
    assert_eq!(keys(&*store).await, vec![key.to_string()]);
    assert!(store.get(&key).await.unwrap().bytes().await.unwrap() == content, "the repeated upload is whole");
    assert_multipart(&bucket, &key, content.len().div_ceil(part)).await;
}

async fn a_failed_tar_is_aborted_and_names_the_key(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.store();
    let key = Key::from("scenes/scn_a/dataset.tar");
    let e = upload::put_tar(&store, &key, dir.path().join("missing"), bucket.part_size()).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::NotFound);
    assert!(e.to_string().contains("scenes/scn_a/dataset.tar"), "{e}");
    assert!(keys(&*store).await.is_empty());
}

async fn checkpoints_are_content_addressed(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.open(&dir.path().join("data"));
    let file = dir.path().join("model.ckpt");
    let first = bytes(4000, 6);
    std::fs::write(&file, &first).unwrap();
    let stored = store.put_checkpoint("mdl_a", &file).await.unwrap();
    let sha: String = Sha256::digest(&first).iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(stored, Stored { sha256: sha.clone(), size: 4000 });
    // The same bytes again: the same key, one object.
    assert_eq!(store.put_checkpoint("mdl_a", &file).await.unwrap(), stored);
    assert_eq!(keys(&**store.store()).await, vec![format!("models/mdl_a/{sha}.ckpt")]);
    let local = store.checkpoint(&model("mdl_a")).await.unwrap();
    assert_eq!(local.path, dir.path().join(format!("data/cache/models/{sha}.ckpt")));
    assert_eq!(std::fs::read(&local.path).unwrap(), first);

    // New bytes: a new key, and the model's checkpoint is the newest (by
    // the listing's modification time: S3 servers give it to the
    // millisecond or, like AWS, the second, hence the wait).
    tokio::time::sleep(Duration::from_millis(1100)).await;
    std::fs::write(&file, b"second").unwrap();
    let second = store.put_checkpoint("mdl_a", &file).await.unwrap();
    assert_ne!(second.sha256, sha);
    assert_eq!(keys(&**store.store()).await.len(), 2);
    assert_eq!(std::fs::read(store.checkpoint(&model("mdl_a")).await.unwrap().path).unwrap(), b"second");
    let e = store.checkpoint(&model("mdl_none")).await.err().unwrap();
    assert_eq!(e.kind(), io::ErrorKind::NotFound);
}

async fn videos_usage_and_readiness(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store: ObjectArtifacts = bucket.open(&dir.path().join("data"));
    store.ready().await.unwrap();
    store.put_video("vid_a", b"GIF89a".to_vec()).await.unwrap();
    let mut info: VideoInfo = serde_json::from_value(serde_json::json!({
        "id": "vid_a", "model_id": "mdl_a", "job_id": "job_a", "format": "gif", "frames": 1,
        "fps": 1, "width": 1, "height": 1, "size_bytes": 6, "created_at": 0
    }))
    .unwrap();
    assert_eq!(store.video(&info).await.unwrap(), b"GIF89a");
    info.id = "vid_b".into();
    assert_eq!(store.video(&info).await.unwrap_err().kind(), io::ErrorKind::NotFound);
    let file = dir.path().join("c");
    std::fs::write(&file, [0u8; 10]).unwrap();
    store.put_checkpoint("mdl_a", &file).await.unwrap();
    let usage = store.usage().await.unwrap();
    assert_eq!((usage.scenes, usage.models, usage.videos, usage.tmp), (0, 10, 6, 0));
    assert_eq!(store.free_space().await.unwrap(), None);
    store.ready().await.unwrap();
}

/// Waits (up to 30 s) until the store holds at least `at_least` bytes of
/// multipart uploads under way, and answers how many; on an existing S3
/// server, whose folder the test cannot see, it waits 3 s instead.
async fn wait_for_staged_bytes(bucket: &Bucket, at_least: u64) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let Some(staged) = bucket.staged_bytes() else {
            tokio::time::sleep(Duration::from_secs(3)).await;
            return at_least;
        };
        if staged >= at_least {
            return staged;
        }
        assert!(Instant::now() < deadline, "{staged} bytes of parts stored after 30 s, not {at_least}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits (up to 30 s) until the store holds at most `at_most` bytes of
/// multipart uploads under way (not checked on an existing S3 server,
/// whose folder the test cannot see).
async fn wait_for_staged_bytes_at_most(bucket: &Bucket, at_most: u64) {
    let deadline = Instant::now() + Duration::from_secs(30);
    while let Some(staged) = bucket.staged_bytes() {
        if staged <= at_most {
            return;
        }
        assert!(Instant::now() < deadline, "{staged} bytes of parts still stored after 30 s, not {at_most}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// `remove` deletes every object of the record named (all parts of a
/// scene, all checkpoints of a model, a video) and nothing of the others;
/// removing again, or what never existed, is no error; a bad id is refused.
async fn removing_a_deleted_records_bytes_takes_its_objects_and_no_others(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let bucket = Bucket::new(backend, dir.path()).await;
    let store = bucket.open(&dir.path().join("data"));
    for id in ["scn_a", "scn_b"] {
        for part in [ScenePart::Data, ScenePart::Upload] {
            let staged = store.staging_dir(id).join(format!("{part:?}"));
            std::fs::create_dir_all(&staged).unwrap();
            std::fs::write(staged.join("f"), id).unwrap();
            store.put_scene_files(id, part, &staged).await.unwrap();
        }
    }
    let file = dir.path().join("model.ckpt");
    for (id, contents) in [("mdl_a", "one"), ("mdl_a", "two"), ("mdl_b", "three")] {
        std::fs::write(&file, contents).unwrap();
        store.put_checkpoint(id, &file).await.unwrap();
    }
    store.put_video("vid_a", b"GIF89a".to_vec()).await.unwrap();
    store.put_video("vid_b", b"GIF89a".to_vec()).await.unwrap();
    assert_eq!(keys(&**store.store()).await.len(), 9);

    store.remove(Artifact::Scene("scn_a")).await.unwrap();
    store.remove(Artifact::Model("mdl_a")).await.unwrap();
    store.remove(Artifact::Video("vid_a")).await.unwrap();
    let left = keys(&**store.store()).await;
    assert_eq!(left.len(), 4, "{left:?}");
    assert!(left.iter().all(|k| k.contains("scn_b") || k.contains("mdl_b") || k.contains("vid_b")), "{left:?}");
    // Again, and what never was: nothing to do, no error.
    for what in [Artifact::Scene("scn_a"), Artifact::Model("mdl_none"), Artifact::Video("vid_a")] {
        store.remove(what).await.unwrap();
    }
    assert_eq!(keys(&**store.store()).await, left);
    let e = store.remove(Artifact::Scene("../scenes")).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{e}");
}
