//! Each check can fail: break one fact in a copy of the real files and
//! check that it is reported.

use crate::checks::{Inputs, problems};

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
    // The web app is compiled in: a build without it fails (issue 34).
    assert_caught("Dockerfile", "COPY web ./web\n", "", "does not COPY web");
    assert_caught(".dockerignore", "/target", "/web", ".dockerignore excludes /web");
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
