//! What the operating system says about this process and machine: the
//! time, peak resident memory, physical memory, free disk space. Linux
//! reads `/proc`; elsewhere the answers are `None`.

use std::path::Path;
use std::time::{SystemTime, UNIX_EPOCH};

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

/// Peak resident memory of this process in bytes (`VmHWM`).
pub fn peak_memory() -> Option<u64> {
    proc_kib("/proc/self/status", "VmHWM:")
}

/// Resets the peak resident memory to the current one (Linux 4.0+), so a
/// later [`peak_memory`] measures from here; harmless where unsupported.
pub fn reset_peak_memory() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Physical memory of the machine in bytes (`MemTotal`).
pub fn total_memory() -> Option<u64> {
    proc_kib("/proc/meminfo", "MemTotal:")
}

/// A `KEY: N kB` line of a `/proc` file, in bytes.
fn proc_kib(file: &str, key: &str) -> Option<u64> {
    let s = std::fs::read_to_string(file).ok()?;
    let line = s.lines().find(|l| l.starts_with(key))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Bytes available to this (unprivileged) user on the file system of `path`.
#[cfg(unix)]
pub fn free_disk(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    let mut s = std::mem::MaybeUninit::<libc::statvfs>::uninit();
    // SAFETY: `c` is a NUL-terminated path and `s` is a valid out pointer.
    let r = unsafe { libc::statvfs(c.as_ptr(), s.as_mut_ptr()) };
    if r != 0 {
        return None;
    }
    // SAFETY: statvfs returned 0, so it filled `s`.
    let s = unsafe { s.assume_init() };
    #[allow(clippy::unnecessary_cast)] // the field types differ between platforms
    Some(s.f_bavail as u64 * s.f_frsize as u64)
}

#[cfg(not(unix))]
pub fn free_disk(_path: &Path) -> Option<u64> {
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(target_os = "linux")]
    fn linux_answers_with_plausible_figures() {
        let total = total_memory().unwrap();
        assert!(total > 64 << 20, "{total}");
        // A fresh 32 MiB allocation, touched, shows in the peak.
        let before = peak_memory().unwrap();
        let v = vec![1u8; 32 << 20];
        assert!(v.iter().step_by(4096).all(|&b| b == 1));
        let after = peak_memory().unwrap();
        assert!(after >= before && after >= 32 << 20, "{before} -> {after}");
        assert!(after < total);
        let dir = tempfile::tempdir().unwrap();
        let free = free_disk(dir.path()).unwrap();
        assert!(free > 0);
        assert_eq!(free_disk(&dir.path().join("missing")), None);
    }
}
