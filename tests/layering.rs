//! The engine's folders depend on each other in one direction
//! (`docs/architecture.md`, "The engine"): this test reads every source file
//! under `src/engine/`, finds which engine folders its code uses, and fails
//! on a use that points up the layers (e.g. a model or a field using
//! `train/`), on a cycle between folders, and on a use of the service
//! outside the engine (`api`, `jobs`, ...). Test code (`#[cfg(test)]` items
//! and `*_tests.rs` files) may use anything and is not read.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// The engine's folders (and top-level files) from the bottom up: each may
/// use those on the lines before its own, never those after. Folders on one
/// line must not use each other.
const LAYERS: &[&[&str]] = &[
    // Base: random numbers, image metrics, the checkpoint container and atomic writes.
    &["rng", "metrics", "io"],
    // Vectors, rays, cameras, rigs and paths.
    &["geometry"],
    // Datasets on disk, the scene a dataset makes.
    &["dataset"],
    // Parameters, layers, encodings, Adam.
    &["nn"],
    // The packed samples every sampler writes, and the samplers.
    &["sampling"],
    // Training rays and what a batch or a ray gives.
    &["batch"],
    // Fields: densities and colours at points.
    &["fields"],
    // Volume rendering: compositing, the render loop, losses on rays.
    &["render"],
    // A model is a folder: a field, a sampler and its training pass.
    &["models"],
    // Views of a model: tiles of rays, the appearance a view takes.
    &["view"],
    // Transient occluders found in the training photos: what training and
    // the bake leave out.
    &["transient"],
    // Baking a field into splats: placing, carving, fitting.
    &["bake"],
    // Textured meshes from a model's views: fusing, extracting, texturing, writing.
    &["mesh"],
    // Training: the trainer, sessions, held-out estimates, checkpoints of a run.
    &["train"],
    // The front door: what the service uses of the engine.
    &["front"],
];

/// The service's folders that may reach the engine only through
/// `engine::front`.
const THROUGH_THE_FRONT_DOOR: &[&str] = &["api", "jobs", "worker", "cli"];

/// Modules of the crate the engine must never use.
const SERVICE: &[&str] = &["api", "jobs", "cli", "backend", "datadir", "records", "worker", "media", "poses"];

/// A use of another part: the file and line it is on.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct Use {
    from: String,
    to: String,
    file: String,
    line: usize,
}

/// The folder (or top-level module) a file under `src/engine/` belongs to.
fn part_of(rel: &str) -> String {
    let first = rel.split('/').next().unwrap_or(rel);
    first.trim_end_matches(".rs").to_string()
}

/// `text` without comments, string literals and `#[cfg(test)]` items (their
/// lines kept, blanked, so that line numbers stay right).
fn code_only(text: &str) -> String {
    // Blank comments and string contents first.
    let mut out = String::with_capacity(text.len());
    let b = text.as_bytes();
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        if c == b'/' && b.get(i + 1) == Some(&b'/') {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if c == b'/' && b.get(i + 1) == Some(&b'*') {
            i += 2;
            while i < b.len() && !(b[i] == b'*' && b.get(i + 1) == Some(&b'/')) {
                if b[i] == b'\n' {
                    out.push('\n');
                }
                i += 1;
            }
            i += 2;
        } else if c == b'"' {
            out.push('"');
            i += 1;
            while i < b.len() && b[i] != b'"' {
                if b[i] == b'\\' {
                    i += 1;
                }
                if i < b.len() && b[i] == b'\n' {
                    out.push('\n');
                }
                i += 1;
            }
            out.push('"');
            i += 1;
        } else if c == b'\'' && b.get(i + 2) == Some(&b'\'') {
            // A character literal such as '{' (lifetimes have no closing quote).
            out.push_str("' '");
            i += 3;
        } else {
            out.push(c as char);
            i += 1;
        }
    }
    // Then blank each `#[cfg(test)]` item: up to its `;`, or its braces' end.
    let lines: Vec<&str> = out.lines().collect();
    let mut keep: Vec<String> = Vec::with_capacity(lines.len());
    let mut n = 0;
    while n < lines.len() {
        if lines[n].trim() == "#[cfg(test)]" {
            let mut depth = 0i64;
            let mut opened = false;
            while n < lines.len() {
                let l = lines[n];
                keep.push(String::new());
                n += 1;
                for ch in l.chars() {
                    match ch {
                        '{' => {
                            depth += 1;
                            opened = true;
                        }
                        '}' => depth -= 1,
                        _ => {}
                    }
                }
                let attr = l.trim_start().starts_with("#[");
                if !attr && ((opened && depth <= 0) || (!opened && l.trim_end().ends_with(';'))) {
                    break;
                }
            }
        } else {
            keep.push(lines[n].to_string());
            n += 1;
        }
    }
    keep.join("\n")
}

fn ident_at(s: &str) -> &str {
    let end = s.find(|c: char| !(c.is_ascii_alphanumeric() || c == '_')).unwrap_or(s.len());
    &s[..end]
}

/// The first path segment of each item in a `{...}` group starting at `s`
/// (just after the `{`), nested groups skipped.
fn group_heads(s: &str) -> Vec<&str> {
    let mut heads = Vec::new();
    let mut depth = 0;
    let mut expect = true;
    let mut i = 0;
    let b = s.as_bytes();
    while i < b.len() {
        match b[i] {
            b'{' => depth += 1,
            b'}' if depth == 0 => break,
            b'}' => depth -= 1,
            b',' if depth == 0 => expect = true,
            c if expect && depth == 0 && (c.is_ascii_alphabetic() || c == b'_') => {
                let id = ident_at(&s[i..]);
                heads.push(id);
                i += id.len();
                expect = false;
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    heads
}

/// Every use of another part in one file (`rel`: its path under `src/engine/`).
fn uses_in(rel: &str, text: &str) -> Vec<Use> {
    let from = part_of(rel);
    let top_level = !rel.contains('/');
    let mut found = Vec::new();
    for (n, line) in code_only(text).lines().enumerate() {
        let mut add = |to: &str| {
            if !to.is_empty() && to != "self" && to != from {
                found.push(Use { from: from.clone(), to: to.to_string(), file: rel.to_string(), line: n + 1 });
            }
        };
        for (at, _) in line.match_indices("crate::engine::") {
            let rest = &line[at + "crate::engine::".len()..];
            if let Some(group) = rest.strip_prefix('{') {
                group_heads(group).into_iter().for_each(&mut add);
            } else {
                add(ident_at(rest));
            }
        }
        for (at, _) in line.match_indices("crate::") {
            let rest = &line[at + "crate::".len()..];
            let head = ident_at(rest);
            if SERVICE.contains(&head) {
                add(head);
            }
        }
        // `super::x` in a file directly under `engine/` names engine's `x`.
        if top_level {
            for (at, _) in line.match_indices("super::") {
                let before = &line[..at];
                if before.ends_with("super::") {
                    continue;
                }
                add(ident_at(&line[at + "super::".len()..]));
            }
        }
    }
    found
}

fn layer_of(part: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&part))
}

/// What is wrong with these uses: uses up the layers, of the service or of
/// an unknown part, and cycles between parts.
fn problems(uses: &[Use]) -> Vec<String> {
    let mut out = Vec::new();
    for u in uses {
        if SERVICE.contains(&u.to.as_str()) {
            out.push(format!("{}:{}: the engine uses the service's `{}`", u.file, u.line, u.to));
            continue;
        }
        match (layer_of(&u.from), layer_of(&u.to)) {
            (None, _) => out.push(format!("{}:{}: `{}` is in no layer of LAYERS", u.file, u.line, u.from)),
            (_, None) => out.push(format!("{}:{}: `{}` is in no layer of LAYERS", u.file, u.line, u.to)),
            (Some(a), Some(b)) if b >= a => out.push(format!(
                "{}:{}: `{}` uses `{}`, which is {} it in LAYERS",
                u.file,
                u.line,
                u.from,
                u.to,
                if a == b { "beside" } else { "above" }
            )),
            _ => {}
        }
    }
    // Cycles, found on their own: a depth-first search over the parts.
    let mut graph: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for u in uses.iter().filter(|u| !SERVICE.contains(&u.to.as_str())) {
        graph.entry(&u.from).or_default().insert(&u.to);
    }
    let mut done: BTreeSet<&str> = BTreeSet::new();
    let nodes: Vec<&str> = graph.keys().copied().collect();
    for start in nodes {
        let mut path = Vec::new();
        find_cycle(&graph, start, &mut path, &mut done, &mut out);
    }
    out
}

fn find_cycle<'a>(
    graph: &BTreeMap<&'a str, BTreeSet<&'a str>>,
    node: &'a str,
    path: &mut Vec<&'a str>,
    done: &mut BTreeSet<&'a str>,
    out: &mut Vec<String>,
) {
    if let Some(at) = path.iter().position(|&p| p == node) {
        let mut cycle: Vec<&str> = path[at..].to_vec();
        cycle.push(node);
        out.push(format!("cycle between engine folders: {}", cycle.join(" -> ")));
        return;
    }
    if done.contains(node) {
        return;
    }
    path.push(node);
    for &next in graph.get(node).into_iter().flatten() {
        find_cycle(graph, next, path, done, out);
    }
    path.pop();
    done.insert(node);
}

fn read_engine(dir: &Path, root: &Path, files: &mut Vec<(String, String)>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir).expect("read src/engine").map(|e| e.unwrap().path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            read_engine(&p, root, files);
        } else if p.extension().is_some_and(|e| e == "rs") {
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            if name.ends_with("_tests.rs") {
                continue;
            }
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/");
            files.push((rel, std::fs::read_to_string(&p).unwrap()));
        }
    }
}

#[test]
fn engine_folders_depend_in_one_direction() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/engine");
    let mut files = Vec::new();
    read_engine(&root, &root, &mut files);
    assert!(files.len() > 50, "found only {} files under src/engine", files.len());
    let uses: Vec<Use> = files.iter().flat_map(|(rel, text)| uses_in(rel, text)).collect();
    // The scanner sees the engine's real wiring (a sanity check of the
    // scanner itself: these uses exist and are allowed).
    for (from, to) in [("models", "fields"), ("train", "models"), ("fields", "nn"), ("dataset", "geometry")] {
        assert!(uses.iter().any(|u| u.from == from && u.to == to), "the scanner found no use of {to} in {from}");
    }
    // Every part under src/engine is in a layer.
    let parts: BTreeSet<String> = files.iter().map(|(rel, _)| part_of(rel)).filter(|p| p != "mod").collect();
    for p in &parts {
        assert!(layer_of(p).is_some(), "src/engine/{p} is in no layer of LAYERS: add it where it belongs");
    }
    let found = problems(&uses);
    assert!(found.is_empty(), "the engine's folders depend on each other the wrong way:\n{}", found.join("\n"));
}

#[test]
fn a_use_up_the_layers_fails() {
    let text = "use crate::engine::train::trainer::TrainConfig;\n";
    let p = problems(&uses_in("models/config.rs", text));
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(p[0].contains("models/config.rs:1: `models` uses `train`, which is above it"), "{p:?}");
    // The same in a group, and in a path inside code.
    let text = "use crate::engine::{geometry::math::Ray, train::pass};\nfn f() { crate::engine::train::x(); }\n";
    let p = problems(&uses_in("fields/mlp.rs", text));
    assert_eq!(p.len(), 2, "{p:?}");
    assert!(p[0].contains("fields/mlp.rs:1:") && p[1].contains("fields/mlp.rs:2:"), "{p:?}");
    // Folders on one line must not use each other.
    let p = problems(&uses_in("io/persist.rs", "use crate::engine::rng::Rng;\n"));
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(p[0].contains("beside"), "{p:?}");
}

#[test]
fn a_use_of_the_service_fails() {
    let p = problems(&uses_in("render/mod.rs", "use crate::jobs::JobHost;\n"));
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(p[0].contains("the engine uses the service's `jobs`"), "{p:?}");
}

#[test]
fn a_cycle_fails() {
    let mut uses = uses_in("geometry/rig.rs", "use crate::engine::dataset::Dataset;\n");
    uses.extend(uses_in("dataset/mod.rs", "use crate::engine::geometry::camera::Camera;\n"));
    let p = problems(&uses);
    assert!(p.iter().any(|m| m.contains("cycle between engine folders: ")), "{p:?}");
    assert!(p.iter().any(|m| m.contains("geometry/rig.rs:1: `geometry` uses `dataset`, which is above it")), "{p:?}");
}

#[test]
fn tests_comments_and_strings_are_not_uses() {
    let text = "\
//! Trained by `crate::engine::train::pass`.
use crate::engine::geometry::math::Ray;
const S: &str = \"crate::engine::train\";
/* crate::engine::train::x */
#[cfg(test)]
mod tests {
    use crate::engine::train::trainer::Trainer;
    fn f() { let c = '{'; }
}
#[cfg(test)]
#[path = \"x_tests.rs\"]
mod more;
fn g() { crate::engine::train::late(); }
";
    let uses = uses_in("models/x.rs", text);
    let tos: Vec<(&str, usize)> = uses.iter().map(|u| (u.to.as_str(), u.line)).collect();
    assert_eq!(tos, vec![("geometry", 2), ("train", 13)]);
}

#[test]
fn top_level_files_use_engine_parts_through_super() {
    let uses = uses_in("batch.rs", "use super::geometry::math::Ray;\nuse super::train::x;\n");
    let p = problems(&uses);
    assert_eq!(p.len(), 1, "{p:?}");
    assert!(p[0].contains("batch.rs:2: `batch` uses `train`"), "{p:?}");
}

/// Every use of the engine in `text` (a file of the service) that does not
/// go through `engine::front`, as `file:line: path`.
fn back_door_uses(rel: &str, text: &str) -> Vec<String> {
    let mut found = Vec::new();
    for (n, line) in code_only(text).lines().enumerate() {
        for (at, _) in line.match_indices("crate::engine") {
            let rest = &line[at + "crate::engine".len()..];
            let heads = match rest.strip_prefix("::") {
                Some(r) => match r.strip_prefix('{') {
                    Some(group) => group_heads(group),
                    None => vec![ident_at(r)],
                },
                None => vec![""],
            };
            if heads.iter().any(|h| *h != "front") {
                found.push(format!("{rel}:{}: {}", n + 1, line.trim()));
            }
        }
    }
    found
}

fn read_rs(dir: &Path, root: &Path, files: &mut Vec<(String, String)>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            read_rs(&p, root, files);
        } else if p.extension().is_some_and(|e| e == "rs") {
            let rel = p.strip_prefix(root).unwrap().to_string_lossy().replace('\\', "/");
            files.push((rel, std::fs::read_to_string(&p).unwrap()));
        }
    }
}

/// `api`, `jobs` and `worker` reach the engine only through its front door
/// (`engine::front`): a load, a render, a training session, an estimate and
/// the types they take. Test code may use anything.
#[test]
fn the_service_uses_the_engine_through_its_front_door() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    for part in THROUGH_THE_FRONT_DOOR {
        read_rs(&src.join(part), &src, &mut files);
    }
    assert!(files.len() > 20, "found only {} files under src/api, src/jobs and src/worker", files.len());
    let through: usize = files.iter().map(|(_, t)| code_only(t).matches("crate::engine::front").count()).sum();
    assert!(through > 10, "the scanner found only {through} uses of engine::front");
    let found: Vec<String> = files.iter().flat_map(|(rel, text)| back_door_uses(rel, text)).collect();
    assert!(found.is_empty(), "the service uses the engine past engine::front:\n{}", found.join("\n"));
}

#[test]
fn a_use_past_the_front_door_fails() {
    let text = "use crate::engine::front::{Model, load_model};\nuse crate::engine::train::persist;\n\
                fn f() { crate::engine::view::render_view_with(); }\nuse crate::engine::{front::Model, io::fsio};\n\
                use crate::engine;\n#[cfg(test)]\nmod tests {\n    use crate::engine::train::trainer::Trainer;\n}\n";
    let found = back_door_uses("api/models.rs", text);
    let lines: Vec<&str> = found.iter().map(|f| &f[..f.find(": ").unwrap()]).collect();
    assert_eq!(lines, ["api/models.rs:2", "api/models.rs:3", "api/models.rs:4", "api/models.rs:5"], "{found:?}");
}

/// The names users pick a model to train by, outside the engine, are the
/// registry's trainable presets exactly (`models::config::trainable_presets`:
/// splats are baked, not trained): openapi.yaml's enum and the web app's
/// picker, each after `auto`.
#[test]
fn user_facing_model_lists_are_the_registrys_presets() {
    let presets: Vec<String> =
        radiance::engine::models::config::trainable_presets().into_iter().map(String::from).collect();
    let mut want = vec!["auto".to_string()];
    want.extend(presets.iter().cloned());
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let spec = std::fs::read_to_string(root.join("openapi.yaml")).unwrap();
    let line = spec.lines().find(|l| l.trim_start().starts_with("enum: [auto,")).expect("openapi.yaml's model enum");
    let listed: Vec<String> = line
        .trim()
        .trim_start_matches("enum: [")
        .trim_end_matches(']')
        .split(',')
        .map(|s| s.trim().to_string())
        .collect();
    assert_eq!(listed, want, "openapi.yaml's model enum");
    let page = std::fs::read_to_string(root.join("web/index.html")).unwrap();
    let start = page.find("<option value=\"auto\"").expect("the web app's model picker");
    let end = start + page[start..].find("</select>").expect("the picker's end");
    let options: Vec<String> =
        page[start..end].split("<option value=\"").skip(1).map(|s| s[..s.find('"').unwrap()].to_string()).collect();
    assert_eq!(options, want, "web/index.html's model picker");
}

/// The longest a function may be, in lines from its `fn` to its closing
/// brace; test code is not counted.
const MAX_FUNCTION_LINES: usize = 80;

/// The functions of `text` (a file's source) longer than `max` lines, as
/// `file:line: name (N lines)`. Comments, strings and `#[cfg(test)]` items
/// are not read.
fn long_functions(rel: &str, text: &str, max: usize) -> Vec<String> {
    let code = code_only(text);
    let lines: Vec<&str> = code.lines().collect();
    let mut found = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        let Some(at) = line.find("fn ") else { continue };
        let before = line[..at].trim();
        let item = before.is_empty()
            || before.split_whitespace().all(|w| {
                matches!(w, "pub" | "const" | "async" | "unsafe" | "extern" | "default") || w.starts_with("pub(")
            });
        let name = ident_at(&line[at + 3..]);
        if !item || name.is_empty() {
            continue;
        }
        // The body: from the first `{` (a `;` first: no body) to its match.
        let mut depth = 0i64;
        let mut end = None;
        'scan: for (m, l) in lines.iter().enumerate().skip(n) {
            let from = if m == n { at } else { 0 };
            for ch in l[from..].chars() {
                match ch {
                    ';' if depth == 0 => break 'scan,
                    '{' => depth += 1,
                    '}' => {
                        depth -= 1;
                        if depth == 0 {
                            end = Some(m);
                            break 'scan;
                        }
                    }
                    _ => {}
                }
            }
        }
        if let Some(end) = end
            && end + 1 - n > max
        {
            found.push(format!("{rel}:{}: {name} ({} lines)", n + 1, end + 1 - n));
        }
    }
    found
}

/// Every file under `src/` but the `tests.rs` / `*_tests.rs` files of unit
/// tests, as (path under `src/`, text).
fn code_files() -> Vec<(String, String)> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    read_rs(&src, &src, &mut files);
    files.retain(|(rel, _)| !(rel.ends_with("/tests.rs") || rel.ends_with("_tests.rs")));
    assert!(files.len() > 100, "found only {} files under src", files.len());
    files
}

/// No function in `src/` is over [`MAX_FUNCTION_LINES`] lines (test code,
/// and the `tests.rs` / `*_tests.rs` files of unit tests, aside).
#[test]
fn no_function_is_over_80_lines() {
    let files = code_files();
    let found: Vec<String> =
        files.iter().flat_map(|(rel, text)| long_functions(rel, text, MAX_FUNCTION_LINES)).collect();
    assert!(found.is_empty(), "functions over {MAX_FUNCTION_LINES} lines:\n{}", found.join("\n"));
}

#[test]
fn a_long_function_is_found() {
    let body = "    let x = 1;\n".repeat(79);
    let text = format!(
        "/// {{ not code\npub(crate) fn long(a: u32) -> u32 {{\n{body}}}\nfn short() {{ let s = \"}}\"; }}\n\
         trait T {{\n    fn declared(&self);\n}}\n#[cfg(test)]\nfn in_tests() {{\n{body}{body}}}\n"
    );
    assert_eq!(long_functions("x.rs", &text, 80), ["x.rs:2: long (81 lines)"]);
    assert!(long_functions("x.rs", &text, 81).is_empty());
}

/// The most lines a file under `src/` has before its tests.
const MAX_FILE_LINES: usize = 600;

/// The lines of `text` (a file's source) before its module of tests (a
/// `#[cfg(test)]` on a `mod`, other attributes between): all of them when
/// it has none.
fn lines_before_tests(text: &str) -> usize {
    let lines: Vec<&str> = text.lines().collect();
    let tests_at =
        (0..lines.len()).find(|&i| {
            lines[i].trim() == "#[cfg(test)]"
                && lines[i + 1..].iter().map(|l| l.trim()).find(|l| !l.starts_with("#[")).is_some_and(|l| {
                    l.starts_with("mod ") || l.starts_with("pub mod ") || l.starts_with("pub(crate) mod ")
                })
        });
    tests_at.unwrap_or(lines.len())
}

/// No file in `src/` has over [`MAX_FILE_LINES`] lines before its tests: a
/// longer one has more than one job.
#[test]
fn no_file_is_over_600_lines_before_its_tests() {
    let files = code_files();
    let found: Vec<String> = files
        .iter()
        .map(|(rel, text)| (rel, lines_before_tests(text)))
        .filter(|(_, n)| *n > MAX_FILE_LINES)
        .map(|(rel, n)| format!("{rel}: {n} lines"))
        .collect();
    assert!(found.is_empty(), "files over {MAX_FILE_LINES} lines before their tests:\n{}", found.join("\n"));
}

#[test]
fn the_lines_before_a_files_tests_are_counted() {
    let code = "use a;\n#[cfg(test)]\nuse b;\nfn f() {}\n";
    assert_eq!(lines_before_tests(code), 4);
    assert_eq!(lines_before_tests(&format!("{code}#[cfg(test)]\n#[path = \"x_tests.rs\"]\nmod tests;\n")), 4);
    assert_eq!(lines_before_tests(&format!("{code}#[cfg(test)]\nmod tests {{\n    fn g() {{}}\n}}\n")), 4);
}

/// The module a file under `src/` is (`engine/bake/mod.rs` is
/// `engine::bake`, `lib.rs` the crate's root, ``).
fn module_of(rel: &str) -> String {
    let stem = rel.trim_end_matches(".rs");
    let mut parts: Vec<&str> = stem.split('/').collect();
    if matches!(parts.last(), Some(&"mod" | &"lib" | &"main")) {
        parts.pop();
    }
    parts.join("::")
}

/// The modules of the crate that the code of file `rel` (module `from`)
/// uses, by `crate::` and `super::` paths, each the longest module of
/// `modules` its path names, with the line; its own ancestors and
/// descendants left out (a folder's `mod.rs` and its files share a home).
fn module_uses(rel: &str, text: &str, modules: &BTreeSet<String>) -> Vec<(String, usize)> {
    let from = module_of(rel);
    let own: Vec<&str> = if from.is_empty() { Vec::new() } else { from.split("::").collect() };
    // `super` of a folder's mod.rs is the folder's parent, of a file its folder's.
    let parent: Vec<&str> = own[..own.len().saturating_sub(1)].to_vec();
    let related = |m: &str| m == from || m.starts_with(&format!("{from}::")) || from.starts_with(&format!("{m}::"));
    let mut found = Vec::new();
    for (n, line) in code_only(text).lines().enumerate() {
        for (base, root) in [("crate::", Vec::new()), ("super::", parent.clone())] {
            for (at, _) in line.match_indices(base) {
                if base == "super::" && at >= 7 && &line[at - 7..at] == "crate::" {
                    continue;
                }
                let mut path: Vec<String> = root.iter().map(|s| s.to_string()).collect();
                let mut rest = &line[at + base.len()..];
                let mut heads = vec![];
                loop {
                    if let Some(group) = rest.strip_prefix('{') {
                        heads = group_heads(group).into_iter().map(String::from).collect();
                        break;
                    }
                    let id = ident_at(rest);
                    if id.is_empty() {
                        break;
                    }
                    path.push(id.to_string());
                    match rest[id.len()..].strip_prefix("::") {
                        Some(r) => rest = r,
                        None => break,
                    }
                }
                let candidates: Vec<Vec<String>> = if heads.is_empty() {
                    vec![path.clone()]
                } else {
                    heads.iter().map(|h| [path.clone(), vec![h.clone()]].concat()).collect()
                };
                for c in candidates {
                    let target = (1..=c.len()).rev().map(|k| c[..k].join("::")).find(|m| modules.contains(m));
                    if let Some(t) = target.filter(|t| !related(t)) {
                        found.push((t, n + 1));
                    }
                }
            }
        }
    }
    found
}

/// Pairs of modules that use each other, each with one line of each side.
fn two_module_circles(files: &[(String, String)]) -> Vec<String> {
    let modules: BTreeSet<String> = files.iter().map(|(rel, _)| module_of(rel)).collect();
    let mut uses: BTreeMap<(String, String), String> = BTreeMap::new();
    for (rel, text) in files {
        for (to, line) in module_uses(rel, text, &modules) {
            uses.entry((module_of(rel), to)).or_insert(format!("{rel}:{line}"));
        }
    }
    uses.iter()
        .filter(|((a, b), _)| a < b)
        .filter_map(|((a, b), at)| uses.get(&(b.clone(), a.clone())).map(|back| format!("{a} ({at}) <-> {b} ({back})")))
        .collect()
}

/// No two modules of the crate use each other: each file's dependencies
/// point one way (a folder's files and its `mod.rs` aside). Test code may
/// use anything.
#[test]
fn no_two_modules_use_each_other() {
    let files = code_files();
    let modules: BTreeSet<String> = files.iter().map(|(rel, _)| module_of(rel)).collect();
    let found: usize = files.iter().map(|(rel, text)| module_uses(rel, text, &modules).len()).sum();
    assert!(found > 500, "the scanner found only {found} uses between modules");
    let circles = two_module_circles(&files);
    assert!(circles.is_empty(), "modules that use each other:\n{}", circles.join("\n"));
}

#[test]
fn two_modules_that_use_each_other_are_found() {
    let files = [
        ("jobs/mod.rs".to_string(), "pub mod bake;\npub mod train;\n".to_string()),
        ("jobs/bake.rs".to_string(), "use super::train::{evaluate, load};\nuse crate::records::X;\n".to_string()),
        ("jobs/train.rs".to_string(), "fn f() { super::bake::enqueue(); }\nuse super::Job;\n".to_string()),
        ("records.rs".to_string(), "use crate::{datadir::now_ms, jobs::Job};\n".to_string()),
        ("datadir.rs".to_string(), "use crate::records::{Info};\n#[cfg(test)]\nuse crate::jobs::bake;\n".to_string()),
    ];
    assert_eq!(
        two_module_circles(&files),
        [
            "datadir (datadir.rs:1) <-> records (records.rs:1)",
            "jobs::bake (jobs/bake.rs:1) <-> jobs::train (jobs/train.rs:1)",
        ]
    );
}
