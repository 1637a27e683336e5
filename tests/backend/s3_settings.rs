//! How `ObjectArtifacts` reaches an S3 server (`common::s3`'s): from the
//! AWS environment alone, as a radiance process will; only with the right
//! secret (the server checks signatures, so a key that does not reach the
//! signature would show); and what a test says when the server's binary
//! is missing.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use object_store::ObjectStoreExt;
use object_store::path::Path as Key;
use radiance::backend::ArtifactStore;
use radiance::backend::object::{ObjectArtifacts, ObjectConfig, S3Keys};
use radiance::records::VideoInfo;

use crate::common::s3::{INSTALL, S3, find_s3s_fs};

/// Set in the child process of [`the_aws_environment_alone_reaches_the_server`]:
/// the store URL it opens.
const CHILD_URL: &str = "RADIANCE_TEST_S3_CHILD_URL";

fn video(id: &str) -> VideoInfo {
    serde_json::from_value(serde_json::json!({
        "id": id, "model_id": "mdl_a", "job_id": "job_a", "format": "gif", "frames": 1,
        "fps": 1, "width": 1, "height": 1, "size_bytes": 6, "created_at": 0
    }))
    .unwrap()
}

/// The test runs itself again as a child process whose environment holds
/// only the harness's `AWS_*` variables (no other `AWS_*`), and which
/// opens the store with the default settings: what `serve` will do. The
/// child stores a video; the parent reads it with its explicit settings.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_aws_environment_alone_reaches_the_server() {
    if let Ok(url) = std::env::var(CHILD_URL) {
        let dir = tempfile::tempdir().unwrap();
        let store = ObjectArtifacts::open(dir.path(), &url, ObjectConfig::default()).unwrap();
        store.ready().await.unwrap();
        store.put_video("vid_env", b"GIF89a".to_vec()).await.unwrap();
        assert_eq!(store.video(&video("vid_env")).await.unwrap(), b"GIF89a");
        return;
    }
    let s3 = S3::start().await;
    let mut child = Command::new(std::env::current_exe().unwrap());
    child.args(["--exact", "s3_settings::the_aws_environment_alone_reaches_the_server", "--nocapture"]);
    for (name, _) in std::env::vars_os() {
        if name.to_string_lossy().starts_with("AWS_") {
            child.env_remove(name);
        }
    }
    child.envs(s3.env()).env(CHILD_URL, s3.url()).stdin(Stdio::null());
    let out = tokio::task::spawn_blocking(move || run_within(child, Duration::from_secs(60))).await.unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).contains("1 passed"),
        "the child failed ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let got = s3.store().get(&Key::from("videos/vid_env.bin")).await.unwrap().bytes().await.unwrap();
    assert_eq!(got, b"GIF89a".as_slice());
}

/// A test run with the `RADIANCE_TEST_S3_*` variables uses that server
/// (here one of our own, started by this test) under a prefix of its own,
/// and deletes what it stored when it ends.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_existing_server_is_used_through_the_radiance_test_s3_variables() {
    let s3 = S3::start().await;
    let keys = s3.options().keys.unwrap();
    // A check that leaves its object (scenes/scn_b/upload.tar) behind.
    let check = "objects::s3::photo_uploads_are_their_own_object_and_bad_ids_are_refused";
    let mut child = Command::new(std::env::current_exe().unwrap());
    child
        .args(["--exact", check, "--nocapture"])
        .env("RADIANCE_TEST_S3_ENDPOINT", s3.endpoint())
        .env("RADIANCE_TEST_S3_ACCESS_KEY_ID", &keys.access_key_id)
        .env("RADIANCE_TEST_S3_SECRET_ACCESS_KEY", &keys.secret_access_key)
        .env("RADIANCE_TEST_S3_BUCKET", "radiance-test")
        // No s3s-fs to find: the check must not start one.
        .env("RADIANCE_S3S_FS", "/nonexistent/s3s-fs")
        .stdin(Stdio::null());
    let out = tokio::task::spawn_blocking(move || run_within(child, Duration::from_secs(60))).await.unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).contains("1 passed"),
        "the check failed on the existing server ({}):\n{}{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    // It stored its scene under a prefix of its own, and deleted it at the end.
    let bucket = s3.root().unwrap().join("data/radiance-test");
    let prefixes: Vec<String> =
        std::fs::read_dir(&bucket).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    // (s3s-fs keeps a deleted key's folders.)
    assert!(prefixes.len() == 1 && prefixes[0].starts_with("t-"), "{prefixes:?}");
    let left = files_in(&bucket);
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// The files under `dir`, recursively.
fn files_in(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        if entry.file_type().unwrap().is_dir() {
            out.extend(files_in(&entry.path()));
        } else {
            out.push(entry.path());
        }
    }
    out
}

/// Runs `cmd` to its end, killing it after `limit`.
fn run_within(mut cmd: Command, limit: Duration) -> std::process::Output {
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let deadline = Instant::now() + limit;
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            child.kill().unwrap();
            panic!("the child ran over {limit:?}: {:?}", child.wait_with_output().unwrap());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_refuses_a_wrong_secret_and_readiness_says_why() {
    let s3 = S3::start().await;
    let dir = tempfile::tempdir().unwrap();
    let mut options = s3.options();
    let keys = options.keys.take().unwrap();
    options.keys = Some(S3Keys { secret_access_key: "not-the-secret".into(), ..keys });
    let config = ObjectConfig { s3: options, ready_timeout: Duration::from_secs(10), ..ObjectConfig::default() };
    let store = ObjectArtifacts::open(dir.path(), &s3.url(), config).unwrap();
    let e = store.ready().await.unwrap_err();
    let said = e.to_string();
    assert!(said.contains("403") && said.contains("SignatureDoesNotMatch"), "{said}");
    assert!(!said.contains("not-the-secret"), "the secret is not shown: {said}");
    assert!(store.put_video("vid_a", b"x".to_vec()).await.is_err());

    let config = ObjectConfig { s3: s3.options(), ..ObjectConfig::default() };
    let store = ObjectArtifacts::open(dir.path(), &s3.url(), config).unwrap();
    store.ready().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_names_a_missing_bucket_and_an_unreachable_server() {
    let s3 = S3::start().await;
    let dir = tempfile::tempdir().unwrap();
    let config = ObjectConfig { s3: s3.options(), ready_timeout: Duration::from_secs(10), ..ObjectConfig::default() };
    let url = "s3://no-such-bucket/x";
    let e = ObjectArtifacts::open(dir.path(), url, config.clone()).unwrap().ready().await.unwrap_err();
    let said = e.to_string();
    assert!(said.starts_with(&format!("the object store {url}: ")) && said.contains("NoSuchBucket"), "{said}");

    // Nothing listens on the port: readiness gives up after its timeout.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut options = s3.options();
    options.endpoint = Some(format!("http://127.0.0.1:{port}"));
    let config = ObjectConfig { s3: options, ready_timeout: Duration::from_secs(1), ..ObjectConfig::default() };
    let store = ObjectArtifacts::open(dir.path(), &s3.url(), config).unwrap();
    let asked = Instant::now();
    let e = store.ready().await.unwrap_err();
    assert!(asked.elapsed() < Duration::from_secs(5), "answered after {:?}", asked.elapsed());
    assert_eq!(e.kind(), std::io::ErrorKind::TimedOut, "{e}");
    let said = e.to_string();
    assert!(said.contains(&s3.url()) && said.contains("did not answer a listing within 1s"), "{said}");
}

#[test]
fn a_missing_server_binary_names_the_install_command() {
    let empty = tempfile::tempdir().unwrap();
    let e = find_s3s_fs(None, Some(empty.path().as_os_str()), Some(empty.path())).unwrap_err();
    assert!(e.contains(INSTALL) && e.contains("RADIANCE_TEST_S3_ENDPOINT"), "{e}");
    let e = find_s3s_fs(Some(empty.path().join("nothing").as_os_str()), None, None).unwrap_err();
    assert!(e.contains("RADIANCE_S3S_FS="), "{e}");
    // Found in cargo's bin folder when not on PATH.
    let bin = empty.path().join("bin");
    std::fs::create_dir(&bin).unwrap();
    std::fs::write(bin.join("s3s-fs"), b"").unwrap();
    assert_eq!(
        find_s3s_fs(None, Some(Path::new("/nonexistent").as_os_str()), Some(empty.path())).unwrap(),
        bin.join("s3s-fs")
    );
}
