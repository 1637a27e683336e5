//! Resource limits and crash safety of the service: jobs too large for the
//! machine are refused before they are queued, jobs wait for memory, a job
//! that keeps killing the server is failed, and `kill -9` at random moments
//! (mid-checkpoint included) loses no job and leaves no temporary file.

mod common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::*;
use radiance::api::limits::scene_data;
use radiance::engine::dataset::MaskUse;
use radiance::engine::models::config::ModelConfig;
use radiance::engine::train::estimate;
use radiance::records::SceneInfo;
use reqwest::StatusCode;
use serde_json::{Value, json};

/// The configuration issue 14 found answered 202 and growing past 12 GiB.
fn twelve_gigabyte_job(scene: &str) -> Value {
    let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
    c.grid.levels = 32;
    c.grid.log2_table = 24;
    c.grid.finest_resolution = 8192;
    c.hidden = 256;
    c.geo_features = 64;
    c.samples_per_step = 1 << 20;
    c.chunk_rays = 4096;
    json!({ "scene_id": scene, "budget": { "steps": 2 }, "config": ModelConfig::Instant(c) })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_too_large_for_the_limit_is_refused_at_once_naming_its_estimate() {
    let data = tempfile::tempdir().unwrap();
    let mut c = config(data.path());
    c.scheduler.max_job_memory_bytes = 8 << 30;
    c.scheduler.memory_budget_bytes = 8 << 30;
    let svc = Svc::start(c).await;
    let scene = svc.upload_ball().await;
    let t0 = Instant::now();
    let (s, v) = svc.post_json("/v1/jobs", twelve_gigabyte_job(&scene)).await;
    // The 422 itself shows it was never queued; the bound only says the
    // answer did not wait on the job (20 s: room for a starved test thread).
    assert!(t0.elapsed() < Duration::from_secs(20), "refused in {:?}", t0.elapsed());
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert_error(&v, "resource_limit");
    let d = &v["error"]["details"];
    assert_eq!(d["limit_bytes"], 8u64 << 30, "{v}");
    assert!(d["estimate_bytes"].as_u64().unwrap() > 24 << 30, "{v}");
    assert!(d["parts"]["parameters"].as_u64().unwrap() > 2 << 30, "{v}");
    let msg = v["error"]["message"].as_str().unwrap();
    assert!(msg.contains("MiB") && msg.contains("--max-job-memory-mb"), "{msg}");
    let (_, jobs) = svc.get("/v1/jobs").await;
    assert_eq!(jobs, json!([]), "nothing was queued");

    // A configuration that fits is queued with its estimate, and trains.
    let (s, v) = svc
        .post_json("/v1/jobs", json!({ "scene_id": scene, "model": "instant-tiny", "budget": { "steps": 20 } }))
        .await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let est = v["memory_estimate_bytes"].as_u64().unwrap();
    assert!(est > 0 && est < 8 << 30, "{v}");
    let id = v["id"].as_str().unwrap();
    let done = svc.wait_job(id, 60.0, |j| j["status"] == "succeeded" || j["status"] == "failed").await;
    assert_eq!(done["status"], "succeeded", "{done}");
    svc.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_waits_while_running_jobs_hold_the_memory_budget() {
    let data = tempfile::tempdir().unwrap();
    // Learn the scene's size, then serve it with room for one job only.
    let svc = Svc::start(config(data.path())).await;
    let scene = svc.upload_ball().await;
    let (_, info) = svc.get(&format!("/v1/scenes/{scene}")).await;
    svc.stop().await;
    let info: SceneInfo = serde_json::from_value(info).unwrap();
    let model = ModelConfig::preset("nerf-tiny").unwrap();
    let one = estimate::training(&model, scene_data(&info, MaskUse::Auto), rayon::current_num_threads()).memory_bytes;
    let mut c = config(data.path());
    c.scheduler.max_concurrent = 2;
    c.scheduler.memory_budget_bytes = one * 3 / 2;
    c.scheduler.max_job_memory_bytes = one * 3 / 2;
    let svc = Svc::start(c).await;
    // `a` runs until canceled, so `b` is seen waiting for it on any machine.
    let a = svc.job(&scene, json!({ "seconds": 600 })).await;
    let b = svc.job(&scene, json!({ "steps": 10 })).await;
    let t0 = Instant::now();
    let mut canceled = false;
    let (ja, jb) = loop {
        // b read before a: b starts only once a has ended, so seeing both
        // running is a real overlap, not a's end and b's start between reads.
        let (_, jb) = svc.get(&format!("/v1/jobs/{b}")).await;
        let (_, ja) = svc.get(&format!("/v1/jobs/{a}")).await;
        assert_eq!(ja["memory_estimate_bytes"], one, "{ja}");
        assert!(!(ja["status"] == "running" && jb["status"] == "running"), "both run: {ja}\n{jb}");
        if !canceled {
            assert_eq!(jb["status"], "queued", "b did not wait for a: {ja}\n{jb}");
            if ja["status"] == "running" {
                // Held: b waits while a runs; now a frees the memory.
                let (s, v) = svc.post_json(&format!("/v1/jobs/{a}/cancel"), json!({})).await;
                assert_eq!(s, StatusCode::ACCEPTED, "{v}");
                canceled = true;
            }
        } else if jb["status"] != "queued" && jb["status"] != "running" {
            break (ja, jb);
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "timed out: {ja}\n{jb}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(ja["status"], "canceled", "{ja}");
    assert_eq!(jb["status"], "succeeded", "{jb}");
    let (a_end, b_start) = (ja["finished_at"].as_u64().unwrap(), jb["started_at"].as_u64().unwrap());
    assert!(b_start >= a_end, "b started at {b_start}, before a ended at {a_end}");
    svc.stop().await;
}

/// Every temporary file of an interrupted atomic write under `dir`.
fn temporaries(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(temporaries(&p));
        } else if radiance::engine::io::fsio::is_temporary(p.file_name().unwrap()) {
            out.push(p);
        }
    }
    out
}

fn kill(child: &mut std::process::Child) {
    child.kill().unwrap(); // SIGKILL: no chance to clean up
    child.wait().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_that_takes_the_server_down_twice_is_failed_at_the_next_start() {
    let data = tempfile::tempdir().unwrap();
    // No checkpoint within the test's time: the job never saves progress.
    let args = ["--checkpoint-every", "1000"];
    let (mut child, base) = spawn_binary_with(data.path(), &args);
    let mut svc = Svc::remote(base);
    let scene = svc.upload_ball().await;
    let (s, v) = svc
        .post_json("/v1/jobs", json!({ "scene_id": scene, "model": "instant-tiny", "budget": { "seconds": 600 } }))
        .await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let id = v["id"].as_str().unwrap().to_string();
    for attempt in 1..=2u32 {
        // Training steps show the job at work: its start is on disk before
        // its work begins (a kill between the scheduler starting it and
        // that write is not a crash of the job, and it is simply queued).
        let at_work = |j: &Value| j["status"] == "running" && j["attempts"] == attempt && j["progress"]["step"] != 0;
        svc.wait_job(&id, 60.0, at_work).await;
        kill(&mut child);
        let (c, base) = spawn_binary_with(data.path(), &args);
        (child, svc) = (c, Svc::remote(base));
        let (_, j) = svc.get(&format!("/v1/jobs/{id}")).await;
        assert_eq!(j["crashes"], attempt, "{j}");
        if attempt == 1 {
            assert_ne!(j["status"], "failed", "one crash is retried: {j}");
        } else {
            assert_eq!(j["status"], "failed", "{j}");
            assert!(j["error"].as_str().unwrap().contains("died 2 times"), "{j}");
        }
    }
    // The server is up and takes new work.
    let next = svc.job(&scene, json!({ "steps": 5 })).await;
    let done = svc.wait_job(&next, 60.0, |j| j["status"] == "succeeded" || j["status"] == "failed").await;
    assert_eq!(done["status"], "succeeded", "{done}");
    kill(&mut child);
}

/// The writer of `killed_mid_write_...`: run by that test in a child process
/// (this test binary again), it starts an atomic write of a checkpoint in
/// `RADIANCE_TEST_WRITE_DIR`, says so with a marker file, and never ends it.
#[test]
#[ignore = "a helper process of killed_mid_write_leaves_no_temporary_after_restart"]
fn helper_hangs_mid_write() {
    use std::io::Write;
    let dir = PathBuf::from(std::env::var("RADIANCE_TEST_WRITE_DIR").expect("run by the test that needs it"));
    radiance::engine::io::fsio::write_atomic_with(&dir.join("models/mdl_x.ckpt"), |w| {
        w.write_all(&vec![7u8; 1 << 20])?;
        w.flush()?;
        std::fs::write(dir.join("writing"), b"")?;
        loop {
            std::thread::sleep(Duration::from_secs(1));
        }
    })
    .unwrap();
}

#[test]
fn killed_mid_write_leaves_no_temporary_after_restart() {
    let data = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(data.path().join("models")).unwrap();
    let mut child = std::process::Command::new(std::env::current_exe().unwrap())
        .args(["helper_hangs_mid_write", "--exact", "--ignored", "--quiet"])
        .env("RADIANCE_TEST_WRITE_DIR", data.path())
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while !data.path().join("writing").exists() {
        assert!(t0.elapsed() < Duration::from_secs(30), "the writer never started");
        std::thread::sleep(Duration::from_millis(10));
    }
    kill(&mut child);
    let left = temporaries(data.path());
    assert_eq!(left.len(), 1, "the killed write left its temporary file: {left:?}");
    assert_eq!(std::fs::metadata(&left[0]).unwrap().len(), 1 << 20);
    assert!(!data.path().join("models/mdl_x.ckpt").exists(), "the write was never completed");
    // The real server on that data directory removes it at start-up.
    let (mut server, _) = spawn_binary(data.path());
    assert_eq!(temporaries(data.path()), Vec::<PathBuf>::new());
    kill(&mut server);
}

/// A tiny deterministic generator for the kill times (the seed is printed,
/// so a failing run can be repeated with RADIANCE_DRILL_SEED).
fn next_random(state: &mut u64) -> u64 {
    *state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    *state >> 33
}

/// The newest `updated_at` of the data directory's model records.
fn newest_checkpoint(data: &Path) -> u64 {
    std::fs::read_dir(data.join("models"))
        .unwrap()
        .filter_map(|e| {
            let p = e.ok()?.path();
            (p.extension()? == "json").then_some(())?;
            let v: Value = serde_json::from_slice(&std::fs::read(&p).ok()?).ok()?;
            v["updated_at"].as_u64()
        })
        .max()
        .unwrap_or(0)
}

/// Enqueues one of the drill's jobs: 14 s of training.
async fn drill_job(svc: &Svc, scene: &str) -> String {
    let body = json!({ "scene_id": scene, "model": "instant-tiny", "budget": { "seconds": 14 } });
    let (s, v) = svc.post_json("/v1/jobs", body).await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    v["id"].as_str().unwrap().to_string()
}

/// Runs of the jobs `jobs` (the list the API answers) that a kill cut
/// short: every start (`attempts`) but a job's current run or the one that
/// succeeded. A job found running at start-up is queued again with its
/// attempts, so each kill that landed while a job ran is counted once.
fn interrupted_runs(jobs: &Value) -> u64 {
    let runs = |j: &Value| {
        let current = j["status"] == "running" || j["status"] == "succeeded";
        j["attempts"].as_u64().unwrap() - current as u64
    };
    jobs.as_array().unwrap().iter().map(runs).sum()
}

/// Issue 14's drill: `kill -9`s at random moments while jobs train with a
/// checkpoint every second (some land mid-checkpoint), until 30 of them
/// have cut a running job short. Each kill waits for a checkpoint of the
/// current process first, so every job keeps making progress (two crashes
/// in a row without one fail a job by design). A job is added whenever all
/// have finished, so the drill does not depend on how much training each
/// life gets. After the next start: no temporary file, and every job
/// succeeds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_kills_during_training_lose_no_job_and_leave_no_temporary() {
    let data = tempfile::tempdir().unwrap();
    let args = ["--checkpoint-every", "1"];
    let mut seed: u64 = std::env::var("RADIANCE_DRILL_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64
    });
    eprintln!("kill drill: RADIANCE_DRILL_SEED={seed}");
    let (mut child, base) = spawn_binary_with(data.path(), &args);
    let mut svc = Svc::remote(base);
    let scene = svc.upload_ball().await;
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(drill_job(&svc, &scene).await);
    }
    let mut kills = 0;
    loop {
        let (_, jobs) = svc.get("/v1/jobs").await;
        let interrupted = interrupted_runs(&jobs);
        if interrupted >= 30 {
            eprintln!("{kills} kills cut {interrupted} runs short");
            break;
        }
        // Room for kills that miss (a job ending just before its kill).
        assert!(kills < 60, "{kills} kills cut only {interrupted} runs short: {jobs}");
        let mut started = radiance::datadir::now_ms();
        let t0 = Instant::now();
        // Until this process has written a checkpoint, with a job to cut short.
        loop {
            let (_, jobs) = svc.get("/v1/jobs").await;
            let open = jobs.as_array().unwrap().iter().any(|j| j["status"] == "queued" || j["status"] == "running");
            if !open {
                ids.push(drill_job(&svc, &scene).await);
                started = radiance::datadir::now_ms();
            } else if newest_checkpoint(data.path()) > started {
                break;
            }
            assert!(t0.elapsed() < Duration::from_secs(60), "no checkpoint within 60 s: {jobs}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // Then at a random moment within the next checkpoint interval.
        tokio::time::sleep(Duration::from_millis(next_random(&mut seed) % 1200)).await;
        kill(&mut child);
        kills += 1;
        let (c, base) = spawn_binary_with(data.path(), &args);
        (child, svc) = (c, Svc::remote(base));
        let left = temporaries(data.path());
        assert!(left.is_empty(), "after kill {kills}: {left:?}");
    }
    for id in &ids {
        let done = svc.wait_job(id, 120.0, |j| j["status"] != "queued" && j["status"] != "running").await;
        assert_eq!(done["status"], "succeeded", "{done}");
        let (_, m) = svc.get(&format!("/v1/models/{}", done["model_id"].as_str().unwrap())).await;
        assert!(m["training_seconds"].as_f64().unwrap() >= 14.0, "{m}");
    }
    let (_, jobs) = svc.get("/v1/jobs").await;
    assert_eq!(jobs.as_array().unwrap().len(), ids.len(), "{jobs}");
    kill(&mut child);
}
