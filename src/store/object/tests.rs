//! `ObjectArtifacts` over a `file://` store in a temporary folder.

use std::io;
use std::path::Path;

use futures_util::StreamExt;
use object_store::ObjectStoreExt;
use sha2::{Digest, Sha256};

use super::*;
use crate::storage::{ModelInfo, ScenePart, sample_scene, sample_view};

/// A store in `dir/bucket` with its local folders in `dir/data`, in small
/// parts and a small cache.
fn open(dir: &Path) -> ObjectArtifacts {
    let config = ObjectConfig { part_size: 1024, cache_max_bytes: 1 << 20, ..ObjectConfig::default() };
    ObjectArtifacts::open(&dir.join("data"), &format!("file://{}", dir.join("bucket").display()), config).unwrap()
}

fn model(id: &str) -> ModelInfo {
    ModelInfo {
        id: id.into(),
        scene_id: "scn_a".into(),
        job_id: "job_a".into(),
        model: "nerf-tiny".into(),
        model_reason: None,
        config: serde_json::json!({}),
        steps: 1,
        training_seconds: 0.0,
        test_psnr: None,
        test_views: 0,
        size_bytes: 0,
        created_at: 0,
        updated_at: 0,
        complete: true,
        training_state: false,
        view: sample_view(),
        poses: None,
    }
}

async fn keys(store: &ObjectArtifacts) -> Vec<String> {
    let mut keys: Vec<String> = store.store().list(None).map(|m| m.unwrap().location.to_string()).collect().await;
    keys.sort();
    keys
}

#[tokio::test]
async fn a_staged_scene_round_trips_through_its_tar_and_the_cache() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(dir.path());
    let staged = store.staging_dir("scn_a").join("data");
    std::fs::create_dir_all(staged.join("lego/train/deeper")).unwrap();
    std::fs::create_dir_all(staged.join("empty")).unwrap();
    std::fs::write(staged.join("lego/transforms_train.json"), b"{\"frames\": []}").unwrap();
    let big: Vec<u8> = (0..5000u32).map(|i| (i * 7 % 256) as u8).collect();
    std::fs::write(staged.join("lego/train/r_0.png"), &big).unwrap();
    std::fs::write(staged.join("lego/train/deeper/r_1.png"), b"png").unwrap();

    store.put_scene_files("scn_a", ScenePart::Data, &staged).await.unwrap();
    assert!(!staged.exists(), "the local copy goes once stored");
    assert_eq!(keys(&store).await, vec!["scenes/scn_a/dataset.tar"]);

    let scene = sample_scene("scn_a");
    let files = store.scene_files(&scene, ScenePart::Data).await.unwrap();
    let data = files.path.join("data");
    assert_eq!(std::fs::read(data.join("lego/transforms_train.json")).unwrap(), b"{\"frames\": []}");
    assert_eq!(std::fs::read(data.join("lego/train/r_0.png")).unwrap(), big);
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

#[tokio::test]
async fn photo_uploads_are_their_own_object_and_bad_ids_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(dir.path());
    let staged = store.staging_dir("scn_b").join("data");
    std::fs::create_dir_all(&staged).unwrap();
    std::fs::write(staged.join("a.jpg"), b"jpeg").unwrap();
    store.put_scene_files("scn_b", ScenePart::Upload, &staged).await.unwrap();
    assert_eq!(keys(&store).await, vec!["scenes/scn_b/upload.tar"]);
    let files = store.scene_files(&sample_scene("scn_b"), ScenePart::Upload).await.unwrap();
    assert_eq!(std::fs::read(files.path.join("upload/a.jpg")).unwrap(), b"jpeg");

    std::fs::create_dir_all(&staged).unwrap();
    let e = store.put_scene_files("../x", ScenePart::Data, &staged).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    assert!(e.to_string().contains("'../x'"), "{e}");
    assert!(store.scene_files(&sample_scene("../x"), ScenePart::Data).await.is_err());
    // Only a staged upload is stored (and removed): not another scene's, not any folder.
    let e = store.put_scene_files("scn_c", ScenePart::Data, &staged).await.unwrap_err();
    assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    assert!(e.to_string().contains("staging folder"), "{e}");
    assert!(staged.is_dir(), "left in place");
    assert!(store.put_video("a/b", vec![1]).await.is_err());
    assert_eq!(keys(&store).await, vec!["scenes/scn_b/upload.tar"]);
}

#[tokio::test]
async fn checkpoints_are_content_addressed() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(dir.path());
    let file = dir.path().join("model.ckpt");
    let first: Vec<u8> = (0..4000u32).map(|i| (i % 13) as u8).collect();
    std::fs::write(&file, &first).unwrap();
    let stored = store.put_checkpoint("mdl_a", &file).await.unwrap();
    let sha: String = Sha256::digest(&first).iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(stored, Stored { sha256: sha.clone(), size: 4000 });
    // The same bytes again: the same key, one object.
    assert_eq!(store.put_checkpoint("mdl_a", &file).await.unwrap(), stored);
    assert_eq!(keys(&store).await, vec![format!("models/mdl_a/{sha}.ckpt")]);
    let local = store.checkpoint(&model("mdl_a")).await.unwrap();
    assert_eq!(local.path, dir.path().join(format!("data/cache/models/{sha}.ckpt")));
    assert_eq!(std::fs::read(&local.path).unwrap(), first);

    // New bytes: a new key, and the model's checkpoint is the newest.
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::write(&file, b"second").unwrap();
    let second = store.put_checkpoint("mdl_a", &file).await.unwrap();
    assert_ne!(second.sha256, sha);
    assert_eq!(keys(&store).await.len(), 2);
    assert_eq!(std::fs::read(store.checkpoint(&model("mdl_a")).await.unwrap().path).unwrap(), b"second");
    let e = store.checkpoint(&model("mdl_none")).await.err().unwrap();
    assert_eq!(e.kind(), io::ErrorKind::NotFound);
}

#[tokio::test]
async fn videos_usage_and_readiness() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(dir.path());
    store.ready().await.unwrap();
    store.put_video("vid_a", b"GIF89a".to_vec()).await.unwrap();
    let mut info: crate::storage::VideoInfo = serde_json::from_value(serde_json::json!({
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
