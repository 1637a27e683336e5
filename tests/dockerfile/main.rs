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
//!
//! Modules: `help` reads the binary's `--help`, `parse` the Dockerfile,
//! `readme` the README's commands; `checks` compares them, and `mutations`
//! shows that each check can fail.

mod checks;
mod compose;
mod help;
mod mutations;
mod parse;
mod readme;

use checks::{Inputs, problems};
use help::{help_of, subcommands};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn read(name: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{name}")).unwrap_or_else(|e| panic!("reading {name}: {e}"))
}

#[test]
fn dockerfile_and_readme_match_the_binary() {
    let p = problems(&Inputs::real());
    assert!(p.is_empty(), "{} problem(s):\n  {}", p.len(), p.join("\n  "));
}

#[test]
fn compose_file_matches_the_binary() {
    let serve = help_of("serve").expect("serve is a subcommand");
    let p = compose::problems(&read("compose.yaml"), serve);
    assert!(p.is_empty(), "{} problem(s):\n  {}", p.len(), p.join("\n  "));
}

#[test]
fn compose_checks_can_fail() {
    let serve = help_of("serve").expect("serve is a subcommand");
    let text = read("compose.yaml");
    for (from, to, expect) in [
        ("\"--role\", \"worker\"", "\"--role\", \"workers\"", "is not a role"),
        ("RADIANCE_OBJECT_STORE:", "RADIANCE_OBJECTS:", "does not read RADIANCE_OBJECTS"),
        ("@postgres:5432", "@db:5432", "does not name the PostgreSQL service"),
        ("http://garage:3900", "http://s3:3900", "does not name the S3 service"),
        ("AWS_ALLOW_HTTP: \"true\"", "AWS_ALLOW_HTTP: \"false\"", "needs AWS_ALLOW_HTTP=true"),
        ("replicas: 2", "replicas: 1", "1 worker(s)"),
        ("image: postgres:16", "image: mysql:8", "no PostgreSQL service"),
    ] {
        assert!(text.contains(from), "compose.yaml no longer has `{from}`: update this test");
        let p = compose::problems(&text.replacen(from, to, 1), serve);
        assert!(p.iter().any(|m| m.contains(expect)), "{from} -> {to}: expected `{expect}` in {p:?}");
    }
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

#[test]
fn build_inputs_are_read_from_the_sources() {
    // Guards the reader of include_str!/include_bytes!: src/api/web.rs compiles in web/.
    let inputs = checks::build_inputs();
    assert!(inputs.contains("web") && inputs.contains("src"), "{inputs:?}");
    assert!(!inputs.contains("tests") && !inputs.contains("target"), "{inputs:?}");
}
