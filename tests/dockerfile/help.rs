//! What the binary says about itself. Parsed from the built binary's
//! `--help` (clap), so no list of flags is kept here.

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;
use std::sync::OnceLock;

/// One subcommand's `--help`: its long flags, the environment variables it
/// reads (`[env: NAME]`) and the defaults it shows (`[default: V]`).
#[derive(Debug, Default)]
pub struct Help {
    pub flags: BTreeSet<String>,
    pub envs: BTreeSet<String>,
    pub defaults: BTreeMap<String, String>,
}

fn run_help(args: &[&str]) -> String {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_radiance"));
    cmd.args(args);
    // clap prints the current value of an env var next to its name; keep the help stable.
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("RADIANCE_") {
            cmd.env_remove(&k);
        }
    }
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "radiance {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

fn parse_help(text: &str) -> Help {
    let mut h = Help::default();
    let mut last: Option<String> = None;
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with('-') {
            for w in t.split_whitespace() {
                let w = w.trim_end_matches(',');
                if w.starts_with("--") {
                    h.flags.insert(w.to_string());
                    last = Some(w.to_string());
                }
            }
        }
        if let Some(i) = line.find("[env: ") {
            let rest = &line[i + 6..];
            let name: String = rest.chars().take_while(|c| *c != '=' && *c != ']').collect();
            h.envs.insert(name);
        }
        if let (Some(i), Some(flag)) = (line.find("[default: "), &last) {
            let rest = &line[i + 10..];
            h.defaults.insert(flag.clone(), rest[..rest.find(']').unwrap()].to_string());
        }
    }
    h
}

/// The subcommands `radiance --help` lists.
pub fn subcommands() -> &'static BTreeSet<String> {
    static S: OnceLock<BTreeSet<String>> = OnceLock::new();
    S.get_or_init(|| {
        let text = run_help(&["--help"]);
        let mut in_commands = false;
        let mut out = BTreeSet::new();
        for line in text.lines() {
            if line.trim().is_empty() {
                in_commands = false;
            } else if line.starts_with("Commands:") {
                in_commands = true;
            } else if in_commands && let Some(w) = line.split_whitespace().next() {
                out.insert(w.to_string());
            }
        }
        out.remove("help");
        out
    })
}

/// `--help` of a subcommand (cached: the mutation tests ask again and again).
pub fn help_of(sub: &str) -> Option<&'static Help> {
    static H: OnceLock<std::sync::Mutex<BTreeMap<String, &'static Help>>> = OnceLock::new();
    if !subcommands().contains(sub) {
        return None;
    }
    let mut m = H.get_or_init(Default::default).lock().unwrap();
    Some(*m.entry(sub.to_string()).or_insert_with(|| Box::leak(Box::new(parse_help(&run_help(&[sub, "--help"]))))))
}
