//! The checks: every disagreement between the Dockerfile, the README, the
//! binary's `--help` and openapi.yaml as one message. Each part of the image
//! has its own check; they run in the order of the Dockerfile and take
//! what earlier ones found (the installed binary, the subcommand's help, the
//! port and the volume).

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;

use crate::help::{Help, help_of, subcommands};
use crate::parse::{Stage, command_words, env_pairs, http_url, parse_dockerfile, shell_words, version_of};
use crate::readme::{DockerRun, docker_run, readme_commands, readme_serve_flags};
use crate::{ROOT, read};

/// The binary `CARGO_BIN_EXE_radiance` names.
const BIN: &str = "radiance";

pub struct Inputs {
    pub dockerfile: String,
    pub readme: String,
    pub dockerignore: String,
    pub openapi: String,
}

impl Inputs {
    pub fn real() -> Inputs {
        Inputs {
            dockerfile: read("Dockerfile"),
            readme: read("README.md"),
            dockerignore: std::fs::read_to_string(format!("{ROOT}/.dockerignore")).unwrap_or_default(),
            openapi: read("openapi.yaml"),
        }
    }
}

/// What the runtime stage promises, which the README's commands must match.
struct Image {
    help: &'static Help,
    port: Option<u16>,
    exposed: Vec<String>,
    volumes: Vec<String>,
}

pub fn problems(inp: &Inputs) -> Vec<String> {
    let mut p = Vec::new();
    let stages = parse_dockerfile(&inp.dockerfile);
    let Some(run) = stages.last() else {
        return vec!["the Dockerfile has no FROM".into()];
    };
    let installed = check_build(&stages, run, &inp.readme, &mut p);
    let Some(help) = check_entrypoint(run, &installed, &mut p) else {
        return p; // the rest compares against the subcommand's flags
    };
    let env: BTreeMap<String, String> = run.all("ENV").flat_map(|e| env_pairs(&e.args)).collect();
    check_env(&env, help, &mut p);
    let port = listen_addr(&env, &mut p).map(|a| a.port());
    let exposed = check_exposed(run, port, &mut p);
    check_healthcheck(run, port, &inp.openapi, &mut p);
    let volumes = check_volume(run, &env, &mut p);
    check_user(run, &mut p);
    check_dockerignore(&inp.dockerignore, &mut p);
    check_readme_docker(&inp.readme, &Image { help, port, exposed, volumes }, &mut p);
    check_readme_serve(&inp.readme, help, &mut p);
    p
}

/// Build: `cargo build --release --locked --bin radiance` in a named stage,
/// and the runtime stage copies exactly that artifact. Returns where the
/// runtime stage installs it.
fn check_build(stages: &[Stage], run: &Stage, readme: &str, p: &mut Vec<String>) -> Option<String> {
    let Some(b) = stages.iter().find(|s| s.all("RUN").any(|r| r.args.contains("cargo build"))) else {
        p.push("no stage runs `cargo build`".into());
        return None;
    };
    let cargo = b.all("RUN").find(|r| r.args.contains("cargo build")).unwrap();
    let words = shell_words(&cargo.args);
    for need in ["--release", "--locked"] {
        if !words.iter().any(|w| w == need) {
            p.push(format!("the builder's `cargo build` lacks {need}: {}", cargo.args));
        }
    }
    let bin_arg = words.iter().position(|w| w == "--bin").and_then(|i| words.get(i + 1));
    if bin_arg.is_some_and(|b| b != BIN) {
        p.push(format!("the builder builds `--bin {}`, the binary is `{BIN}`", bin_arg.unwrap()));
    }
    let workdir = b.last("WORKDIR").map(|w| w.args.trim_end_matches('/').to_string()).unwrap_or_default();
    let artifact = format!("{workdir}/target/release/{BIN}");
    // What the builder's COPYs take from the context: every word but the last (the destination) and flags.
    let copied = (b.all("COPY").map(|c| shell_words(&c.args)))
        .flat_map(|w| w[..w.len().saturating_sub(1)].to_vec())
        .filter(|w| !w.starts_with("--"))
        .map(|w| w.trim_start_matches("./").trim_end_matches('/').to_string())
        .collect::<Vec<_>>();
    for input in build_inputs() {
        if !copied.contains(&input) {
            p.push(format!("the builder does not COPY {input}"));
        }
    }
    check_rust_version(b, readme, p);
    let from = b.name.clone().unwrap_or_default();
    let copy = run.all("COPY").find(|c| c.args.contains(&format!("--from={from} ")) && !from.is_empty());
    match copy.map(|c| shell_words(&c.args)) {
        None => p.push(format!("the runtime stage does not COPY --from={from}")),
        Some(w) if w.len() != 3 || w[1] != artifact => {
            p.push(format!("the runtime stage copies {:?}, the build produces {artifact}", &w[1..]))
        }
        Some(w) => return Some(w[2].clone()),
    }
    None
}

/// What `cargo build` reads: the manifest, the lock file, `src/`, and every
/// top-level folder a file under `src/` compiles in with `include_str!` or
/// `include_bytes!` (the web app, `web/`), found by reading the sources.
pub fn build_inputs() -> BTreeSet<String> {
    let mut inputs: BTreeSet<String> = ["Cargo.toml", "Cargo.lock", "src"].map(String::from).into();
    let root = std::path::Path::new(ROOT);
    let mut dirs = vec![root.join("src")];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("reading {}: {e}", dir.display())) {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap_or_default();
            let after = |m: &'static str| text.split(m).skip(1);
            for piece in after("include_str!(\"").chain(after("include_bytes!(\"")) {
                let Some(rel) = piece.split('"').next() else { continue };
                // Resolve `..` by hand: the file need not exist for the check to say where it points.
                let mut parts: Vec<String> = path
                    .parent()
                    .unwrap()
                    .strip_prefix(root)
                    .unwrap()
                    .iter()
                    .map(|c| c.to_string_lossy().into_owned())
                    .collect();
                for c in rel.split('/') {
                    match c {
                        ".." => {
                            parts.pop();
                        }
                        "." | "" => {}
                        c => parts.push(c.to_string()),
                    }
                }
                if parts.len() > 1 {
                    inputs.insert(parts[0].clone());
                }
            }
        }
    }
    inputs
}

/// Image tag `rust:1.95-...` against the README's minimum Rust.
fn check_rust_version(builder: &Stage, readme: &str, p: &mut Vec<String>) {
    let min = (readme.split("Rust ").skip(1))
        .find(|s| s.starts_with(|c: char| c.is_ascii_digit()) && s.contains(" or newer"))
        .and_then(version_of);
    let tag = builder.image.split_once(':').map(|(_, t)| t).and_then(version_of);
    match (min, tag) {
        (Some(min), Some(tag)) if tag < min => {
            p.push(format!("the builder image {} is older than the README's minimum Rust {min:?}", builder.image))
        }
        (None, _) => p.push("the README does not state a minimum Rust (`Rust X.Y or newer`)".into()),
        (_, None) => p.push(format!("cannot read a Rust version from the builder image {}", builder.image)),
        _ => {}
    }
}

/// ENTRYPOINT + CMD: the copied binary, a real subcommand, real flags.
/// Returns the help of the subcommand it runs.
fn check_entrypoint(run: &Stage, installed: &Option<String>, p: &mut Vec<String>) -> Option<&'static Help> {
    let entry = run.last("ENTRYPOINT").map(|i| command_words(&i.args)).unwrap_or_default();
    let cmd = run.last("CMD").map(|i| command_words(&i.args)).unwrap_or_default();
    let argv: Vec<String> = entry.iter().chain(&cmd).cloned().collect();
    if argv.is_empty() {
        p.push("no ENTRYPOINT or CMD".into());
        return None;
    }
    let program_ok = match installed {
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
    let mut help = None;
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
    help
}

/// ENV: only variables the subcommand reads.
fn check_env(env: &BTreeMap<String, String>, help: &Help, p: &mut Vec<String>) {
    for k in env.keys().filter(|k| k.starts_with("RADIANCE_")) {
        if !help.envs.contains(k) {
            p.push(format!("ENV {k} is not read by `radiance serve` (it reads {:?})", help.envs));
        }
    }
}

/// Port: RADIANCE_ADDR, on all interfaces.
fn listen_addr(env: &BTreeMap<String, String>, p: &mut Vec<String>) -> Option<SocketAddr> {
    let Some(a) = env.get("RADIANCE_ADDR") else {
        p.push("no ENV RADIANCE_ADDR: the service would listen on 127.0.0.1 inside the container".into());
        return None;
    };
    match a.parse::<SocketAddr>() {
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
    }
}

/// EXPOSE: the port the service listens on, alone. Returns what is exposed.
fn check_exposed(run: &Stage, port: Option<u16>, p: &mut Vec<String>) -> Vec<String> {
    let exposed: Vec<String> = run.all("EXPOSE").flat_map(|e| shell_words(&e.args)).collect();
    if let Some(port) = port
        && exposed.iter().map(|e| e.trim_end_matches("/tcp")).collect::<Vec<_>>() != [port.to_string()]
    {
        p.push(format!("EXPOSE {exposed:?}, but the service listens on port {port}"));
    }
    exposed
}

/// HEALTHCHECK: polls `/healthz` (listed in openapi.yaml) on the container
/// itself at the service's port, with a program the runtime stage installs.
fn check_healthcheck(run: &Stage, port: Option<u16>, openapi: &str, p: &mut Vec<String>) {
    let Some(h) = run.last("HEALTHCHECK") else {
        p.push("no HEALTHCHECK".into());
        return;
    };
    let words = shell_words(&h.args);
    let at = words.iter().position(|w| w.eq_ignore_ascii_case("CMD"));
    let probe = at.map(|i| {
        let rest = h.args.split_once(words[i].as_str()).map_or("", |(_, r)| r).trim().to_string();
        command_words(&rest)
    });
    let Some(probe) = probe else {
        p.push(format!("HEALTHCHECK has no CMD: {}", h.args));
        return;
    };
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
            if !openapi.contains(&format!("\n  {path}:")) {
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
    if probe[0] != "/bin/sh" && !runs.contains(&format!(" {prog} ")) && !runs.contains(&format!(" {prog}=")) {
        p.push(format!("the HEALTHCHECK runs {prog}, which the runtime stage does not install"));
    }
}

/// Data: RADIANCE_DATA_DIR is the (only) volume. Returns the volumes.
fn check_volume(run: &Stage, env: &BTreeMap<String, String>, p: &mut Vec<String>) -> Vec<String> {
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
    volumes
}

/// Not root.
fn check_user(run: &Stage, p: &mut Vec<String>) {
    match run.last("USER").map(|u| u.args.split(':').next().unwrap_or("").to_string()) {
        None => p.push("no USER: the service would run as root".into()),
        Some(u) if u == "root" || u == "0" => p.push("USER is root".into()),
        Some(u) if u.parse::<u32>().is_err() => p.push(format!("USER {u} is not numeric (hadolint DL3066)")),
        _ => {}
    }
}

/// .dockerignore must not hide the build's inputs.
fn check_dockerignore(dockerignore: &str, p: &mut Vec<String>) {
    for line in dockerignore.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let pat = line.trim_start_matches('/').trim_end_matches('/');
        if build_inputs().contains(pat) || ["*", "**"].contains(&pat) {
            p.push(format!(".dockerignore excludes {line}, which the build needs"));
        }
    }
}

/// README: `docker build -t IMAGE .` and `docker run` with the same image,
/// the exposed port, the volume, real variables and real flags.
fn check_readme_docker(readme: &str, image: &Image, p: &mut Vec<String>) {
    let (tags, runs) = readme_docker_commands(readme, p);
    if tags.len() > 1 {
        p.push(format!("README: docker build tags disagree: {tags:?}"));
    }
    if !runs.iter().any(|(_, r)| !r.publish.is_empty() && !r.volumes.is_empty()) {
        p.push("README: no `docker run` publishes the port and mounts the volume".into());
    }
    for (c, r) in &runs {
        check_docker_run(c, r, &tags, image, p);
    }
}

/// The README's `docker build` tags and `docker run` commands (each with
/// its text); reports builds that tag nothing or build elsewhere than the
/// repository root, and a README with no build or no run.
fn readme_docker_commands(readme: &str, p: &mut Vec<String>) -> (BTreeSet<String>, Vec<(String, DockerRun)>) {
    let mut tags = BTreeSet::new();
    let (mut builds, mut runs) = (0, Vec::new());
    for c in &readme_commands(readme) {
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
    (tags, runs)
}

/// One README `docker run` (`c`) against the image it should run.
fn check_docker_run(c: &str, r: &DockerRun, tags: &BTreeSet<String>, image: &Image, p: &mut Vec<String>) {
    let (port, exposed, volumes) = (image.port, &image.exposed, &image.volumes);
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
        if k.starts_with("RADIANCE_") && !image.help.envs.contains(k) {
            p.push(format!("README: `{c}` sets {k}, which `radiance serve` does not read"));
        }
    }
    for a in r.args.iter().filter(|a| a.starts_with("--")) {
        let flag = a.split('=').next().unwrap();
        if !image.help.flags.contains(flag) {
            p.push(format!("README: `{c}` passes {flag} to `radiance serve`, which has no such flag"));
        }
    }
}

/// README: `radiance serve` flags and defaults, and every RADIANCE_* it names.
fn check_readme_serve(readme: &str, help: &Help, p: &mut Vec<String>) {
    let serve_flags = readme_serve_flags(readme, "serve");
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
    for w in readme.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
        if w.starts_with("RADIANCE_") && w.len() > "RADIANCE_".len() && !help.envs.contains(w) {
            p.push(format!("README names {w}, which `radiance serve` does not read"));
        }
    }
}
