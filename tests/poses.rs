//! Pose estimation with the real COLMAP (and ffmpeg for videos), run as
//! subprocesses on photos this test renders: a textured procedural scene
//! (SIFT needs texture), whose true cameras the estimated ones must match up
//! to a similarity transform. CI installs both programs with apt; when they
//! are missing these tests fail, they do not skip.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use radiance::engine::dataset::textured::TexturedScene;
use radiance::engine::dataset::{Dataset, DatasetFormat, LoadOptions};
use radiance::engine::geometry::align::{angle_between_deg, mat_mul, similarity};
use radiance::engine::geometry::camera::Camera;
use radiance::poses::{self, Matcher, PoseError, PoseOptions, Progress, Stage, Tools, video};

mod common;
use common::poses::{noise_pngs, tools};

fn opts() -> PoseOptions {
    PoseOptions { threads: 2, time_limit: Duration::from_secs(300), ..Default::default() }
}

fn estimate(
    input: &Path,
    out: &Path,
    tools: &Tools,
    opts: &PoseOptions,
) -> (Result<poses::PoseReport, PoseError>, Vec<Progress>) {
    let mut seen = Vec::new();
    let r = poses::estimate(input, out, tools, opts, &mut |p| seen.push(p), &AtomicBool::new(false));
    (r, seen)
}

/// Nothing but `keep` is left in `dir` (no working folders).
fn only(dir: &Path, keep: &[&str]) {
    let mut names: Vec<String> =
        std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names, keep, "left in {}", dir.display());
}

fn rotation(c: &Camera) -> [[f64; 3]; 3] {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| c.c2w[i][j] as f64))
}

fn centre(c: &Camera) -> [f64; 3] {
    [0, 1, 2].map(|i| c.c2w[i][3] as f64)
}

/// The worst camera-centre error (in units of the ring's radius) and
/// orientation error (degrees) of `estimated` against `truth` after the
/// best similarity transform between their centres.
fn pose_errors(truth: &[Camera], estimated: &[Camera]) -> (f64, f64) {
    let (tc, ec): (Vec<_>, Vec<_>) = (truth.iter().map(centre).collect(), estimated.iter().map(centre).collect());
    let s = similarity(&ec, &tc).expect("cameras not on a line");
    let ring = 3.0;
    let mut worst = (0.0f64, 0.0f64);
    for (t, e) in truth.iter().zip(estimated) {
        let p = s.apply(centre(e));
        let d = (0..3).map(|k| (p[k] - centre(t)[k]).powi(2)).sum::<f64>().sqrt() / ring;
        let angle = angle_between_deg(&mat_mul(&s.rotation, &rotation(e)), &rotation(t));
        worst = (worst.0.max(d), worst.1.max(angle));
    }
    worst
}

#[test]
fn colmap_poses_rendered_photos_as_they_were_rendered() {
    let tools = tools();
    let dir = tempfile::tempdir().unwrap();
    let (photos, out) = (dir.path().join("photos"), dir.path().join("posed"));
    let scene = TexturedScene::default();
    let truth = scene.write_photos(&photos).unwrap();
    let (report, progress) = estimate(&photos, &out, &tools, &opts());
    let report = report.unwrap();
    assert_eq!((report.images, report.registered, report.models), (16, 16, 1), "{report:?}");
    assert!(report.unregistered.is_empty() && report.warnings.is_empty(), "{report:?}");
    assert_eq!(report.matcher, Matcher::Exhaustive);
    assert_eq!((report.width, report.height), (320, 240));
    assert!(report.points > 500, "{} points", report.points);
    let err = report.mean_reprojection_error_px.expect("model_analyzer reports an error");
    assert!(err > 0.0 && err < 1.0, "mean reprojection error {err} px");
    // Progress went through every stage in order and ended at 1.
    let stages: Vec<Stage> = progress.iter().map(|p| p.stage).fold(Vec::new(), |mut v, s| {
        if v.last() != Some(&s) {
            v.push(s)
        }
        v
    });
    assert_eq!(stages, [Stage::Photos, Stage::Features, Stage::Matching, Stage::Mapping, Stage::Checking]);
    assert!(progress.windows(2).all(|w| w[1].fraction >= w[0].fraction - 1e-6));
    assert_eq!(progress.last().unwrap().fraction, 1.0);
    // The dataset is COLMAP format, complete, and nothing else is left.
    only(dir.path(), &["photos", "posed"]);
    only(&out, &["images", "poses.json", "sparse"]);
    let mut on_disk: poses::PoseReport =
        serde_json::from_slice(&std::fs::read(out.join("poses.json")).unwrap()).unwrap();
    // Times equal up to JSON's decimal round trip.
    assert!((on_disk.seconds.total - report.seconds.total).abs() < 1e-9);
    assert!((on_disk.seconds.matching - report.seconds.matching).abs() < 1e-9);
    on_disk.seconds = report.seconds.clone();
    assert_eq!(on_disk, report);
    let ds = Dataset::load(&out, &LoadOptions { splits: vec![], ..Default::default() }).unwrap();
    assert_eq!(ds.format, DatasetFormat::Colmap);
    let estimated: Vec<Camera> = ds.frames.iter().map(|f| f.camera.clone()).collect();
    let names: Vec<&str> = ds.frames.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, (0..16).map(|k| format!("view_{k:03}")).collect::<Vec<_>>());
    // Up to a similarity, every camera is where it was rendered from: within
    // 1.5% of the ring's radius and 1 degree (measured 0.4-0.5% and 0.25-0.4 degrees
    // in three runs on the 2-core VM).
    let (d, angle) = pose_errors(&truth, &estimated);
    eprintln!("worst camera error after alignment: {:.4} of the radius, {angle:.3} degrees", d);
    assert!(d < 0.015 && angle < 1.0, "centre error {d} of the radius, orientation error {angle} degrees");
    // And the focal length COLMAP found is the one rendered with (2%).
    let f = estimated[0].fx / truth[0].fx;
    assert!((f - 1.0).abs() < 0.02, "focal length ratio {f}");
}

#[test]
fn a_video_gives_its_sharp_frames_and_they_pose() {
    let tools = tools();
    let dir = tempfile::tempdir().unwrap();
    // 72 rendered frames around the ring; two of every three blurred, so
    // the sharp ones are the frames 1, 4, 7, ... (15 degrees apart).
    let scene = TexturedScene { width: 320, height: 240, views: 72, fov: 0.9 };
    let frames = dir.path().join("frames");
    scene.write_photos(&frames).unwrap();
    for k in 0..72 {
        if k % 3 != 1 {
            let p = frames.join(format!("view_{k:03}.png"));
            image::open(&p).unwrap().blur(2.5).save(&p).unwrap();
        }
    }
    let clip = dir.path().join("walk.mp4");
    let status = std::process::Command::new(&tools.ffmpeg.as_ref().unwrap().ffmpeg)
        .args(["-loglevel", "error", "-framerate", "12", "-i"])
        .arg(frames.join("view_%03d.png"))
        .args(["-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .status()
        .unwrap();
    assert!(status.success());
    // Frame extraction alone: 24 frames from 72 candidates, each the sharp one of its three.
    let (picked, scratch) = (dir.path().join("picked"), dir.path().join("scratch"));
    let cancel = AtomicBool::new(false);
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    let names = video::extract(
        tools.ffmpeg.as_ref().unwrap(),
        &clip,
        &picked,
        &scratch,
        24,
        800,
        deadline,
        &cancel,
        &mut |_| {},
    )
    .unwrap();
    assert_eq!(names.len(), 24);
    for (k, name) in names.iter().enumerate() {
        let got = image::open(picked.join(name)).unwrap().to_rgb8();
        let mse = |i: usize| {
            let want = image::open(frames.join(format!("view_{i:03}.png"))).unwrap().to_rgb8();
            got.as_raw().iter().zip(want.as_raw()).map(|(a, b)| (*a as f64 - *b as f64).powi(2)).sum::<f64>()
                / got.as_raw().len() as f64
        };
        let errors: Vec<f64> = (3 * k..3 * k + 3).map(mse).collect();
        // JPEG and H.264's colour subsampling leave some error even on the
        // right frame; the blurred neighbours are far further off.
        assert!(
            errors[1] < 200.0 && errors[1] * 5.0 < errors[0].min(errors[2]),
            "frame {name} is not the sharp frame {} (MSE against {}..={}: {errors:?})",
            3 * k + 1,
            3 * k,
            3 * k + 2
        );
    }
    // The whole way: the video in, 24 posed frames out, matched sequentially.
    let out = dir.path().join("posed");
    let (report, progress) = estimate(&clip, &out, &tools, &PoseOptions { frames: 24, ..opts() });
    let report = report.unwrap();
    // Matching moves in parts (one run of COLMAP each), not from 0 to 1.
    let mut matching: Vec<f32> =
        progress.iter().filter(|p| p.stage == Stage::Matching).map(|p| p.stage_fraction).collect();
    matching.dedup();
    assert!(matching.iter().filter(|f| **f > 0.0 && **f < 1.0).count() >= 3, "{matching:?}");
    assert_eq!((report.source.as_str(), report.images, report.matcher), ("video", 24, Matcher::Sequential));
    assert_eq!(report.registered, 24, "{report:?}");
    only(dir.path(), &["frames", "picked", "posed", "scratch", "walk.mp4"]);
}

#[test]
fn bad_photo_sets_fail_clearly_and_leave_nothing() {
    let tools = tools();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let err = |input: &Path, opts: &PoseOptions| {
        let (r, _) = estimate(input, &out, &tools, opts);
        let e = r.expect_err("should fail");
        assert!(!out.exists(), "{} was written after: {e}", out.display());
        e
    };

    // Nothing usable in the folder.
    let junk = dir.path().join("junk");
    std::fs::create_dir_all(&junk).unwrap();
    std::fs::write(junk.join("readme.txt"), "hello").unwrap();
    let e = err(&junk, &opts());
    assert!(matches!(e, PoseError::Input(_)) && e.to_string().contains("found only: readme.txt"), "{e}");

    // One photo.
    let one = dir.path().join("one");
    TexturedScene { views: 1, ..Default::default() }.write_photos(&one).unwrap();
    let e = err(&one, &opts());
    assert!(e.to_string().contains("1 photo found"), "{e}");

    // A photo that is not an image.
    let corrupt = dir.path().join("corrupt");
    TexturedScene { views: 4, ..Default::default() }.write_photos(&corrupt).unwrap();
    std::fs::write(corrupt.join("view_002.png"), b"\x89PNG truncated").unwrap();
    let e = err(&corrupt, &opts());
    assert!(e.to_string().contains("view_002.png"), "{e}");

    // Photos with nothing in common: noise, each its own.
    let noise = dir.path().join("noise");
    std::fs::create_dir_all(&noise).unwrap();
    for (name, png) in noise_pngs(5) {
        std::fs::write(noise.join(name), png).unwrap();
    }
    let e = err(&noise, &opts());
    assert!(matches!(e, PoseError::Reconstruction(_)), "{e}");
    assert!(e.to_string().contains("overlap"), "{e}");

    // A time limit too short for the run: COLMAP is stopped, nothing stays.
    let photos = dir.path().join("photos");
    TexturedScene::default().write_photos(&photos).unwrap();
    let t = std::time::Instant::now();
    let e = err(&photos, &PoseOptions { time_limit: Duration::from_millis(1500), ..opts() });
    assert!(matches!(e, PoseError::TimedOut { .. }), "{e}");
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    assert!(
        std::process::Command::new("pgrep")
            .args(["-f", &dir.path().display().to_string()])
            .status()
            .map_or(true, |s| !s.success()),
        "a COLMAP process outlived the timeout"
    );

    // COLMAP crashing: the real binary, starved of memory, dies mid-run.
    let starved = dir.path().join("starved-colmap");
    std::fs::write(&starved, format!("#!/bin/sh\nulimit -v 150000\nexec {} \"$@\"\n", tools.colmap.path.display()))
        .unwrap();
    std::fs::set_permissions(&starved, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let crashing =
        Tools { colmap: radiance::poses::Colmap { path: starved, version: "COLMAP (starved)".into() }, ffmpeg: None };
    let (r, _) = estimate(&photos, &out, &crashing, &opts());
    let e = r.expect_err("COLMAP without memory cannot succeed");
    assert!(matches!(e, PoseError::Tool(_)), "{e}");
    // (Under this limit COLMAP 3.8 aborts as it starts its threads.)
    assert!(e.to_string().contains("COLMAP's feature extraction failed: starved-colmap"), "{e}");
    assert!(!out.exists());

    // An output folder that holds something already is never touched.
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("keep.txt"), "mine").unwrap();
    let (r, _) = estimate(&photos, &out, &tools, &opts());
    let e = r.unwrap_err().to_string();
    assert!(e.contains("already exists and is not empty"), "{e}");
    assert_eq!(std::fs::read_to_string(out.join("keep.txt")).unwrap(), "mine");

    // No working folders left behind.
    only(dir.path(), &["corrupt", "junk", "noise", "one", "out", "photos", "starved-colmap"]);
}

#[test]
fn the_cli_writes_a_dataset_that_train_reads() {
    let dir = tempfile::tempdir().unwrap();
    let (photos, out) = (dir.path().join("photos"), dir.path().join("posed"));
    // Photos larger than the poses' size, downscaled to the size the other
    // tests' photos give COLMAP (at 200x150 it found too few matches in
    // about one run of 25).
    TexturedScene { width: 480, height: 360, ..TexturedScene::default() }.write_photos(&photos).unwrap();
    let bin = env!("CARGO_BIN_EXE_radiance");
    let run = std::process::Command::new(bin)
        .args(["poses", "--threads", "2", "--max-size", "320", "--images"])
        .arg(&photos)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&run.stderr));
    assert!(stdout.contains("posed 16 of 16 photos (320x240)"), "{stdout}");
    let ckpt = dir.path().join("m.ckpt");
    let train = std::process::Command::new(bin)
        .args(["train", "--threads", "2", "--steps", "20", "--data"])
        .arg(&out)
        .arg("--out")
        .arg(&ckpt)
        .output()
        .unwrap();
    assert!(train.status.success(), "{}", String::from_utf8_lossy(&train.stderr));
    assert!(ckpt.is_file());
    // A missing COLMAP is named, with how to get it.
    let missing = std::process::Command::new(bin)
        .args(["poses", "--colmap", "/nonexistent/colmap", "--images"])
        .arg(&photos)
        .arg("--out")
        .arg(dir.path().join("never"))
        .output()
        .unwrap();
    assert!(!missing.status.success());
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert!(stderr.contains("COLMAP not found") && stderr.contains("apt-get install colmap"), "{stderr}");
    assert!(!dir.path().join("never").exists());
}

#[test]
fn videos_without_enough_distinct_frames_fail_before_colmap_saying_how_many() {
    let tools = tools();
    let ffmpeg = tools.ffmpeg.as_ref().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let clip = |name: &str, source: &str, frames: u32| {
        let path = dir.path().join(name);
        let status = std::process::Command::new(&ffmpeg.ffmpeg)
            .args([
                "-loglevel",
                "error",
                "-f",
                "lavfi",
                "-i",
                &format!("{source}{}size=320x240:rate=12", if source.contains('=') { ":" } else { "=" }),
            ])
            .args(["-frames:v", &frames.to_string(), "-c:v", "libx264", "-pix_fmt", "yuv420p"])
            .arg(&path)
            .status()
            .unwrap();
        assert!(status.success());
        path
    };
    for (path, says) in [
        (clip("one.mp4", "testsrc", 1), "'one.mp4' has 1 distinct frame;"),
        (clip("still.mp4", "color=c=gray", 60), "'still.mp4' has 1 distinct frame (60 in all, the rest repeats)"),
    ] {
        let out = dir.path().join("out");
        let t = std::time::Instant::now();
        let (r, progress) = estimate(&path, &out, &tools, &opts());
        let e = r.unwrap_err();
        assert!(matches!(e, PoseError::Input(_)) && e.to_string().contains(says), "{e}");
        // Before any COLMAP step (the one-frame clip matched for 202 s).
        assert!(progress.iter().all(|p| p.stage == Stage::Frames), "{progress:?}");
        assert!(t.elapsed() < Duration::from_secs(30), "{:?}", t.elapsed());
        assert!(!out.exists());
    }
    // Probed as an upload is: the same answers, and a moving clip's counts.
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    let e = video::probe(ffmpeg, &dir.path().join("still.mp4"), "x/still.mp4", deadline).unwrap_err().to_string();
    assert!(e.contains("'x/still.mp4' has 1 distinct frame (60 in all"), "{e}");
    let p = video::probe(ffmpeg, &clip("moving.mp4", "testsrc", 36), "moving.mp4", deadline).unwrap();
    assert_eq!((p.width, p.height, p.frames, p.distinct), (320, 240, 36, Some(36)), "{p:?}");
    assert!((p.duration - 3.0).abs() < 0.1, "{p:?}");
}

#[test]
fn a_kept_working_folder_resumes_at_the_stage_it_stopped() {
    let tools = tools();
    let dir = tempfile::tempdir().unwrap();
    let (photos, out, keep) = (dir.path().join("photos"), dir.path().join("posed"), dir.path().join("work"));
    TexturedScene::default().write_photos(&photos).unwrap();
    let o = PoseOptions { resume_in: Some(keep.clone()), ..opts() };
    // Stopped as a shutdown stops it, once matching has begun.
    let cancel = AtomicBool::new(false);
    let stop = |p: Progress| {
        if p.stage == Stage::Matching {
            cancel.store(true, std::sync::atomic::Ordering::SeqCst);
        }
    };
    let r = poses::estimate(&photos, &out, &tools, &o, &mut { stop }, &cancel);
    assert!(matches!(r, Err(PoseError::Cancelled)), "{r:?}");
    assert!(!out.exists());
    let saved: serde_json::Value =
        serde_json::from_slice(&std::fs::read(keep.join(poses::PROGRESS_FILE)).unwrap()).unwrap();
    assert_eq!(saved["done"], serde_json::json!(["features"]), "{saved}");
    assert_eq!(saved["gathered"]["names"].as_array().map(Vec::len), Some(16), "{saved}");
    // The next run goes on from matching, and removes the folder at its end.
    let (report, progress) = estimate(&photos, &out, &tools, &o);
    let report = report.unwrap();
    assert_eq!((report.registered, report.seconds.features), (16, 0.0), "{report:?}");
    assert!(report.seconds.matching > 0.0 && report.seconds.mapping > 0.0, "{report:?}");
    assert!(progress.iter().any(|p| p.stage == Stage::Features && p.stage_fraction == 1.0));
    assert!(!keep.exists());
    only(dir.path(), &["photos", "posed"]);
    // A run that fails (not cancelled) removes its kept folder too.
    let noise = dir.path().join("noise");
    std::fs::create_dir_all(&noise).unwrap();
    for (name, png) in noise_pngs(5) {
        std::fs::write(noise.join(name), png).unwrap();
    }
    let (r, _) = estimate(&noise, &dir.path().join("never"), &tools, &o);
    assert!(matches!(r, Err(PoseError::Reconstruction(_))), "{r:?}");
    assert!(!keep.exists());
}
