//! The memory estimate against measurement: `radiance train` prints its
//! estimate before training and its measured peak (`VmHWM`) at the end; for
//! small and large configurations of every model the measured peak must
//! stay below the estimate, and the estimate within 2.5 times of it (an
//! estimate that is too high refuses jobs that would fit; one that is too
//! low lets a job take the machine down).

use std::process::Command;

use radiance::engine::dataset::synthetic::BallScene;

/// `(estimated MiB, measured MiB)` of a short training run.
fn estimate_and_peak(data: &str, out: &str, model: &str, sets: &[&str]) -> (f64, f64) {
    let mut args = vec!["train", "--data", data, "--model", model, "--steps", "3", "--threads", "2", "--out", out];
    for s in sets {
        args.extend(["--set", s]);
    }
    let o = Command::new(env!("CARGO_BIN_EXE_radiance")).args(&args).output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(o.status.success(), "{args:?}\n{stdout}\n{stderr}");
    let mib = |text: &str, key: &str| -> f64 {
        let line = text.lines().find(|l| l.starts_with(key)).unwrap_or_else(|| panic!("no '{key}' in {text}"));
        line[key.len()..].split_whitespace().next().unwrap().parse().unwrap()
    };
    (mib(&stderr, "estimated peak memory"), mib(&stdout, "peak memory"))
}

#[test]
#[cfg(target_os = "linux")]
fn measured_peak_is_below_the_estimate_and_within_a_factor_of_it() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ball");
    BallScene { size: 64, views: 16, ..Default::default() }.write_blender(&data).unwrap();
    let out = dir.path().join("m.ckpt");
    let (d, o) = (data.to_str().unwrap(), out.to_str().unwrap());
    let cases: [(&str, &[&str]); 7] = [
        ("instant", &[]),
        // Parameters dominate: 16 levels of 2^20 entries (32 M parameters).
        ("instant", &["grid.log2_table=20", "grid.finest_resolution=2048"]),
        // Activations dominate: wide MLPs and large chunks.
        ("instant", &["hidden=128", "samples_per_step=131072", "chunk_rays=1024"]),
        ("nerf", &["net.width=64", "net.depth=4", "net.skip=2"]),
        ("nerf", &["chunk_rays=256"]),
        ("capture", &[]),
        // Activations dominate: large chunks of rays with many samples.
        ("capture", &["chunk_rays=1024", "rays_per_step=4096", "samples=64", "proposal.coarse_samples=128"]),
    ];
    let mut report = Vec::new();
    for (model, sets) in cases {
        let (est, peak) = estimate_and_peak(d, o, model, sets);
        report.push(format!("{model} {sets:?}: estimate {est:.0} MiB, measured {peak:.0} MiB"));
        assert!(peak <= est && est <= 2.5 * peak, "{}", report.join("\n"));
    }
    eprintln!("{}", report.join("\n"));
}
