//! The command line end to end on a tiny generated Blender-format scene:
//! train, render, eval, and an independent check of eval's numbers.

use std::path::Path;
use std::process::Command;

use radiance::engine::dataset::synthetic::BallScene;

fn radiance(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_radiance")).args(args).env("RAYON_NUM_THREADS", "2").output().unwrap()
}

fn ok(out: &std::process::Output) -> String {
    let s = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(out.status.success(), "stdout: {s}\nstderr: {}", String::from_utf8_lossy(&out.stderr));
    s
}

#[test]
fn train_render_eval() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let model = dir.path().join("m.ckpt");
    let (d, m) = (data.to_str().unwrap(), model.to_str().unwrap());
    let run = radiance(&["train", "--data", d, "--steps", "2", "--batch-rays", "32", "--out", m]);
    let out = ok(&run);
    assert!(out.contains("steps          2") && out.contains("rays/s"), "{out}");
    assert!(model.exists());
    // `--model auto`, the default: the transparent ball gets the fast
    // model, and the reason is printed before training.
    let err = String::from_utf8_lossy(&run.stderr);
    let chosen = "model 'instant' (auto): 8 of 8 training images have transparent pixels: an object on an empty \
                  background, the fast model";
    assert!(err.starts_with(chosen) || err.contains(&format!("\n{chosen}\n")), "{err}");
    // Resuming with `auto` continues the checkpoint's model (and its choice).
    let more = dir.path().join("more.ckpt");
    ok(&radiance(&["train", "--data", d, "--steps", "3", "--resume", m, "--out", more.to_str().unwrap()]));
    let resumed = radiance::engine::train::persist::load(&more).unwrap();
    assert_eq!((resumed.model.kind(), resumed.state.step), ("instant", 3));
    assert_eq!(resumed.train.model_choice.map(|c| c.preset), Some("instant".to_string()));

    let renders = dir.path().join("renders");
    let r = renders.to_str().unwrap();
    ok(&radiance(&["render", "--model", m, "--data", d, "--limit", "2", "--out", r]));
    let mut names: Vec<_> = std::fs::read_dir(&renders).unwrap().map(|e| e.unwrap().file_name()).collect();
    names.sort();
    assert_eq!(names, vec!["r_8.png", "r_9.png"], "named by the frames' file stems");

    let out = ok(&radiance(&["eval", "--model", m, "--data", d, "--limit", "2"]));
    let last = out.lines().last().unwrap();
    let ours: f64 = last.split_whitespace().nth(3).unwrap().parse().unwrap();
    assert!(last.starts_with("2 views"), "{last}");

    // Independent check with the shared Python tool, when it can run here.
    let tool = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/tools/nerf_eval.py");
    let has_numpy = Command::new("python3").args(["-c", "import numpy, PIL"]).status().is_ok_and(|s| s.success());
    if !tool.exists() || !has_numpy {
        eprintln!("note: nerf_eval.py or numpy/Pillow unavailable; skipped the independent check");
        return;
    }
    let py = Command::new("python3").arg(&tool).args([d, r, "--limit", "2", "--json"]).output().unwrap();
    let v: serde_json::Value = serde_json::from_slice(&py.stdout).unwrap();
    let theirs = v["psnr"].as_f64().unwrap();
    assert!((ours - theirs).abs() < 0.01, "eval {ours} dB vs nerf_eval.py {theirs} dB");
}

#[test]
fn bad_input_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let m = dir.path().join("m.ckpt");
    let out = radiance(&["train", "--data", "/nonexistent/x", "--steps", "1", "--out", m.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/x") && err.contains("does not exist"), "{err}");
    std::fs::write(&m, b"not a checkpoint").unwrap();
    let out = radiance(&["eval", "--model", m.to_str().unwrap(), "--data", dir.path().to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("m.ckpt"), "{err}");
}

#[test]
fn serve_refuses_a_bad_retention() {
    for hours in ["-1", "NaN", "1e300"] {
        let err = serve_refusal(&[&format!("--keep-training-state-hours={hours}")], &[]);
        assert!(err.contains("--keep-training-state-hours must be a number of hours"), "{hours}: {err}");
    }
}

/// Runs `radiance serve` with `args` and `env`, which must refuse to start
/// (it is killed, and the test fails, if it is still running after 20 s);
/// returns what it printed on stderr.
fn serve_refusal(args: &[&str], env: &[(&str, &str)]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_radiance"));
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--data-dir", dir.path().to_str().unwrap()]).args(args);
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("RADIANCE_") {
            cmd.env_remove(&k);
        }
    }
    cmd.envs(env.iter().copied()).stdout(std::process::Stdio::null()).stderr(std::process::Stdio::piped());
    let mut child = cmd.spawn().unwrap();
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if t0.elapsed().as_secs() > 20 {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("serve started with {args:?} {env:?}");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    assert!(!status.success(), "{args:?} {env:?}: {err}");
    assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none(), "a refused node touched its data directory");
    err
}

#[test]
fn serve_refuses_roles_without_the_stores_they_need() {
    // An API node or a worker without the shared stores: refused, saying
    // what it needs; by flag or by variable.
    for (args, env) in [(&["--role", "api"][..], &[][..]), (&[][..], &[("RADIANCE_ROLE", "worker")][..])] {
        let err = serve_refusal(args, env);
        assert!(
            err.contains("needs the shared stores of distributed mode (--database-url and --object-store)"),
            "{err}"
        );
        assert!(err.contains("--role all"), "{err}");
    }
    // One store without the other.
    let err = serve_refusal(&["--role", "api", "--object-store", "s3://bucket/radiance"], &[]);
    assert!(err.contains("--database-url and --object-store go together"), "{err}");
    // Both, but no database answers: refused once the start-up wait is
    // over, naming the server and not echoing the password.
    let err = serve_refusal(
        &["--role", "api", "--object-store", "s3://bucket/radiance", "--startup-wait-seconds", "1"],
        &[("RADIANCE_DATABASE_URL", "postgres://radiance:s3cret@127.0.0.1:1/radiance")],
    );
    assert!(err.contains("PostgreSQL (127.0.0.1:1") && err.contains("is not reachable"), "{err}");
    assert!(!err.contains("s3cret"), "{err}");
    // A role that does not exist is clap's error, listing the roles.
    let err = serve_refusal(&["--role", "leader"], &[]);
    assert!(err.contains("leader") && err.contains("all, api, worker"), "{err}");
}

/// `radiance demo`: a scene, a trained model and an orbit video from no data.
#[test]
fn demo_needs_no_data() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let o = out.to_str().unwrap();
    let printed = ok(&radiance(&["demo", "--out", o, "--steps", "200", "--frames", "4"]));
    let video = out.join(if cfg!(feature = "mp4") { "orbit.mp4" } else { "orbit.gif" });
    assert_eq!(printed.trim(), video.to_str().unwrap());
    let bytes = std::fs::read(&video).unwrap();
    if cfg!(feature = "mp4") {
        assert_eq!(&bytes[4..8], b"ftyp", "an MP4 starts with its ftyp box");
    }
    assert!(bytes.len() > 1000, "{} bytes", bytes.len());
    assert!(out.join("scene/transforms_train.json").exists());
    // The model learned the scene: eval on its held-out views.
    let (m, d) = (out.join("model.ckpt"), out.join("scene"));
    let e = ok(&radiance(&["eval", "--model", m.to_str().unwrap(), "--data", d.to_str().unwrap(), "--limit", "2"]));
    let psnr: f64 = e.lines().last().unwrap().split_whitespace().nth(3).unwrap().parse().unwrap();
    // 200 steps score about 17.8 dB; a blank white frame scores about 7 dB
    // on these views, their mean colour 10 to 11.
    assert!(psnr > 16.0, "demo model PSNR {psnr} dB:\n{e}");
    // An orbit video of it with no parameters: around the point the training
    // cameras look at (the mug), from their distance.
    let gif = dir.path().join("orbit.gif");
    let g = gif.to_str().unwrap();
    let printed =
        ok(&radiance(&["video", "--model", m.to_str().unwrap(), "--out", g, "--frames", "4", "--width", "32"]));
    assert_eq!(printed.trim(), g);
    use image::AnimationDecoder;
    let decoder =
        image::codecs::gif::GifDecoder::new(std::io::BufReader::new(std::fs::File::open(&gif).unwrap())).unwrap();
    let frames = decoder.into_frames().collect_frames().unwrap();
    assert_eq!(frames.len(), 4);
    for f in &frames {
        let im = f.buffer();
        assert_eq!(im.dimensions(), (32, 32));
        let sum = |x, y| im.get_pixel(x, y).0[..3].iter().map(|&c| c as u32).sum::<u32>();
        // The mug is in the middle; above it, the top corners are the white
        // background (the mat fills the bottom ones).
        assert!(sum(16, 16) < 700, "centre {:?}", im.get_pixel(16, 16));
        assert!(sum(0, 0) > 700 && sum(31, 0) > 700, "corners {:?} {:?}", im.get_pixel(0, 0), im.get_pixel(31, 0));
    }
    let bad = radiance(&["video", "--model", m.to_str().unwrap(), "--out", dir.path().join("o.avi").to_str().unwrap()]);
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("write a .mp4 or a .gif"));
    // Bad input is a clear error.
    let bad = radiance(&["demo", "--out", o, "--seconds", "0"]);
    assert!(!bad.status.success() && String::from_utf8_lossy(&bad.stderr).contains("--seconds"));
}

/// `--masks` on train, eval, render and bench, on the ball as an LLFF scene
/// with its silhouettes in `masks_8/`.
#[test]
fn masks_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    let ball = BallScene { size: 16, views: 8, ..Default::default() };
    ball.write_llff(&data).unwrap();
    std::fs::rename(data.join("images"), data.join("images_8")).unwrap();
    std::fs::create_dir_all(data.join("masks_8")).unwrap();
    for (k, f) in ball.dataset().frames.iter().enumerate() {
        let alpha: Vec<u8> = f.image.rgba.chunks(4).map(|p| p[3]).collect();
        let mask = image::GrayImage::from_raw(f.image.width, f.image.height, alpha).unwrap();
        mask.save(data.join(format!("masks_8/img{k:03}.png"))).unwrap();
    }
    let model = dir.path().join("m.ckpt");
    let (d, m) = (data.to_str().unwrap(), model.to_str().unwrap());

    let out = radiance(&["train", "--data", d, "--steps", "2", "--masks", "ignore", "--out", m]);
    ok(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("masks from masks_8/") && err.contains("ignore: training draws only"), "{err}");
    assert!(err.contains("training pixels inside the masks"), "the estimate counts the lists: {err}");

    // eval: `auto` scores inside the masks too, `off` does not.
    let out = ok(&radiance(&["eval", "--model", m, "--data", d]));
    // (A capture model, auto's choice for these opaque photos, first says
    // which appearance scores the views, and how they are fitted.)
    let heading = |l: &str| l.starts_with("appearance: ") || l.starts_with("fitted: ");
    assert!(out.lines().filter(|l| !heading(l)).all(|l| l.contains(" | inside mask PSNR ")), "{out}");
    assert!(out.lines().last().unwrap().starts_with("2 views"), "{out}");
    let out = ok(&radiance(&["eval", "--model", m, "--data", d, "--masks", "off"]));
    assert!(!out.contains("inside mask"), "{out}");

    // bench: two more columns and the JSON fields.
    let json = dir.path().join("bench.json");
    let args =
        ["bench", "--data", d, "--model", "instant", "--budgets", "0.25", "--test-views", "1", "--masks", "score"];
    let out = ok(&radiance(&[&args[..], &["--json", json.to_str().unwrap()]].concat()));
    assert!(out.lines().next().unwrap().contains("PSNR dB    SSIM  mask dB  mask SSIM  ms/view"), "{out}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    assert_eq!(report["masks"], "score");
    let row = &report["rows"][0];
    assert!(row["psnr_mask"].as_f64().is_some() && row["ssim_mask"].as_f64().is_some(), "{row}");

    // A missing mask fails loading, naming it, unless the masks are off.
    std::fs::remove_file(data.join("masks_8/img009.png")).unwrap();
    let out = radiance(&["eval", "--model", m, "--data", d]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("img009.png") && err.contains("--masks off"), "{err}");
    let renders = dir.path().join("renders");
    ok(&radiance(&["render", "--model", m, "--data", d, "--masks", "off", "--out", renders.to_str().unwrap()]));

    let out = radiance(&["train", "--data", d, "--masks", "sometimes", "--out", m]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("auto, score, ignore, composite or off"), "{err}");
}

/// A capture model's appearance on the command line: `eval` scores with the
/// nearest training camera's appearance and prints the mean's beside it,
/// `render` and `video` take a training image's index, and an index the
/// model did not train on is an error naming the images it did.
#[test]
fn appearance_on_the_command_line() {
    use radiance::engine::dataset::{Dataset, LoadOptions};

    use radiance::engine::models::config::ModelConfig;
    use radiance::engine::models::training::Budget;
    use radiance::engine::train::persist;
    use radiance::engine::train::trainer::{TrainState, Trainer};
    use radiance::engine::view::appearance::index_ranges;

    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let model = dir.path().join("c.ckpt");
    let (d, m) = (data.to_str().unwrap(), model.to_str().unwrap());
    // `capture-tiny` is a preset of the library's (the command line trains the full presets).
    let ds = Dataset::load(&data, &LoadOptions::default()).unwrap();
    let config = ModelConfig::preset("capture-tiny").unwrap();
    let (net, adam) = config.build_with_adam(ds.scene(), 1, None).unwrap();
    let train = config.train_config(1, 256, Budget { steps: Some(3), seconds: None });
    let mut t = Trainer::new(net, adam, train, TrainState::default(), &ds);
    t.run(&std::sync::atomic::AtomicBool::new(false), |_, _| true);
    persist::save(&model, &*t.model, &t.adam, &t.config, &t.state, None).unwrap();
    let trained = t.model.appearance().map(|a| a.images()).unwrap();
    assert!(!trained.is_empty());

    let views = dir.path().join("views");
    let out = ok(&radiance(&["eval", "--model", m, "--data", d, "--limit", "2", "--out", views.to_str().unwrap()]));
    assert!(out.starts_with("appearance: the nearest training camera's"), "{out}");
    // --out holds each view and, beside it, the view with its fitted appearance.
    let mut names: Vec<String> =
        std::fs::read_dir(&views).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names.len(), 4, "{names:?}");
    for pair in names.chunks(2) {
        assert_eq!(pair[1], pair[0].replace(".png", "_fitted.png"), "{names:?}");
    }
    let last = out.lines().last().unwrap();
    assert!(last.starts_with("2 views  PSNR ") && last.contains(" dB (mean "), "{last}");
    // Each view is also scored on its right half with an appearance fitted on its left half, and
    // whole, each half with the other's fit.
    assert!(out.lines().nth(1).unwrap().starts_with("fitted: appearances fitted on each view's halves"), "{out}");
    assert!(last.contains(") (fitted right half ") && last.contains(", whole frame "), "{last}");
    // With the mean asked for, both numbers are the same; `--fit-steps 0` fits nothing.
    let out =
        ok(&radiance(&["eval", "--model", m, "--data", d, "--limit", "1", "--appearance", "mean", "--fit-steps", "0"]));
    assert!(!out.contains("fitted"), "{out}");
    let line = out.lines().nth(1).unwrap();
    let words: Vec<&str> = line.split_whitespace().collect();
    assert_eq!((words[4], words[5]), ("(mean", &*format!("{})", words[2])), "{line}");

    let renders = dir.path().join("renders");
    let r = renders.to_str().unwrap();
    let first = trained[0].to_string();
    ok(&radiance(&["render", "--model", m, "--data", d, "--limit", "1", "--appearance", &first, "--out", r]));
    assert_eq!(std::fs::read_dir(&renders).unwrap().count(), 1);
    let gif = dir.path().join("o.gif");
    let g = gif.to_str().unwrap();
    for cmd in [
        vec!["render", "--model", m, "--data", d, "--appearance", "99999", "--out", r],
        vec!["eval", "--model", m, "--data", d, "--appearance", "99999"],
        vec!["video", "--model", m, "--out", g, "--frames", "2", "--appearance", "99999"],
    ] {
        let out = radiance(&cmd);
        let err = String::from_utf8_lossy(&out.stderr);
        let want = format!("training images: {}", index_ranges(&trained));
        assert!(!out.status.success() && err.contains("99999") && err.contains(&want), "{cmd:?}: {err}");
    }
    assert!(!gif.exists());
    let out = radiance(&["render", "--model", m, "--data", d, "--appearance", "bright", "--out", r]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("expected mean, nearest or a training image's index"), "{err}");
}

/// `serve`'s log written to a file (or a pipe) is plain text: no terminal
/// colour codes, which would litter a log file or a container's log.
#[test]
fn a_served_log_in_a_file_has_no_colour_codes() {
    use std::io::BufRead;
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("serve.log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_radiance"))
        .args(["serve", "--addr", "127.0.0.1:0", "--threads", "1", "--data-dir"])
        .arg(dir.path().join("data"))
        .env_remove("RADIANCE_API_KEY")
        .env_remove("NO_COLOR")
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.starts_with("listening on "), "{line}");
    // The start-up lines are logged before the address is printed; give
    // the writer a moment, bounded.
    let t0 = std::time::Instant::now();
    while std::fs::read_to_string(&log).unwrap().is_empty() && t0.elapsed().as_secs() < 10 {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let _ = child.kill();
    let _ = child.wait();
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.contains("INFO") && text.contains("listening"), "the log has its lines: {text}");
    assert!(!text.contains('\u{1b}'), "colour codes in a log file: {text:?}");
}

/// Transients: a `capture` model drops them by default (`--keep-transients`
/// trains on every pixel); `--drop-transients` is refused for a model that
/// cannot find them (nothing written); with `bench --occlude`, the masks
/// found are scored against the pasted ones, printed and kept in the JSON
/// report.
#[test]
fn drop_transients_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 16, views: 8, ..Default::default() }.write_blender(&data).unwrap();
    let model = dir.path().join("m.ckpt");
    let (d, m) = (data.to_str().unwrap(), model.to_str().unwrap());
    let out = radiance(&["train", "--data", d, "--model", "instant", "--steps", "2", "--drop-transients", "--out", m]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--drop-transients needs a capture model"), "{err}");
    assert!(!model.exists());

    let json = dir.path().join("bench.json");
    let saved = dir.path().join("saved");
    let args = ["bench", "--data", d, "--model", "capture-tiny", "--budgets", "0.5", "--test-views", "1"];
    let more = ["--occlude", "0.5", "--json", json.to_str().unwrap()];
    let out = ok(&radiance(&[&args[..], &more[..], &["--save", saved.to_str().unwrap()]].concat()));
    assert!(out.contains("transient masks: ") && out.contains("% of the static pixels"), "{out}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    // --save: each occluded photo with the mask found, and the view scored.
    let mut names: Vec<String> =
        std::fs::read_dir(&saved).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    let occluded = report["occluded"].as_array().unwrap();
    assert_eq!(names.len(), 2 * occluded.len() + 1, "{names:?}");
    for p in occluded {
        let name = p["name"].as_str().unwrap();
        for suffix in ["occluded", "found"] {
            let img = image::open(saved.join(format!("{name}.{suffix}.png"))).unwrap();
            assert_eq!((img.width(), img.height()), (16, 16));
        }
    }
    assert!(names.iter().any(|n| n.starts_with("capture_") && n.ends_with(".png")), "{names:?}");
    let found = &report["found"];
    for key in ["recall", "static_share"] {
        let v = found[key].as_f64().unwrap_or(-1.0);
        assert!((0.0..=1.0).contains(&v), "{key}: {found}");
    }
    // Trained on every pixel, nothing is scored.
    let out = ok(&radiance(&[&args[..], &["--occlude", "0.5", "--keep-transients"]].concat()));
    assert!(!out.contains("transient masks"), "{out}");
    let both = radiance(&[&args[..], &["--drop-transients", "--keep-transients"]].concat());
    assert!(!both.status.success(), "{}", String::from_utf8_lossy(&both.stdout));

    // `train` reports what it dropped and writes one mask a training photo,
    // named by its stem, of its size, 0 or 255.
    let masks = dir.path().join("masks");
    let args = ["train", "--data", d, "--model", "capture-tiny", "--steps", "20", "--out", m];
    let instant = ["train", "--data", d, "--model", "instant", "--steps", "2", "--out", m];
    let out = radiance(&[&instant[..], &["--transient-masks", masks.to_str().unwrap()]].concat());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--transient-masks needs a capture model"), "{err}");
    assert!(!model.exists() && !masks.exists());
    let out = radiance(&[&args[..], &["--keep-transients", "--transient-masks", masks.to_str().unwrap()]].concat());
    assert!(!out.status.success() && !masks.exists(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = ok(&radiance(&[&args[..], &["--transient-masks", masks.to_str().unwrap()]].concat()));
    assert!(out.contains("transients     ") && out.contains("% of the training pixels dropped, in "), "{out}");
    let mut stems: Vec<String> = std::fs::read_dir(data.join("train"))
        .unwrap()
        .map(|e| e.unwrap().path().file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    let mut written: Vec<String> = std::fs::read_dir(&masks)
        .unwrap()
        .map(|e| e.unwrap().path().file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    stems.sort();
    written.sort();
    assert_eq!(written, stems);
    assert!(out.contains(&format!("masks          {} in ", stems.len())), "{out}");
    let img = image::open(masks.join(format!("{}.png", stems[0]))).unwrap().to_luma8();
    assert_eq!(img.dimensions(), (16, 16));
    assert!(img.pixels().all(|p| p.0[0] == 0 || p.0[0] == 255));
    // The checkpoint keeps the maps.
    let maps = radiance::engine::front::load_checkpoint(&model).unwrap().transients.expect("maps saved");
    assert_eq!(maps.photos().len(), stems.len());

    // `train --model splats`: its field (a capture model for these opaque
    // photos) drops transients, and its masks are written too (the flag
    // asks for what is the default).
    let llff = dir.path().join("llff");
    BallScene { size: 16, views: 8, ..Default::default() }.write_llff(&llff).unwrap();
    let masks = dir.path().join("splat_masks");
    let splats = dir.path().join("s.ckpt");
    let args = ["train", "--data", llff.to_str().unwrap(), "--model", "splats", "--seconds", "4"];
    let more = ["--drop-transients", "--transient-masks", masks.to_str().unwrap(), "--out", splats.to_str().unwrap()];
    let out = ok(&radiance(&[&args[..], &more[..]].concat()));
    assert!(out.contains("transients     ") && out.contains("(the field's)"), "{out}");
    assert!(std::fs::read_dir(&masks).unwrap().count() > 0 && splats.exists(), "{out}");
    // An `instant` field (the transparent ball) finds none: refused.
    let (masks, splats) = (dir.path().join("no_masks"), dir.path().join("no.ckpt"));
    let args = ["train", "--data", d, "--model", "splats", "--seconds", "4", "--out", splats.to_str().unwrap()];
    let out = radiance(&[&args[..], &["--transient-masks", masks.to_str().unwrap()]].concat());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--transient-masks needs a capture field"), "{err}");
    assert!(!masks.exists() && !splats.exists() && !dir.path().join("no.field.ckpt").exists());
}
