//! Running an external program (COLMAP, ffmpeg) under a deadline and a
//! cancel flag, its output read line by line as it comes.
//!
//! The child runs in a process group of its own, so a timeout or a cancel
//! kills it and anything it started; its standard output and error are read
//! on two threads and handed, one line at a time, to the caller's callback;
//! the last lines are kept for the error message when it fails.
//!
//! No child outlives what started it: the kernel kills it when the thread
//! that started it dies (`PR_SET_PDEATHSIG`: the server killed with -9 takes
//! its COLMAP with it), a run that unwinds kills its group, and a caller
//! that names a registry ([`with_registry`]) has each running group listed
//! there (its id and start time), so the next start-up kills what a crash
//! left of them ([`reap`]).

use std::cell::RefCell;
use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read};
use std::os::unix::process::{CommandExt, ExitStatusExt};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::thread::JoinHandle;
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

thread_local! {
    /// Where this thread's runs list their process groups ([`with_registry`]).
    static REGISTRY: RefCell<Option<PathBuf>> = const { RefCell::new(None) };
}

/// Runs `f` with every program this thread starts meanwhile listed in the
/// folder `dir` while it runs (a file per process group, named by its id,
/// holding its start time), for [`reap`] to find after a crash.
pub fn with_registry<T>(dir: &Path, f: impl FnOnce() -> T) -> T {
    struct Reset(Option<PathBuf>);
    impl Drop for Reset {
        fn drop(&mut self) {
            REGISTRY.with(|r| *r.borrow_mut() = self.0.take());
        }
    }
    let _reset = Reset(REGISTRY.with(|r| r.borrow_mut().replace(dir.to_path_buf())));
    f()
}

/// Kills the process groups listed in `dir` (by a process that died without
/// ending them) that still run, and empties it. A listed id whose process
/// started at another time is another process now and is left alone.
/// Returns the groups killed.
pub fn reap(dir: &Path) -> Vec<u32> {
    let mut killed = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let listed = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok());
        let started = std::fs::read_to_string(e.path()).ok().and_then(|s| s.trim().parse::<u64>().ok());
        if let (Some(pgid), Some(started)) = (listed, started)
            && start_time(pgid) == Some(started)
        {
            // SAFETY: kill(2) of a process group; it touches no memory.
            unsafe { libc::kill(-(pgid as libc::pid_t), libc::SIGKILL) };
            killed.push(pgid);
        }
        let _ = std::fs::remove_file(e.path());
    }
    killed
}

/// When process `pid` started (clock ticks after boot, `/proc/PID/stat`
/// field 22); `None` when it does not exist.
pub fn start_time(pid: u32) -> Option<u64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The command name (field 2) may hold spaces: count after its `)`.
    stat[stat.rfind(')')? + 1..].split_whitespace().nth(19)?.parse().ok()
}

/// A started child: killed with its group, and taken off the registry,
/// however the run ends (an unwinding caller included).
struct Running {
    child: Child,
    listed: Option<PathBuf>,
    reaped: bool,
}

impl Running {
    /// Kills the group (what the child started too, should the child have
    /// ended), then reaps the child.
    fn kill(&mut self) {
        // SAFETY: kill(2) with a negative pid signals the child's own
        // process group (made by `process_group(0)`); it touches no memory.
        unsafe { libc::kill(-(self.child.id() as libc::pid_t), libc::SIGKILL) };
        if !self.reaped {
            let _ = self.child.kill();
            let _ = self.child.wait();
            self.reaped = true;
        }
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        self.kill();
        if let Some(p) = &self.listed {
            let _ = std::fs::remove_file(p);
        }
    }
}

/// Lists a started group in this thread's registry, if it has one.
fn list(pgid: u32) -> Option<PathBuf> {
    let dir = REGISTRY.with(|r| r.borrow().clone())?;
    let started = start_time(pgid)?;
    std::fs::create_dir_all(&dir).ok()?;
    let path = dir.join(pgid.to_string());
    std::fs::write(&path, started.to_string()).ok()?;
    Some(path)
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
    in_own_group(&mut cmd);
    let started = Instant::now();
    let child = cmd.spawn().map_err(|source| RunError::Spawn { program: program.clone(), source })?;
    let listed = list(child.id());
    let mut running = Running { child, listed, reaped: false };
    let (readers, rx) = read_output(&mut running.child);
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
    let status: ExitStatus = loop {
        match rx.recv_timeout(POLL) {
            Ok(line) => take(line, on_line),
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                // Both streams closed: the child is ending (or closed them
                // and goes on: the deadline still applies while waiting).
                if let Some(status) = wait_until(&mut running.child, deadline, cancel) {
                    running.reaped = true;
                    break status;
                }
            }
        }
        if cancel.load(Ordering::Relaxed) {
            running.kill();
            return Err(RunError::Cancelled);
        }
        if Instant::now() >= deadline {
            running.kill();
            return Err(RunError::TimedOut { program, seconds: started.elapsed().as_secs_f64() });
        }
        if let Ok(Some(status)) = running.child.try_wait() {
            running.reaped = true;
            // What it started and left running goes with it (and would hold
            // its output open); then drain what the readers still hold.
            // SAFETY: kill(2) of the child's process group; no memory.
            unsafe { libc::kill(-(running.child.id() as libc::pid_t), libc::SIGKILL) };
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
    Err(RunError::Failed { program, failure: failure(status), tail: tail.into() })
}

/// Sets `cmd` up to run in a process group of its own, with no input and
/// its output piped, killed when the thread that starts it dies.
fn in_own_group(cmd: &mut Command) {
    cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).process_group(0);
    // SAFETY: getpid(2) before the fork, prctl(2) and getppid(2) in the
    // child between fork and exec: async-signal-safe calls on no memory.
    let parent = unsafe { libc::getpid() };
    unsafe {
        cmd.pre_exec(move || {
            // Killed when the thread that started it dies (with the server).
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL as libc::c_ulong, 0, 0, 0) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent died before the line above: exit at once.
            if libc::getppid() != parent {
                libc::_exit(137);
            }
            Ok(())
        });
    }
}

/// A thread for each of the child's output streams, sending its lines to
/// the receiver returned, which disconnects once both streams are closed.
fn read_output(child: &mut Child) -> (Vec<JoinHandle<()>>, mpsc::Receiver<String>) {
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
    (readers, rx)
}

/// How a run that did not succeed ended, as a clause ("exited with status 1").
fn failure(status: ExitStatus) -> String {
    match (status.code(), status.signal()) {
        (Some(code), _) => format!("exited with status {code}"),
        (None, Some(sig)) => format!("was killed by signal {sig} ({})", signal_name(sig)),
        _ => "failed".to_string(),
    }
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
    use std::os::unix::process::CommandExt;

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
        let pid_file = dir.path().join("grandchild");
        // The child starts a grandchild and writes its pid, then hangs.
        let script = format!("sleep 60 & echo $! > {}; sleep 60", pid_file.display());
        let t = Instant::now();
        let e = run(sh(&script), soon(3.0), &cancel, &mut |_| {}).unwrap_err();
        assert!(matches!(e, RunError::TimedOut { .. }), "{e}");
        // Stopped at the deadline, not when the 60 s sleep ends (30 s: room
        // for a starved thread).
        assert!(t.elapsed() < Duration::from_secs(30), "{:?}", t.elapsed());
        let pid = std::fs::read_to_string(&pid_file).expect("the child wrote its child's pid within 3 s");
        let pid: u32 = pid.trim().parse().unwrap();
        wait_for("the child's own child dies with it", 10.0, || !alive(pid));
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

    /// Whether process `pid` exists and is not a zombie.
    fn alive(pid: u32) -> bool {
        std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .and_then(|s| s[s.rfind(')')? + 1..].split_whitespace().next().map(|st| st != "Z"))
            .unwrap_or(false)
    }

    fn wait_for(what: &str, secs: f64, mut pred: impl FnMut() -> bool) {
        let t = Instant::now();
        while !pred() {
            assert!(t.elapsed().as_secs_f64() < secs, "{what} within {secs} s");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Run by `a_child_dies_with_the_process_that_started_it` in a child
    /// process (this test binary again): runs a long child that writes its
    /// pid to `RADIANCE_TEST_PROCESS_DIR/pid`.
    #[test]
    #[ignore = "a helper process of a_child_dies_with_the_process_that_started_it"]
    fn helper_runs_a_long_child() {
        let dir = PathBuf::from(std::env::var("RADIANCE_TEST_PROCESS_DIR").expect("run by the test that needs it"));
        let script = format!("echo $$ > {0}/pid.tmp && mv {0}/pid.tmp {0}/pid && exec sleep 60", dir.display());
        let _ = run(sh(&script), soon(120.0), &AtomicBool::new(false), &mut |_| {});
    }

    #[test]
    fn a_child_dies_with_the_process_that_started_it() {
        let dir = tempfile::tempdir().unwrap();
        let mut helper = Command::new(std::env::current_exe().unwrap())
            .args(["--ignored", "--exact", "poses::process::tests::helper_runs_a_long_child"])
            .env("RADIANCE_TEST_PROCESS_DIR", dir.path())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let pid_file = dir.path().join("pid");
        wait_for("the helper's child starts", 30.0, || pid_file.exists());
        let pid: u32 = std::fs::read_to_string(&pid_file).unwrap().trim().parse().unwrap();
        assert!(alive(pid));
        helper.kill().unwrap(); // SIGKILL: the helper cleans nothing up
        helper.wait().unwrap();
        // Without the parent-death signal the child would sleep on for a minute.
        wait_for("the orphaned child is killed", 5.0, || !alive(pid));
    }

    #[test]
    fn runs_are_listed_while_they_run_and_reaped_after_a_crash() {
        let dir = tempfile::tempdir().unwrap();
        let registry = dir.path().join("processes");
        // Listed while it runs (its start time in the file), off the list after.
        let mut seen = Vec::new();
        with_registry(&registry, || {
            run(sh("echo $$; sleep 0.2"), soon(10.0), &AtomicBool::new(false), &mut |l| {
                let pid: u32 = l.trim().parse().unwrap();
                let listed = std::fs::read_to_string(registry.join(l.trim())).unwrap();
                seen.push((pid, listed.trim().parse::<u64>().unwrap()));
            })
            .unwrap();
        });
        assert!(seen.len() == 1 && seen[0].1 > 0, "{seen:?}");
        assert_eq!(std::fs::read_dir(&registry).unwrap().count(), 0);
        // Outside `with_registry` nothing is listed.
        run(sh("true"), soon(10.0), &AtomicBool::new(false), &mut |_| {}).unwrap();
        assert_eq!(std::fs::read_dir(&registry).unwrap().count(), 0);

        // What a crash left: a listed group still running is killed; a
        // listed id whose process started at another time is not touched.
        let spawn = || Command::new("sleep").arg("60").process_group(0).spawn().unwrap();
        let (mut left, mut other) = (spawn(), spawn());
        std::fs::write(registry.join(left.id().to_string()), start_time(left.id()).unwrap().to_string()).unwrap();
        std::fs::write(registry.join(other.id().to_string()), "1").unwrap();
        assert_eq!(reap(&registry), [left.id()]);
        assert_eq!(left.wait().unwrap().signal(), Some(libc::SIGKILL));
        assert!(other.try_wait().unwrap().is_none(), "a process not of the registry was killed");
        let _ = other.kill();
        let _ = other.wait();
        assert_eq!(std::fs::read_dir(&registry).unwrap().count(), 0);
    }

    #[test]
    fn a_missing_program_is_a_spawn_error() {
        let cancel = AtomicBool::new(false);
        let e = run(Command::new("/nonexistent/colmap"), soon(5.0), &cancel, &mut |_| {}).unwrap_err();
        assert!(matches!(e, RunError::Spawn { .. }) && e.to_string().contains("could not start colmap"), "{e}");
    }
}
