//! Running an external program (COLMAP, ffmpeg) under a deadline and a
//! cancel flag, its output read line by line as it comes.
//!
//! The child runs in a process group of its own, so a timeout or a cancel
//! kills it and anything it started; its standard output and error are read
//! on two threads and handed, one line at a time, to the caller's callback;
//! the last lines are kept for the error message when it fails.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::Path;
use std::process::{Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// How many of the last output lines a failure quotes.
const TAIL_LINES: usize = 12;

/// The longest output line kept (COLMAP's lines are short; a binary spewing
/// bytes must not grow a line without bound).
const MAX_LINE: usize = 4096;

/// How often the deadline and the cancel flag are looked at.
const POLL: Duration = Duration::from_millis(50);

/// Why a run did not succeed.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    #[error("could not start {program}: {source}")]
    Spawn { program: String, source: std::io::Error },
    #[error("{program} {failure}{}", tail_text(.tail))]
    Failed { program: String, failure: String, tail: Vec<String> },
    #[error("{program} did not finish within {seconds:.0} s and was stopped")]
    TimedOut { program: String, seconds: f64 },
    #[error("cancelled")]
    Cancelled,
}

fn tail_text(tail: &[String]) -> String {
    if tail.is_empty() { String::new() } else { format!("; its last output:\n  {}", tail.join("\n  ")) }
}

/// Runs `cmd` to the end, `deadline` at the latest, calling `on_line` with
/// each line it prints (standard output and error interleaved as they come).
/// A non-zero exit, a death by signal, the deadline passing or `cancel`
/// being set are errors; in the last two cases the child's process group is
/// killed before returning.
pub fn run(
    mut cmd: Command,
    deadline: Instant,
    cancel: &AtomicBool,
    on_line: &mut dyn FnMut(&str),
) -> Result<(), RunError> {
    let program = Path::new(cmd.get_program()).file_name().unwrap_or_default().to_string_lossy().into_owned();
    cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).process_group(0);
    let started = Instant::now();
    let mut child = cmd.spawn().map_err(|source| RunError::Spawn { program: program.clone(), source })?;
    let (tx, rx) = mpsc::channel::<String>();
    let readers: Vec<_> = [
        child.stdout.take().map(|s| Box::new(s) as Box<dyn Read + Send>),
        child.stderr.take().map(|s| Box::new(s) as Box<dyn Read + Send>),
    ]
    .into_iter()
    .flatten()
    .map(|stream| {
        let tx = tx.clone();
        std::thread::spawn(move || read_lines(stream, &tx))
    })
    .collect();
    drop(tx);
    let mut tail = VecDeque::with_capacity(TAIL_LINES);
    let mut take = |line: String, on_line: &mut dyn FnMut(&str)| {
        on_line(&line);
        if !line.trim().is_empty() {
            if tail.len() == TAIL_LINES {
                tail.pop_front();
            }
            tail.push_back(line);
        }
    };
    let kill = |child: &mut std::process::Child| {
        // SAFETY: kill(2) with a negative pid signals the child's own process
        // group (made by `process_group(0)` above); it touches no memory.
        unsafe { libc::kill(-(child.id() as libc::pid_t), libc::SIGKILL) };
        let _ = child.kill();
        let _ = child.wait();
    };
    let status: ExitStatus = loop {
        match rx.recv_timeout(POLL) {
            Ok(line) => take(line, on_line),
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                // Both streams closed: the child is ending (or closed them
                // and goes on: the deadline still applies while waiting).
                if let Some(status) = wait_until(&mut child, deadline, cancel) {
                    break status;
                }
            }
        }
        if cancel.load(Ordering::Relaxed) {
            kill(&mut child);
            return Err(RunError::Cancelled);
        }
        if Instant::now() >= deadline {
            kill(&mut child);
            return Err(RunError::TimedOut { program, seconds: started.elapsed().as_secs_f64() });
        }
        if let Ok(Some(status)) = child.try_wait() {
            // Drain what the readers still hold, then stop.
            for r in readers {
                let _ = r.join();
            }
            while let Ok(line) = rx.try_recv() {
                take(line, on_line);
            }
            break status;
        }
    };
    if status.success() {
        return Ok(());
    }
    let failure = match (status.code(), status.signal()) {
        (Some(code), _) => format!("exited with status {code}"),
        (None, Some(sig)) => format!("was killed by signal {sig} ({})", signal_name(sig)),
        _ => "failed".to_string(),
    };
    Err(RunError::Failed { program, failure, tail: tail.into() })
}

/// Runs `cmd` to the end within `timeout` and returns its first
/// `max_lines` lines of output (asking a program for its version or help).
pub fn first_lines(cmd: Command, timeout: Duration, max_lines: usize) -> Result<Vec<String>, RunError> {
    let mut lines = Vec::new();
    run(cmd, Instant::now() + timeout, &AtomicBool::new(false), &mut |l| {
        if lines.len() < max_lines {
            lines.push(l.to_string());
        }
    })?;
    Ok(lines)
}

/// Waits for the child to exit, polling the deadline and the cancel flag;
/// `None` when either ends the wait first (the caller kills the child).
fn wait_until(child: &mut std::process::Child, deadline: Instant, cancel: &AtomicBool) -> Option<ExitStatus> {
    while Instant::now() < deadline && !cancel.load(Ordering::Relaxed) {
        if let Ok(Some(status)) = child.try_wait() {
            return Some(status);
        }
        std::thread::sleep(POLL);
    }
    None
}

/// Splits a stream into lines (`\n` or `\r`, so progress bars redrawn in
/// place count as lines), lossily decoded, each cut at [`MAX_LINE`] bytes.
fn read_lines(stream: Box<dyn Read + Send>, tx: &mpsc::Sender<String>) {
    let mut reader = BufReader::new(stream);
    let mut line = Vec::new();
    loop {
        let buf = match reader.fill_buf() {
            Ok([]) | Err(_) => break,
            Ok(b) => b,
        };
        let n = buf.len();
        for &b in buf {
            if b == b'\n' || b == b'\r' {
                if tx.send(String::from_utf8_lossy(&line).into_owned()).is_err() {
                    return;
                }
                line.clear();
            } else if line.len() < MAX_LINE {
                line.push(b);
            }
        }
        reader.consume(n);
    }
    if !line.is_empty() {
        let _ = tx.send(String::from_utf8_lossy(&line).into_owned());
    }
}

fn signal_name(sig: i32) -> &'static str {
    match sig {
        libc::SIGSEGV => "segmentation fault",
        libc::SIGABRT => "aborted",
        libc::SIGKILL => "killed, perhaps for lack of memory",
        libc::SIGBUS => "bus error",
        libc::SIGILL => "illegal instruction",
        libc::SIGFPE => "arithmetic exception",
        libc::SIGTERM => "terminated",
        _ => "signal",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sh(script: &str) -> Command {
        let mut c = Command::new("sh");
        c.arg("-c").arg(script);
        c
    }

    fn soon(s: f64) -> Instant {
        Instant::now() + Duration::from_secs_f64(s)
    }

    #[test]
    fn lines_from_both_streams_reach_the_callback() {
        let mut seen = Vec::new();
        let cancel = AtomicBool::new(false);
        run(sh("printf 'a\\nb\\r'; echo c >&2; printf d"), soon(10.0), &cancel, &mut |l| seen.push(l.to_string()))
            .unwrap();
        seen.sort();
        assert_eq!(seen, ["a", "b", "c", "d"]);
    }

    #[test]
    fn a_failure_names_the_status_and_quotes_the_last_lines() {
        let cancel = AtomicBool::new(false);
        let e = run(sh("for i in $(seq 1 30); do echo line$i; done; exit 3"), soon(10.0), &cancel, &mut |_| {})
            .unwrap_err();
        let text = e.to_string();
        assert!(text.starts_with("sh exited with status 3"), "{text}");
        assert!(text.contains("line30") && text.contains("line19") && !text.contains("line18\n"), "{text}");
    }

    #[test]
    fn a_crash_is_named_by_its_signal() {
        let cancel = AtomicBool::new(false);
        let e = run(sh("kill -SEGV $$"), soon(10.0), &cancel, &mut |_| {}).unwrap_err();
        assert!(e.to_string().contains("signal 11 (segmentation fault)"), "{e}");
    }

    #[test]
    fn a_hang_is_stopped_at_the_deadline_with_its_children() {
        let cancel = AtomicBool::new(false);
        let dir = tempfile::tempdir().unwrap();
        let marker = dir.path().join("survived");
        // The grandchild would write the marker after 2 s if it outlived the kill.
        let script = format!("(sleep 2; touch {}) & sleep 60", marker.display());
        let t = Instant::now();
        let e = run(sh(&script), soon(0.5), &cancel, &mut |_| {}).unwrap_err();
        assert!(matches!(e, RunError::TimedOut { .. }), "{e}");
        assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
        std::thread::sleep(Duration::from_millis(2500));
        assert!(!marker.exists(), "the child's own child outlived the timeout");
    }

    #[test]
    fn cancel_stops_a_run() {
        let cancel = AtomicBool::new(false);
        let t = Instant::now();
        let mut n = 0;
        let e = run(sh("while true; do echo tick; sleep 0.05; done"), soon(30.0), &cancel, &mut |_| {
            n += 1;
            if n == 3 {
                cancel.store(true, Ordering::Relaxed);
            }
        })
        .unwrap_err();
        assert!(matches!(e, RunError::Cancelled), "{e}");
        assert!(t.elapsed() < Duration::from_secs(5));
    }

    #[test]
    fn a_missing_program_is_a_spawn_error() {
        let cancel = AtomicBool::new(false);
        let e = run(Command::new("/nonexistent/colmap"), soon(5.0), &cancel, &mut |_| {}).unwrap_err();
        assert!(matches!(e, RunError::Spawn { .. }) && e.to_string().contains("could not start colmap"), "{e}");
    }
}
