//! The Dockerfile against the binary and the README: the image must build the
//! real binary, run a real subcommand with real flags, set only environment
//! variables `radiance serve` reads, expose and health-check the port it
//! listens on, and keep its data on the declared volume; the README's
//! `docker build` / `docker run` commands and `radiance serve` lines must agree.
//!
//! Docker is not available on CI, so this reads the files (hadolint lints the
//! Dockerfile's style in `.ci/run`). The flags and environment variables come
//! from the built binary's `--help` (clap), not from a list kept here. The
//! `mutation_*` tests break one fact at a time and check that it is reported.

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;
use std::process::Command;
use std::sync::OnceLock;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn read(name: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{name}")).unwrap_or_else(|e| panic!("reading {name}: {e}"))
}

// ---------------------------------------------------------------------------
// What the binary says about itself.

/// One subcommand's `--help`: its long flags, the environment variables it
/// reads (`[env: NAME]`) and the defaults it shows (`[default: V]`).
#[derive(Debug, Default)]
struct Help {
    flags: BTreeSet<String>,
    envs: BTreeSet<String>,
    defaults: BTreeMap<String, String>,
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
fn subcommands() -> &'static BTreeSet<String> {
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
fn help_of(sub: &str) -> Option<&'static Help> {
    static H: OnceLock<std::sync::Mutex<BTreeMap<String, &'static Help>>> = OnceLock::new();
    if !subcommands().contains(sub) {
        return None;
    }
    let mut m = H.get_or_init(Default::default).lock().unwrap();
    Some(*m.entry(sub.to_string()).or_insert_with(|| Box::leak(Box::new(parse_help(&run_help(&[sub, "--help"]))))))
}

// ---------------------------------------------------------------------------
// A small Dockerfile reader: instructions of each stage, with continuation
// lines joined and comments dropped (enough for this file; no heredocs).

#[derive(Debug, Clone)]
struct Instr {
    cmd: String,
    args: String,
}

#[derive(Debug, Default)]
struct Stage {
    image: String,
    name: Option<String>,
    instrs: Vec<Instr>,
}

impl Stage {
    fn all(&self, cmd: &str) -> impl Iterator<Item = &Instr> {
        self.instrs.iter().filter(move |i| i.cmd == cmd)
    }
    /// The last instruction `cmd` (the one Docker uses for ENTRYPOINT, CMD, USER...).
    fn last(&self, cmd: &str) -> Option<&Instr> {
        self.all(cmd).last()
    }
}

fn parse_dockerfile(text: &str) -> Vec<Stage> {
    let mut logical = Vec::new();
    let mut cur = String::new();
    for line in text.lines() {
        let t = line.trim();
        if t.starts_with('#') || (t.is_empty() && cur.is_empty()) {
            continue; // comments (also inside continued instructions) and blank lines
        }
        if let Some(body) = t.strip_suffix('\\') {
            cur.push_str(body);
            cur.push(' ');
        } else {
            cur.push_str(t);
            logical.push(std::mem::take(&mut cur));
        }
    }
    let mut stages: Vec<Stage> = Vec::new();
    for l in logical {
        let (cmd, args) = l.split_once(char::is_whitespace).unwrap_or((&l, ""));
        let (cmd, args) = (cmd.to_uppercase(), args.trim().to_string());
        if cmd == "FROM" {
            let w: Vec<&str> = args.split_whitespace().filter(|w| !w.starts_with("--")).collect();
            let name = (w.len() == 3 && w[1].eq_ignore_ascii_case("as")).then(|| w[2].to_string());
            stages.push(Stage { image: w.first().unwrap_or(&"").to_string(), name, instrs: Vec::new() });
        } else if let Some(s) = stages.last_mut() {
            s.instrs.push(Instr { cmd, args });
        }
    }
    stages
}

/// Splits like a POSIX shell would (quotes and backslashes; no expansions).
fn shell_words(s: &str) -> Vec<String> {
    let (mut out, mut w, mut in_word) = (Vec::new(), String::new(), false);
    let mut chars = s.chars();
    let mut quote: Option<char> = None;
    while let Some(c) = chars.next() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some('"'), '\\') => w.extend(chars.next()),
            (Some(_), c) => w.push(c),
            (None, '\'' | '"') => {
                quote = Some(c);
                in_word = true;
            }
            (None, '\\') => {
                w.extend(chars.next());
                in_word = true;
            }
            (None, c) if c.is_whitespace() => {
                if in_word {
                    out.push(std::mem::take(&mut w));
                    in_word = false;
                }
            }
            (None, c) => {
                w.push(c);
                in_word = true;
            }
        }
    }
    if in_word {
        out.push(w);
    }
    out
}

/// Exec form (`["a", "b"]`) or shell form (`a b`, run by `/bin/sh -c`).
fn command_words(args: &str) -> Vec<String> {
    if args.trim_start().starts_with('[') {
        serde_json::from_str(args).unwrap_or_else(|e| vec![format!("<invalid JSON array {args:?}: {e}>")])
    } else {
        vec!["/bin/sh".into(), "-c".into(), args.to_string()]
    }
}

/// `ENV K=V K2="V 2"` (or the legacy `ENV K V`).
fn env_pairs(args: &str) -> Vec<(String, String)> {
    let words = shell_words(args);
    if words.first().is_some_and(|w| !w.contains('=')) {
        return vec![(words[0].clone(), words[1..].join(" "))];
    }
    words.iter().filter_map(|w| w.split_once('=')).map(|(k, v)| (k.to_string(), v.to_string())).collect()
}

/// `(host, port, path)` of an `http://` URL.
fn http_url(url: &str) -> Option<(String, u16, String)> {
    let rest = url.strip_prefix("http://")?;
    let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    let (host, port) = authority.rsplit_once(':').unwrap_or((authority, "80"));
    let path = path.split(['?', '#']).next().unwrap_or("");
    Some((host.to_string(), port.parse().ok()?, if path.is_empty() { "/".into() } else { path.into() }))
}

fn version_of(s: &str) -> Option<(u32, u32)> {
    let mut it = s.split('.').map(|p| p.chars().take_while(char::is_ascii_digit).collect::<String>());
    Some((it.next()?.parse().ok()?, it.next()?.parse().ok()?))
}

// ---------------------------------------------------------------------------
// The README's shell commands.

/// Shell snippets of the README: lines of code blocks (fenced or indented, with
/// `\` continuations joined) and inline `code` spans of prose, each split at
/// `&&`, `;` and `|`.
fn readme_commands(readme: &str) -> Vec<String> {
    let mut snippets = Vec::new();
    let (mut fenced, mut cur) = (false, String::new());
    for line in readme.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced || line.starts_with("    ") {
            let t = line.trim();
            if let Some(body) = t.strip_suffix('\\') {
                cur.push_str(body);
                cur.push(' ');
            } else {
                cur.push_str(t);
                snippets.push(std::mem::take(&mut cur));
            }
        } else {
            snippets.extend(line.split('`').skip(1).step_by(2).map(str::to_string));
        }
    }
    snippets
        .iter()
        .flat_map(|s| s.split("&&").flat_map(|s| s.split([';', '|'])))
        .map(|s| s.trim().to_string())
        .collect()
}

/// A `docker run`: options, image, arguments for the entrypoint.
#[derive(Debug, Default)]
struct DockerRun {
    publish: Vec<String>,
    volumes: Vec<String>,
    env: Vec<String>,
    image: String,
    args: Vec<String>,
}

fn docker_run(words: &[String]) -> DockerRun {
    const WITH_VALUE: [&str; 16] = [
        "-p",
        "--publish",
        "-v",
        "--volume",
        "-e",
        "--env",
        "--name",
        "--mount",
        "-u",
        "--user",
        "--network",
        "--cpus",
        "-m",
        "--memory",
        "--env-file",
        "--entrypoint",
    ];
    let mut r = DockerRun::default();
    let mut it = words.iter();
    while let Some(w) = it.next() {
        let (opt, inline) = match w.split_once('=') {
            Some((o, v)) if o.starts_with("--") => (o, Some(v.to_string())),
            _ => (w.as_str(), None),
        };
        if !opt.starts_with('-') {
            r.image = w.clone();
            r.args = it.cloned().collect();
            break;
        }
        let value = if WITH_VALUE.contains(&opt) { inline.or_else(|| it.next().cloned()) } else { None };
        let value = value.unwrap_or_default();
        match opt {
            "-p" | "--publish" => r.publish.push(value),
            "-v" | "--volume" => r.volumes.push(value),
            "-e" | "--env" => r.env.push(value),
            _ => {}
        }
    }
    r
}

/// Long flags written after `radiance serve` (or `cargo run ... -- serve`) in
/// the README, with the value shown in `[--flag VALUE]` brackets if any.
fn readme_serve_flags(readme: &str, sub: &str) -> Vec<(String, Option<String>)> {
    let mut texts = Vec::new();
    let mut in_usage = false;
    let (mut fenced, lines) = (false, readme.lines());
    for line in lines {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        let code = fenced || line.starts_with("    ");
        let spans: Vec<&str> = if code { vec![line] } else { line.split('`').skip(1).step_by(2).collect() };
        let mut found = false;
        for span in spans {
            for marker in [format!("radiance {sub}"), format!("-- {sub}")] {
                if let Some(i) = span.find(&marker) {
                    texts.push(span[i + marker.len()..].to_string());
                    found = true;
                }
            }
        }
        if found {
            in_usage = code;
        } else if in_usage && code && line.trim_start().starts_with('[') {
            texts.push(line.to_string()); // continuation of a usage line
        } else {
            in_usage = false;
        }
    }
    let mut out = Vec::new();
    for t in texts {
        let words: Vec<&str> = t.split_whitespace().collect();
        for (i, w) in words.iter().enumerate() {
            let bracketed = w.starts_with("[--");
            let flag = w.trim_start_matches('[').trim_end_matches([']', ',', ')', '`', '.']);
            if !flag.starts_with("--") || flag.len() < 3 {
                continue;
            }
            let value = (bracketed && !w.ends_with(']'))
                .then(|| words.get(i + 1).filter(|v| v.ends_with(']')).map(|v| v.trim_end_matches(']').to_string()))
                .flatten();
            out.push((flag.split('=').next().unwrap().to_string(), value));
        }
    }
    out
}

// ---------------------------------------------------------------------------
// The checks: every disagreement as one message.

struct Inputs {
    dockerfile: String,
    readme: String,
    dockerignore: String,
    openapi: String,
}

impl Inputs {
    fn real() -> Inputs {
        Inputs {
            dockerfile: read("Dockerfile"),
            readme: read("README.md"),
            dockerignore: std::fs::read_to_string(format!("{ROOT}/.dockerignore")).unwrap_or_default(),
            openapi: read("openapi.yaml"),
        }
    }
}

fn problems(inp: &Inputs) -> Vec<String> {
    let mut p = Vec::new();
    let stages = parse_dockerfile(&inp.dockerfile);
    let Some(run) = stages.last() else {
        return vec!["the Dockerfile has no FROM".into()];
    };
    let bin = "radiance"; // the binary CARGO_BIN_EXE_radiance names

    // Build: `cargo build --release --locked --bin radiance` in a named stage,
    // and the runtime stage copies exactly that artifact.
    let build = stages.iter().find(|s| s.all("RUN").any(|r| r.args.contains("cargo build")));
    let mut installed: Option<String> = None;
    match build {
        None => p.push("no stage runs `cargo build`".into()),
        Some(b) => {
            let cargo = b.all("RUN").find(|r| r.args.contains("cargo build")).unwrap();
            let words = shell_words(&cargo.args);
            for need in ["--release", "--locked"] {
                if !words.iter().any(|w| w == need) {
                    p.push(format!("the builder's `cargo build` lacks {need}: {}", cargo.args));
                }
            }
            let bin_arg = words.iter().position(|w| w == "--bin").and_then(|i| words.get(i + 1));
            if bin_arg.is_some_and(|b| b != bin) {
                p.push(format!("the builder builds `--bin {}`, the binary is `{bin}`", bin_arg.unwrap()));
            }
            let workdir = b.last("WORKDIR").map(|w| w.args.trim_end_matches('/').to_string()).unwrap_or_default();
            let artifact = format!("{workdir}/target/release/{bin}");
            let copied = b.all("COPY").flat_map(|c| shell_words(&c.args)).collect::<Vec<_>>();
            for input in ["Cargo.toml", "Cargo.lock", "src"] {
                if !copied.iter().any(|w| w == input) {
                    p.push(format!("the builder does not COPY {input}"));
                }
            }
            // Image tag `rust:1.95-...` against the README's minimum Rust.
            let min = (inp.readme.split("Rust ").skip(1))
                .find(|s| s.starts_with(|c: char| c.is_ascii_digit()) && s.contains(" or newer"))
                .and_then(version_of);
            let tag = b.image.split_once(':').map(|(_, t)| t).and_then(version_of);
            match (min, tag) {
                (Some(min), Some(tag)) if tag < min => {
                    p.push(format!("the builder image {} is older than the README's minimum Rust {min:?}", b.image))
                }
                (None, _) => p.push("the README does not state a minimum Rust (`Rust X.Y or newer`)".into()),
                (_, None) => p.push(format!("cannot read a Rust version from the builder image {}", b.image)),
                _ => {}
            }
            let from = b.name.clone().unwrap_or_default();
            let copy = run.all("COPY").find(|c| c.args.contains(&format!("--from={from} ")) && !from.is_empty());
            match copy.map(|c| shell_words(&c.args)) {
                None => p.push(format!("the runtime stage does not COPY --from={from}")),
                Some(w) if w.len() != 3 || w[1] != artifact => {
                    p.push(format!("the runtime stage copies {:?}, the build produces {artifact}", &w[1..]))
                }
                Some(w) => installed = Some(w[2].clone()),
            }
        }
    }

    // ENTRYPOINT + CMD: the copied binary, a real subcommand, real flags.
    let entry = run.last("ENTRYPOINT").map(|i| command_words(&i.args)).unwrap_or_default();
    let cmd = run.last("CMD").map(|i| command_words(&i.args)).unwrap_or_default();
    let argv: Vec<String> = entry.iter().chain(&cmd).cloned().collect();
    let mut help: Option<&Help> = None;
    if argv.is_empty() {
        p.push("no ENTRYPOINT or CMD".into());
    } else {
        let program_ok = match &installed {
            Some(dest) if argv[0].starts_with('/') => argv[0] == *dest,
            Some(dest) => {
                let (dir, file) = dest.rsplit_once('/').unwrap_or(("", dest));
                argv[0] == file && ["/usr/local/bin", "/usr/bin", "/bin"].contains(&dir)
            }
            None => true, // already reported
        };
        if !program_ok {
            p.push(format!("the entrypoint runs {:?}, the image installs {installed:?} (on PATH?)", argv[0]));
        }
        match argv.get(1).map(String::as_str) {
            Some(sub) if help_of(sub).is_some() => {
                help = help_of(sub);
                if sub != "serve" {
                    p.push(format!("the image runs `radiance {sub}`, a service image must run `radiance serve`"));
                }
            }
            other => p.push(format!("`radiance {other:?}` is not a subcommand of {:?}", subcommands())),
        }
        if let Some(h) = help {
            for a in argv[2..].iter().filter(|a| a.starts_with("--")) {
                let flag = a.split('=').next().unwrap();
                if !h.flags.contains(flag) {
                    p.push(format!("ENTRYPOINT/CMD passes {flag}, which `radiance {}` does not take", argv[1]));
                }
            }
        }
    }
    let Some(help) = help else {
        return p; // the rest compares against the subcommand's flags
    };

    // ENV: only variables the subcommand reads.
    let env: BTreeMap<String, String> = run.all("ENV").flat_map(|e| env_pairs(&e.args)).collect();
    for k in env.keys().filter(|k| k.starts_with("RADIANCE_")) {
        if !help.envs.contains(k) {
            p.push(format!("ENV {k} is not read by `radiance serve` (it reads {:?})", help.envs));
        }
    }

    // Port: RADIANCE_ADDR on all interfaces, EXPOSEd, health-checked.
    let addr: Option<SocketAddr> = match env.get("RADIANCE_ADDR") {
        None => {
            p.push("no ENV RADIANCE_ADDR: the service would listen on 127.0.0.1 inside the container".into());
            None
        }
        Some(a) => match a.parse::<SocketAddr>() {
            Err(e) => {
                p.push(format!("RADIANCE_ADDR={a} is not an address: {e}"));
                None
            }
            Ok(s) => {
                if !s.ip().is_unspecified() {
                    p.push(format!("RADIANCE_ADDR={a} is not reachable from outside the container (use 0.0.0.0)"));
                }
                Some(s)
            }
        },
    };
    let exposed: Vec<String> = run.all("EXPOSE").flat_map(|e| shell_words(&e.args)).collect();
    let port = addr.map(|a| a.port());
    if let Some(port) = port
        && exposed.iter().map(|e| e.trim_end_matches("/tcp")).collect::<Vec<_>>() != [port.to_string()]
    {
        p.push(format!("EXPOSE {exposed:?}, but the service listens on port {port}"));
    }
    match run.last("HEALTHCHECK") {
        None => p.push("no HEALTHCHECK".into()),
        Some(h) => {
            let words = shell_words(&h.args);
            let at = words.iter().position(|w| w.eq_ignore_ascii_case("CMD"));
            let probe = at.map(|i| {
                let rest = h.args.split_once(words[i].as_str()).map_or("", |(_, r)| r).trim().to_string();
                command_words(&rest)
            });
            match probe {
                None => p.push(format!("HEALTHCHECK has no CMD: {}", h.args)),
                Some(probe) => {
                    let words: Vec<String> = probe.iter().flat_map(|w| shell_words(w)).collect();
                    match words.iter().find_map(|w| http_url(w)) {
                        None => p.push(format!("the HEALTHCHECK requests no http:// URL: {probe:?}")),
                        Some((host, hport, path)) => {
                            if Some(hport) != port {
                                p.push(format!("the HEALTHCHECK polls port {hport}, the service listens on {port:?}"));
                            }
                            if path != "/healthz" {
                                p.push(format!("the HEALTHCHECK polls {path}, not /healthz"));
                            }
                            if !inp.openapi.contains(&format!("\n  {path}:")) {
                                p.push(format!("the HEALTHCHECK polls {path}, which openapi.yaml does not list"));
                            }
                            if !["127.0.0.1", "localhost", "[::1]"].contains(&host.as_str()) {
                                p.push(format!("the HEALTHCHECK polls host {host}, not the container itself"));
                            }
                        }
                    }
                    // The probe program must exist in the runtime image.
                    let prog = probe[0].rsplit('/').next().unwrap_or_default().to_string();
                    let runs: String = run.all("RUN").map(|r| format!(" {} ", r.args)).collect();
                    if probe[0] != "/bin/sh"
                        && !runs.contains(&format!(" {prog} "))
                        && !runs.contains(&format!(" {prog}="))
                    {
                        p.push(format!("the HEALTHCHECK runs {prog}, which the runtime stage does not install"));
                    }
                }
            }
        }
    }

    // Data: RADIANCE_DATA_DIR is the (only) volume.
    let volumes: Vec<String> = run
        .all("VOLUME")
        .flat_map(|v| if v.args.starts_with('[') { command_words(&v.args) } else { shell_words(&v.args) })
        .map(|v| v.trim_end_matches('/').to_string())
        .collect();
    let data_dir = env.get("RADIANCE_DATA_DIR").map(|d| d.trim_end_matches('/').to_string());
    match &data_dir {
        None => p.push("no ENV RADIANCE_DATA_DIR: data would go to ./radiance-data, off the volume".into()),
        Some(d) if volumes != [d.clone()] => p.push(format!("VOLUME {volumes:?}, but RADIANCE_DATA_DIR={d}")),
        _ => {}
    }

    // Not root.
    match run.last("USER").map(|u| u.args.split(':').next().unwrap_or("").to_string()) {
        None => p.push("no USER: the service would run as root".into()),
        Some(u) if u == "root" || u == "0" => p.push("USER is root".into()),
        Some(u) if u.parse::<u32>().is_err() => p.push(format!("USER {u} is not numeric (hadolint DL3066)")),
        _ => {}
    }

    // .dockerignore must not hide the build's inputs.
    for line in inp.dockerignore.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let pat = line.trim_start_matches('/').trim_end_matches('/');
        if ["src", "Cargo.toml", "Cargo.lock", "*", "**"].contains(&pat) {
            p.push(format!(".dockerignore excludes {line}, which the build needs"));
        }
    }

    // README: `docker build -t IMAGE .` and `docker run` with the same image,
    // the exposed port, the volume, real variables and real flags.
    let cmds = readme_commands(&inp.readme);
    let mut tags = BTreeSet::new();
    let (mut builds, mut runs) = (0, Vec::new());
    for c in &cmds {
        let w = shell_words(c);
        if w.len() < 2 || w[0] != "docker" {
            continue;
        }
        if w[1] == "build" {
            builds += 1;
            match w.iter().position(|x| x == "-t" || x == "--tag").and_then(|i| w.get(i + 1)) {
                None => p.push(format!("README: `{c}` tags no image")),
                Some(t) => {
                    tags.insert(t.clone());
                }
            }
            if w.last().map(String::as_str) != Some(".") {
                p.push(format!("README: `{c}` does not build the repository root"));
            }
        } else if w[1] == "run" {
            runs.push((c.clone(), docker_run(&w[2..])));
        }
    }
    if builds == 0 || runs.is_empty() {
        p.push("README: no `docker build -t IMAGE .` and `docker run ... IMAGE` commands".into());
    }
    if tags.len() > 1 {
        p.push(format!("README: docker build tags disagree: {tags:?}"));
    }
    if !runs.iter().any(|(_, r)| !r.publish.is_empty() && !r.volumes.is_empty()) {
        p.push("README: no `docker run` publishes the port and mounts the volume".into());
    }
    for (c, r) in &runs {
        if !tags.contains(&r.image) {
            p.push(format!("README: `{c}` runs image {:?}, the README builds {tags:?}", r.image));
        }
        for pb in &r.publish {
            let container = pb.trim_end_matches("/tcp").rsplit(':').next().unwrap_or_default();
            if Some(container.to_string()) != port.map(|p| p.to_string()) {
                p.push(format!("README: `{c}` publishes container port {container}, the image exposes {exposed:?}"));
            }
        }
        for v in &r.volumes {
            let dst = v.split(':').nth(1).unwrap_or_default().trim_end_matches('/');
            if volumes.len() != 1 || dst != volumes[0] {
                p.push(format!("README: `{c}` mounts {dst}, the image's data volume is {volumes:?}"));
            }
        }
        for e in &r.env {
            let k = e.split('=').next().unwrap_or_default();
            if k.starts_with("RADIANCE_") && !help.envs.contains(k) {
                p.push(format!("README: `{c}` sets {k}, which `radiance serve` does not read"));
            }
        }
        for a in r.args.iter().filter(|a| a.starts_with("--")) {
            let flag = a.split('=').next().unwrap();
            if !help.flags.contains(flag) {
                p.push(format!("README: `{c}` passes {flag} to `radiance serve`, which has no such flag"));
            }
        }
    }

    // README: `radiance serve` flags and defaults, and every RADIANCE_* it names.
    let serve_flags = readme_serve_flags(&inp.readme, "serve");
    if serve_flags.is_empty() {
        p.push("README: found no `radiance serve --flag` to check".into());
    }
    for (flag, value) in serve_flags {
        if !help.flags.contains(&flag) {
            p.push(format!("README: `radiance serve {flag}`: no such flag in `radiance serve --help`"));
        } else if let (Some(v), Some(d)) = (value, help.defaults.get(&flag))
            && v != *d
            && !v.chars().all(|c| c.is_ascii_uppercase() || c == '_')
        {
            p.push(format!("README: `[{flag} {v}]`, but the default is {d}"));
        }
    }
    for w in inp.readme.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
        if w.starts_with("RADIANCE_") && w.len() > "RADIANCE_".len() && !help.envs.contains(w) {
            p.push(format!("README names {w}, which `radiance serve` does not read"));
        }
    }
    p
}

#[test]
fn dockerfile_and_readme_match_the_binary() {
    let p = problems(&Inputs::real());
    assert!(p.is_empty(), "{} problem(s):\n  {}", p.len(), p.join("\n  "));
}

#[test]
fn help_is_parsed() {
    // Guards the parser itself: if clap's help format changes, say so here.
    let h = help_of("serve").expect("serve is a subcommand");
    for f in ["--addr", "--data-dir", "--api-key", "--threads", "--help"] {
        assert!(h.flags.contains(f), "{f} in {:?}", h.flags);
    }
    for e in ["RADIANCE_ADDR", "RADIANCE_DATA_DIR", "RADIANCE_API_KEY"] {
        assert!(h.envs.contains(e), "{e} in {:?}", h.envs);
    }
    assert_eq!(h.defaults.get("--addr").map(String::as_str), Some("127.0.0.1:8080"), "{:?}", h.defaults);
    assert!(subcommands().contains("train") && !subcommands().contains("help"), "{:?}", subcommands());
}

// ---------------------------------------------------------------------------
// Each check can fail: break one fact in a copy of the real files.

/// Problems after replacing every `from` by `to` in the file `which` (which must contain `from`).
fn mutated(which: &str, from: &str, to: &str) -> Vec<String> {
    let mut inp = Inputs::real();
    let text = match which {
        "Dockerfile" => &mut inp.dockerfile,
        "README.md" => &mut inp.readme,
        ".dockerignore" => &mut inp.dockerignore,
        _ => unreachable!(),
    };
    assert!(text.contains(from), "{which} no longer contains {from:?}: update this mutation");
    *text = text.replace(from, to);
    problems(&inp)
}

fn assert_caught(which: &str, from: &str, to: &str, expect: &str) {
    let p = mutated(which, from, to);
    assert!(p.iter().any(|m| m.contains(expect)), "{which}: {from:?} -> {to:?} should report {expect:?}, got {p:#?}");
}

#[test]
fn mutation_build_steps() {
    assert_caught("Dockerfile", "--bin radiance", "--bin radiant", "the builder builds `--bin radiant`");
    assert_caught("Dockerfile", "--locked", "", "lacks --locked");
    assert_caught("Dockerfile", "cargo build", "cargo check", "no stage runs `cargo build`");
    assert_caught("Dockerfile", "/target/release/radiance", "/target/debug/radiance", "the build produces");
    assert_caught("Dockerfile", "--from=build", "--from=builder", "does not COPY --from=build");
    assert_caught("Dockerfile", "COPY src ./src", "COPY srcs ./src", "does not COPY src");
    assert_caught("Dockerfile", "FROM rust:1.", "FROM rust:0.", "older than the README's minimum Rust");
    assert_caught("README.md", "Rust 1.88 or newer", "Rust 1.88", "does not state a minimum Rust");
    assert_caught(".dockerignore", "/target", "/src", ".dockerignore excludes /src");
}

#[test]
fn mutation_entrypoint() {
    let entry = r#"["radiance", "serve"]"#;
    assert_caught("Dockerfile", entry, r#"["radiance", "server"]"#, "is not a subcommand");
    assert_caught("Dockerfile", entry, r#"["radiance", "train"]"#, "must run `radiance serve`");
    assert_caught("Dockerfile", entry, r#"["radiant", "serve"]"#, "the entrypoint runs");
    assert_caught("Dockerfile", entry, r#"["radiance", "serve", "--port", "8080"]"#, "passes --port");
    assert_caught("Dockerfile", "ENTRYPOINT [", "CMD [\"--max-jobs\", \"2\"]\nENTRYPOINT [", "passes --max-jobs");
    assert_caught("Dockerfile", &format!("ENTRYPOINT {entry}"), "", "no ENTRYPOINT or CMD");
}

#[test]
fn mutation_env() {
    assert_caught("Dockerfile", "RADIANCE_DATA_DIR=/data", "RADIANCE_DATA=/data", "ENV RADIANCE_DATA is not read");
    assert_caught("Dockerfile", "RADIANCE_DATA_DIR=/data", "", "no ENV RADIANCE_DATA_DIR");
    assert_caught("Dockerfile", "RADIANCE_ADDR=0.0.0.0:8080 ", "", "no ENV RADIANCE_ADDR");
    assert_caught("Dockerfile", "RADIANCE_ADDR=0.0.0.0:8080", "RADIANCE_ADDR=127.0.0.1:8080", "use 0.0.0.0");
    assert_caught("Dockerfile", "RADIANCE_ADDR=0.0.0.0:8080", "RADIANCE_ADDR=0.0.0.0", "not an address");
}

#[test]
fn mutation_port_and_healthcheck() {
    let url = "http://127.0.0.1:8080/healthz";
    assert_caught("Dockerfile", "EXPOSE 8080", "EXPOSE 8000", "but the service listens on port 8080");
    assert_caught("Dockerfile", "EXPOSE 8080", "EXPOSE 8080 9090", "but the service listens on port 8080");
    assert_caught("Dockerfile", "RADIANCE_ADDR=0.0.0.0:8080", "RADIANCE_ADDR=0.0.0.0:9090", "listens on port 9090");
    assert_caught("Dockerfile", url, "http://127.0.0.1:8081/healthz", "polls port 8081");
    assert_caught("Dockerfile", url, "http://127.0.0.1:8080/health", "not /healthz");
    assert_caught("Dockerfile", url, "http://127.0.0.1:8080/health", "openapi.yaml does not list");
    assert_caught("Dockerfile", url, "http://example.com:8080/healthz", "not the container itself");
    assert_caught("Dockerfile", url, "127.0.0.1:8080/healthz", "requests no http:// URL");
    assert_caught("Dockerfile", " CMD [", " [", "HEALTHCHECK has no CMD");
    assert_caught("Dockerfile", "curl=7.*", "wget", "does not install");
    assert_caught("Dockerfile", "HEALTHCHECK", "# HEALTHCHECK", "no HEALTHCHECK");
}

#[test]
fn mutation_volume_and_user() {
    assert_caught(
        "Dockerfile",
        r#"VOLUME ["/data"]"#,
        r#"VOLUME ["/var/lib/radiance"]"#,
        "but RADIANCE_DATA_DIR=/data",
    );
    assert_caught("Dockerfile", r#"VOLUME ["/data"]"#, "", "but RADIANCE_DATA_DIR=/data");
    assert_caught("Dockerfile", "USER 10001:10001", "USER root", "USER is root");
    assert_caught("Dockerfile", "USER 10001:10001", "USER radiance", "not numeric");
    assert_caught("Dockerfile", "USER 10001:10001", "", "no USER");
}

#[test]
fn mutation_readme_docker_commands() {
    let run = "-p 8080:8080 -v radiance-data:/data radiance";
    assert_caught("README.md", run, "-p 8080:80 -v radiance-data:/data radiance", "container port 80,");
    assert_caught("README.md", run, "-p 8080:8080 -v radiance-data:/srv radiance", "mounts /srv");
    assert_caught("README.md", "-p 8080:8080 ", "", "no `docker run` publishes the port");
    assert_caught(
        "README.md",
        "docker build -t radiance .",
        "docker build -t radiance-img .",
        "runs image \"radiance\"",
    );
    assert_caught("README.md", "docker build -t radiance .", "docker build .", "tags no image");
    assert_caught("README.md", "docker build -t radiance .", "docker build -t radiance docker/", "repository root");
    assert_caught(
        "README.md",
        "=2 radiance --threads",
        "=2 radiance:latest --threads",
        "runs image \"radiance:latest\"",
    );
    assert_caught("README.md", "docker run", "podman run", "no `docker build -t IMAGE .` and `docker run");
    assert_caught(
        "README.md",
        "RADIANCE_MAX_CONCURRENT_JOBS=2",
        "RADIANCE_CONCURRENT_JOBS=2",
        "sets RADIANCE_CONCURRENT_JOBS",
    );
    assert_caught("README.md", "radiance --threads 8", "radiance --workers 8", "passes --workers");
}

#[test]
fn mutation_readme_serve_flags() {
    assert_caught("README.md", "[--max-upload-mb 512]", "[--max-upload-mib 512]", "--max-upload-mib`: no such flag");
    assert_caught("README.md", "[--max-queued-jobs 100]", "[--max-queued-jobs 10]", "the default is 100");
    assert_caught("README.md", "`RADIANCE_API_KEY`", "`RADIANCE_KEY`", "README names RADIANCE_KEY");
    assert_caught("README.md", "serve --data-dir ./radiance-data &", "serve --datadir ./radiance-data &", "--datadir");
}
