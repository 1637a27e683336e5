//! The README's shell commands.

/// Shell snippets of the README: lines of code blocks (fenced or indented, with
/// `\` continuations joined) and inline `code` spans of prose, each split at
/// `&&`, `;` and `|`.
pub fn readme_commands(readme: &str) -> Vec<String> {
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
pub struct DockerRun {
    pub publish: Vec<String>,
    pub volumes: Vec<String>,
    pub env: Vec<String>,
    pub image: String,
    pub args: Vec<String>,
}

pub fn docker_run(words: &[String]) -> DockerRun {
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
pub fn readme_serve_flags(readme: &str, sub: &str) -> Vec<(String, Option<String>)> {
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
