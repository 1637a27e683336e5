//! The COLMAP and ffmpeg runs of a server under test, found in /proc, and
//! held still at a chosen stage of a poses job, so that a test kills the
//! server while that stage's program really runs, however fast or slow the
//! machine is (a stage seen through the API may already be over).

use std::path::Path;
use std::time::{Duration, Instant};

/// Processes (not zombies) whose command line names `dir`, as `pid: cmd`:
/// the COLMAP and ffmpeg runs of a server on that data directory (the
/// server itself left out).
pub fn processes_in(dir: &Path) -> Vec<String> {
    let needle = dir.display().to_string();
    let mut found = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        if !e.file_name().to_string_lossy().bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        let Ok(cmd) = std::fs::read(e.path().join("cmdline")) else { continue };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        if cmd.contains(&needle) && !cmd.contains("radiance serve") && !cmd.contains(" serve --addr") {
            found.push(format!("{}: {cmd}", e.file_name().to_string_lossy()));
        }
    }
    found
}

/// Whether a command line (its arguments) is the program that runs a poses
/// job's `stage`: COLMAP's subcommand (16 photos match exhaustively;
/// `matches_importer` is the sequential matcher's), or ffmpeg writing a
/// video's candidate frames.
fn runs_stage(stage: &str, args: &[&str]) -> bool {
    let colmap: &[&str] = match stage {
        "feature extraction" => &["feature_extractor"],
        "matching" => &["exhaustive_matcher", "matches_importer"],
        "mapping" => &["mapper"],
        "extracting video frames" => return args.iter().any(|a| a.ends_with("c_%05d.jpg")),
        _ => panic!("no program of a poses job runs during {stage}"),
    };
    args.iter().any(|a| colmap.contains(a))
}

/// Waits for the program of `stage` run by the server on `dir`, and stops
/// its process group (SIGSTOP) the moment it is seen: the stage then stays
/// current until the server is killed (the kernel's SIGKILL for a dead
/// parent still ends a stopped process). /proc is read every 2 ms, so a
/// program is caught unless it runs for less than that. `ended` is asked
/// now and then whether the job is over, which fails the test at once
/// (the stage went by unseen). Returns the pid stopped.
pub async fn freeze_at(dir: &Path, stage: &str, mut ended: impl AsyncFnMut() -> bool) -> i32 {
    let t = Instant::now();
    for polls in 1u64.. {
        for p in processes_in(dir) {
            let (pid, cmd) = p.split_once(':').unwrap();
            let args: Vec<&str> = cmd.split(' ').collect();
            if !runs_stage(stage, &args) {
                continue;
            }
            let pid: libc::pid_t = pid.parse().unwrap();
            // Its whole group (the server starts each program in a group
            // of its own), or the process alone if it shares ours.
            // SAFETY: getpgid(2), getpgrp(2) and kill(2) on a pid just
            // read; they touch no memory.
            let stopped = unsafe {
                let group = libc::getpgid(pid);
                let target = if group > 0 && group != libc::getpgrp() { -group } else { pid };
                libc::kill(target, libc::SIGSTOP) == 0
            };
            if stopped {
                return pid;
            }
        }
        if polls % 250 == 0 {
            assert!(!ended().await, "the job ended before its {stage} was seen running");
        }
        assert!(t.elapsed() < Duration::from_secs(180), "no program of {stage} ran in 180 s");
        // An async sleep: a server in the test's own runtime keeps both
        // of its workers.
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    unreachable!()
}

/// Waits for the programs on `dir` to die with their killed server: they
/// go within seconds (the kernel's parent-death signal), not when the next
/// start reaps them; 10 s leaves room for a test thread starved on a
/// loaded machine.
pub fn wait_until_gone(dir: &Path, what: &str) {
    let t = Instant::now();
    while !processes_in(dir).is_empty() {
        assert!(t.elapsed() < Duration::from_secs(10), "orphans after a kill {what}: {:?}", processes_in(dir));
        std::thread::sleep(Duration::from_millis(50));
    }
}
