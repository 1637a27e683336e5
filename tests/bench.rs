//! `radiance bench` end to end on a tiny generated Blender-format scene:
//! the table, the JSON rows and the PNG plot.

use std::process::Command;

use radiance::cli::BenchReport;
use radiance::engine::dataset::synthetic::BallScene;

fn radiance(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_radiance")).args(args).env("RAYON_NUM_THREADS", "2").output().unwrap()
}

#[test]
fn bench_writes_table_json_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let json = dir.path().join("bench.json");
    let plot = dir.path().join("bench.png");
    let out = radiance(&[
        "bench",
        "--data",
        data.to_str().unwrap(),
        "--model",
        "instant",
        // Unsorted on purpose. The first step of the fresh model marches
        // the whole box (over a second here), later ones are far cheaper:
        // the second budget leaves room for several steps.
        "--budgets",
        "3,0.25",
        "--test-views",
        "1",
        "--json",
        json.to_str().unwrap(),
        "--plot",
        plot.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "stdout: {stdout}\nstderr: {}", String::from_utf8_lossy(&out.stderr));

    // The table: a header and one row per (model, budget), budgets in order.
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 3, "{stdout}");
    assert!(lines[0].starts_with("model") && lines[0].contains("PSNR") && lines[0].contains("peak MiB"), "{stdout}");
    let budgets: Vec<&str> = lines[1..].iter().map(|l| l.split_whitespace().nth(1).unwrap()).collect();
    assert_eq!(budgets, ["0.25", "3"], "{stdout}");
    for l in &lines[1..] {
        assert!(l.starts_with("instant "), "{l}");
        let last = l.split_whitespace().last().unwrap();
        if cfg!(target_os = "linux") {
            assert!(last.parse::<f64>().is_ok_and(|m| m > 0.0), "peak memory in {l}");
        } else {
            assert_eq!(last, "n/a");
        }
    }

    // The JSON: the same rows.
    let report: BenchReport = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(report.test_views, 1);
    let rows = &report.rows;
    assert_eq!(rows.iter().map(|r| r.budget_seconds).collect::<Vec<_>>(), [0.25, 3.0]);
    for r in rows {
        assert_eq!(r.model, "instant");
        assert!(r.psnr.is_finite() && r.psnr > 0.0, "{r:?}");
        assert!(r.ssim.is_finite() && r.ssim <= 1.0, "{r:?}");
        assert!(r.train_seconds >= r.budget_seconds, "{r:?}");
        assert!(r.rays > 0 && r.samples > 0 && r.samples_per_ray > 0.0 && r.render_ms > 0.0, "{r:?}");
    }
    // One slow step may cross both budgets (then both rows hold the same
    // scores), so counts never decrease but need not grow.
    assert!(rows[0].steps > 0 && rows[1].steps >= rows[0].steps, "steps never decrease: {rows:?}");
    assert!(rows[1].rays >= rows[0].rays && rows[1].train_seconds >= rows[0].train_seconds, "{rows:?}");
    // The table shows the JSON's PSNRs.
    for (l, r) in lines[1..].iter().zip(rows) {
        assert!(l.contains(&format!("{:.2}", r.psnr)), "{l} vs {r:?}");
    }

    // The plot decodes as an image.
    let img = radiance::media::png::decode_rgb(&std::fs::read(&plot).unwrap()).unwrap();
    assert_eq!(img.dimensions(), (800, 500));
    assert!(img.pixels().any(|p| p.0 != [255, 255, 255]), "the plot is not blank");
}

#[test]
fn bench_rejects_bad_arguments() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let d = data.to_str().unwrap();
    for (args, msg) in [
        (vec!["--model", "nope"], "unknown model 'nope'"),
        (vec!["--budgets", "0"], "--budgets must be positive"),
        (vec!["--test-views", "0"], "--test-views must be at least 1"),
        (vec!["--occlude", "1.5"], "share of occluded photos must be within 0 and 1"),
        (vec!["--occlude", "0.3", "--occluder-area", "0.3,0.1"], "an occluder's area must be within 0 and 1"),
        (vec!["--occlude", "0.3", "--occluder-cutouts", "/nonexistent"], "reading the cut-outs in /nonexistent"),
        (vec!["--occlude", "0.3", "--occluder-area", "0.1,0.2,0.3"], "--occluder-area takes one number or LEAST,MOST"),
        (vec!["--occlude", "0.3", "--occluders-per-photo", "1,1000"], "occluders per photo must be from 1 to 100"),
        (vec!["--occluder-area", "0.1"], "--occlude"),
    ] {
        let mut all = vec!["bench", "--data", d];
        all.extend(args);
        let out = radiance(&all);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(msg), "{all:?}: {err}");
    }
}

/// `--occlude` pastes occluders into the asked share of the training
/// photos (8 of them: 0.5 is 4), says so, lists them in the JSON, and the
/// run still scores its (clean) test views.
#[test]
fn bench_occludes_a_share_of_the_training_photos() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 32, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let json = dir.path().join("bench.json");
    let args = ["--model", "instant-tiny", "--budgets", "0.2", "--test-views", "1", "--occlude", "0.5"];
    let out = radiance(
        &[&["bench", "--data", data.to_str().unwrap()][..], &args[..], &["--json", json.to_str().unwrap()]].concat(),
    );
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "stdout: {stdout}\nstderr: {stderr}");
    assert!(stderr.contains("occluded 4 of 8 training photos"), "{stderr}");
    let report: BenchReport = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(report.occluded.len(), 4, "{:?}", report.occluded);
    // One or two occluders of 5-20% of the frame each, less what falls past
    // its edges.
    assert!(report.occluded.iter().all(|p| p.share > 0.0 && p.share <= 0.4), "{:?}", report.occluded);
    assert_eq!(report.rows.len(), 1);
    assert!(report.rows[0].psnr.is_finite());
}

/// `--model auto` benches the model `train` would choose (the ball's
/// transparent pixels: `instant`) under its own name, and says why; the
/// capture model's rows count its proposal samples: 64 + 32 per ray in
/// training (every ray of the scene can be sampled), at most that and at
/// least each level's first round of 8 in rendering (which stops rays
/// behind opaque matter).
#[test]
fn bench_resolves_auto_and_counts_proposal_samples() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let json = dir.path().join("bench.json");
    let args = ["--model", "auto,capture", "--budgets", "0.2", "--test-views", "1", "--json", json.to_str().unwrap()];
    let out = radiance(&[&["bench", "--data", data.to_str().unwrap()][..], &args[..]].concat());
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "stdout: {stdout}\nstderr: {stderr}");
    assert!(stderr.contains("model 'instant' (auto): 8 of 8 training images have transparent pixels"), "{stderr}");
    let lines: Vec<&str> = stdout.lines().collect();
    let columns: Vec<&str> = lines[0].split_whitespace().collect();
    assert_eq!(columns[8..10], ["smp/ray", "prop/ray"], "{stdout}");
    let report: BenchReport = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(report.model_choice.as_ref().map(|c| c.preset.as_str()), Some("instant"));
    let models: Vec<&str> = report.rows.iter().map(|r| r.model.as_str()).collect();
    assert_eq!(models, ["instant", "capture"], "{stdout}");
    let (instant, capture) = (&report.rows[0], &report.rows[1]);
    assert_eq!((instant.proposal_samples, instant.render_proposal_samples_per_ray), (0, 0.0), "{instant:?}");
    assert!(capture.rays > 0 && capture.proposal_samples == 96 * capture.rays, "{capture:?}");
    assert_eq!(capture.proposal_samples_per_ray, 96.0, "{capture:?}");
    assert!((16.0..=96.0).contains(&capture.render_proposal_samples_per_ray), "{capture:?}");
    // The table shows the JSON's proposal samples per ray.
    for (l, r) in lines[1..].iter().zip(&report.rows) {
        let cells: Vec<&str> = l.split_whitespace().collect();
        assert_eq!((cells[0], cells[7]), (r.model.as_str(), format!("{:.1}", r.proposal_samples_per_ray).as_str()));
    }
}

/// When `auto` chooses a capture model (opaque photographs all around: `capture-360`), the table has
/// the mean and fitted appearances' columns in its header and in its rows alike.
#[test]
fn bench_auto_capture_rows_have_the_mean_column() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_llff(&data).unwrap();
    let json = dir.path().join("bench.json");
    let args = ["--model", "auto", "--budgets", "0.2", "--test-views", "1", "--json", json.to_str().unwrap()];
    let out = radiance(&[&["bench", "--data", data.to_str().unwrap()][..], &args[..]].concat());
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "stdout: {stdout}\nstderr: {stderr}");
    assert!(stderr.contains("model 'capture-360' (auto)"), "{stderr}");
    let report: BenchReport = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let lines: Vec<&str> = stdout.lines().collect();
    assert!(lines[0].contains("PSNR dB  mean dB   fit dB cross dB"), "{stdout}");
    let mean = report.rows[0].psnr_mean.expect("a capture row has the mean appearance's PSNR");
    let fit = report.rows[0].psnr_fit.expect("a capture row has the fitted appearance's PSNR");
    let cross = report.rows[0].psnr_fit_whole.expect("and the cross-fitted whole frame's");
    let cells: Vec<&str> = lines[1].split_whitespace().collect();
    // model, budget, train s, steps, rays, samples, smp/ray, prop/ray, skip/ray, PSNR, mean, fit, cross.
    let want = (&*format!("{mean:.2}"), &*format!("{fit:.2}"), &*format!("{cross:.2}"));
    assert_eq!((cells[10], cells[11], cells[12]), want, "{stdout}");
}

/// `--bake`: after the last budget the model is baked into splats and
/// scored on the same views, a `splats` row with the bake's time, steps
/// and Gaussians; then as export gives them, after the floater cleanup
/// (`cleaned`) and through SPZ (`spz`), each with its file's bytes.
#[test]
fn bench_bakes_and_scores_the_splats() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 24, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let json = dir.path().join("bench.json");
    let d = data.to_str().unwrap();
    let args = ["bench", "--data", d, "--model", "instant-tiny", "--budgets", "4", "--test-views", "2", "--bake", "3"];
    let out = radiance(&[&args[..], &["--json", json.to_str().unwrap()]].concat());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "stdout: {stdout}\nstderr: {}", String::from_utf8_lossy(&out.stderr));
    let report: BenchReport = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    // A ring of cameras around the ball: the automatic crop's row too.
    let [source, splats, cleaned, spz, cropped] = &report.rows[..] else { panic!("five rows: {:?}", report.rows) };
    assert_eq!(cropped.model, "cropped");
    assert!(cropped.gaussians.unwrap() <= cleaned.gaussians.unwrap() && cropped.gaussians.unwrap() > 0);
    assert_eq!((source.model.as_str(), splats.model.as_str()), ("instant-tiny", "splats"));
    assert_eq!((cleaned.model.as_str(), spz.model.as_str()), ("cleaned", "spz"));
    let (kept, ply) = (cleaned.gaussians.unwrap(), cleaned.bytes.unwrap());
    assert!(kept <= splats.gaussians.unwrap() && spz.gaussians == Some(kept), "{cleaned:?} {spz:?}");
    assert_eq!(splats.bytes.unwrap(), radiance::engine::models::splats::export::ply_len(splats.gaussians.unwrap(), 4));
    assert!(spz.bytes.unwrap() * 3 < ply, "the .spz is a fraction of the .ply: {spz:?} {cleaned:?}");
    // The SPZ's quantisation costs little (its scales step by 6%, its
    // colours by 2/255: on this 24-pixel ball up to about half a dB).
    assert!((spz.psnr - cleaned.psnr).abs() < 1.5, "{spz:?} {cleaned:?}");
    let n = splats.gaussians.expect("the Gaussians are counted");
    assert!(n > 0 && splats.steps > 0 && splats.budget_seconds == 3.0, "{splats:?}");
    assert!(splats.train_seconds >= 3.0 && splats.train_seconds < 30.0, "the bake's own time: {splats:?}");
    // Scored: a baked ball is recognisably the ball.
    assert!(splats.psnr > 15.0 && splats.render_ms > 0.0, "{splats:?}");
    assert!(stdout.contains(&format!("{n} Gaussians")), "{stdout}");
}
