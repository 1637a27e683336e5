//! `compose.yaml` against the binary: a deployment of PostgreSQL, an S3
//! server, API nodes and workers must set only `RADIANCE_*` variables
//! `radiance serve` reads, give each radiance service a role the binary
//! accepts and the shared stores distributed mode needs, and point those
//! stores at services the file defines. CI has no Docker: this reads the
//! file with a small reader of the YAML subset compose files use (block
//! maps and lists, flow lists, anchors and aliases of whole maps).

use std::collections::BTreeMap;

use super::help::Help;

/// A YAML node of the subset: scalars, block/flow lists, block maps.
#[derive(Clone, Debug, PartialEq)]
pub enum Node {
    Scalar(String),
    List(Vec<Node>),
    Map(BTreeMap<String, Node>),
}

impl Node {
    pub fn get(&self, key: &str) -> Option<&Node> {
        match self {
            Node::Map(m) => m.get(key),
            _ => None,
        }
    }

    pub fn scalar(&self) -> Option<&str> {
        match self {
            Node::Scalar(s) => Some(s),
            _ => None,
        }
    }
}

struct Line<'a> {
    indent: usize,
    text: &'a str,
    number: usize,
}

/// Parses `text`; errors name the line.
pub fn parse(text: &str) -> Result<Node, String> {
    let lines: Vec<Line> = text
        .lines()
        .enumerate()
        .filter_map(|(i, l)| {
            let t = l.trim_end();
            let body = t.trim_start();
            (!body.is_empty() && !body.starts_with('#')).then(|| Line {
                indent: t.len() - body.len(),
                text: body,
                number: i + 1,
            })
        })
        .collect();
    let mut anchors = BTreeMap::new();
    let mut at = 0;
    let node = block(&lines, &mut at, 0, &mut anchors)?;
    match lines.get(at) {
        None => Ok(node),
        Some(l) => Err(format!("line {}: unexpected indentation", l.number)),
    }
}

fn block(lines: &[Line], at: &mut usize, indent: usize, anchors: &mut BTreeMap<String, Node>) -> Result<Node, String> {
    let Some(first) = lines.get(*at) else { return Ok(Node::Map(BTreeMap::new())) };
    if first.text.starts_with("- ") || first.text == "-" {
        let mut items = Vec::new();
        while let Some(l) = lines.get(*at).filter(|l| l.indent == indent && l.text.starts_with('-')) {
            let rest = l.text[1..].trim_start();
            *at += 1;
            if rest.contains(": ") || rest.ends_with(':') {
                // A map item: its first key on the dash's line, the others
                // below it at the same column.
                let column = l.indent + (l.text.len() - rest.len());
                let mut sub = vec![Line { indent: column, text: rest, number: l.number }];
                while let Some(n) = lines.get(*at).filter(|n| n.indent > l.indent) {
                    sub.push(Line { indent: n.indent, text: n.text, number: n.number });
                    *at += 1;
                }
                let mut i = 0;
                items.push(block(&sub, &mut i, column, anchors)?);
                if let Some(n) = sub.get(i) {
                    return Err(format!("line {}: unexpected indentation", n.number));
                }
                continue;
            }
            items.push(scalar_or_flow(rest, l.number)?);
        }
        return Ok(Node::List(items));
    }
    let mut map = BTreeMap::new();
    while let Some(l) = lines.get(*at).filter(|l| l.indent == indent) {
        let (key, rest) = split_key(l.text).ok_or_else(|| format!("line {}: expected `key: value`", l.number))?;
        *at += 1;
        let value = if rest == "|" {
            // A literal block: the more indented lines, kept as text.
            let mut s = String::new();
            while let Some(n) = lines.get(*at).filter(|n| n.indent > indent) {
                s.push_str(n.text);
                s.push('\n');
                *at += 1;
            }
            Node::Scalar(s)
        } else if let Some(name) = rest.strip_prefix('&') {
            let node = nested(lines, at, indent, anchors)?;
            anchors.insert(name.to_string(), node.clone());
            node
        } else if let Some(name) = rest.strip_prefix('*') {
            anchors.get(name).cloned().ok_or_else(|| format!("line {}: no anchor `{name}`", l.number))?
        } else if rest.is_empty() {
            nested(lines, at, indent, anchors)?
        } else {
            scalar_or_flow(rest, l.number)?
        };
        if key == "<<" {
            match value {
                Node::Map(m) => map.extend(m),
                _ => return Err(format!("line {}: `<<` merges a map", l.number)),
            }
        } else if map.insert(key.to_string(), value).is_some() {
            return Err(format!("line {}: `{key}` given twice", l.number));
        }
    }
    Ok(Node::Map(map))
}

/// The block under a key: the lines indented more than it.
fn nested(lines: &[Line], at: &mut usize, indent: usize, anchors: &mut BTreeMap<String, Node>) -> Result<Node, String> {
    match lines.get(*at) {
        Some(n) if n.indent > indent => block(lines, at, n.indent, anchors),
        // A list may sit at its key's indentation.
        Some(n) if n.indent == indent && n.text.starts_with('-') => block(lines, at, indent, anchors),
        _ => Ok(Node::Scalar(String::new())),
    }
}

fn split_key(text: &str) -> Option<(&str, &str)> {
    if let Some(k) = text.strip_suffix(':') {
        return Some((unquote(k), ""));
    }
    let i = text.find(": ")?;
    Some((unquote(&text[..i]), text[i + 2..].trim()))
}

fn unquote(s: &str) -> &str {
    let s = s.trim();
    s.strip_prefix('"').and_then(|t| t.strip_suffix('"')).unwrap_or(s)
}

fn scalar_or_flow(text: &str, number: usize) -> Result<Node, String> {
    let text = text.split(" #").next().unwrap_or(text).trim();
    if let Some(inner) = text.strip_prefix('[') {
        let inner = inner.strip_suffix(']').ok_or_else(|| format!("line {number}: unclosed flow list"))?;
        return Ok(Node::List(
            inner
                .split(',')
                .map(|s| s.trim())
                .filter(|s| !s.is_empty())
                .map(|s| Node::Scalar(unquote(s).into()))
                .collect(),
        ));
    }
    Ok(Node::Scalar(unquote(text).to_string()))
}

/// What is wrong with `compose` (the file's text) for the binary `serve`.
pub fn problems(compose: &str, serve: &Help) -> Vec<String> {
    let mut p = Vec::new();
    let doc = match parse(compose) {
        Ok(d) => d,
        Err(e) => return vec![format!("compose.yaml: {e}")],
    };
    let Some(Node::Map(services)) = doc.get("services") else {
        return vec!["compose.yaml: no services".into()];
    };
    let image = |s: &Node| s.get("image").and_then(Node::scalar).unwrap_or("").to_string();
    let postgres: Vec<&String> = services.keys().filter(|k| image(&services[*k]).starts_with("postgres")).collect();
    let s3: Vec<&String> = services.keys().filter(|k| image(&services[*k]).contains("garage")).collect();
    if postgres.is_empty() {
        p.push("compose.yaml: no PostgreSQL service (image postgres:...)".into());
    }
    if s3.is_empty() {
        p.push("compose.yaml: no S3 server service (image .../garage)".into());
    }
    let mut roles = BTreeMap::new();
    for (name, svc) in services {
        if svc.get("build").is_none() {
            continue;
        }
        let command: Vec<&str> = match svc.get("command") {
            Some(Node::List(c)) => c.iter().filter_map(Node::scalar).collect(),
            _ => Vec::new(),
        };
        let role =
            command.iter().position(|a| *a == "--role").and_then(|i| command.get(i + 1)).copied().unwrap_or("all");
        if !["all", "api", "worker"].contains(&role) {
            p.push(format!("service {name}: --role {role} is not a role (all, api, worker)"));
        }
        for flag in command.iter().filter(|a| a.starts_with("--")) {
            if !serve.flags.contains(*flag) {
                p.push(format!("service {name}: `radiance serve` has no flag {flag}"));
            }
        }
        let env = match svc.get("environment") {
            Some(Node::Map(m)) => m.clone(),
            _ => BTreeMap::new(),
        };
        for k in env.keys().filter(|k| k.starts_with("RADIANCE_")) {
            if !serve.envs.contains(k) {
                p.push(format!("service {name}: `radiance serve` does not read {k}"));
            }
        }
        let var = |k: &str| env.get(k).and_then(Node::scalar).unwrap_or("");
        let db = var("RADIANCE_DATABASE_URL");
        let store = var("RADIANCE_OBJECT_STORE");
        if !db.starts_with("postgres://")
            || !postgres.iter().any(|s| db.contains(&format!("@{s}:")) || db.contains(&format!("@{s}/")))
        {
            p.push(format!("service {name}: RADIANCE_DATABASE_URL `{db}` does not name the PostgreSQL service"));
        }
        if !store.starts_with("s3://") {
            p.push(format!("service {name}: RADIANCE_OBJECT_STORE `{store}` is not an s3:// bucket"));
        }
        let endpoint = var("AWS_ENDPOINT_URL");
        if !s3.iter().any(|s| endpoint.starts_with(&format!("http://{s}:"))) {
            p.push(format!("service {name}: AWS_ENDPOINT_URL `{endpoint}` does not name the S3 service"));
        }
        if endpoint.starts_with("http://") && var("AWS_ALLOW_HTTP") != "true" {
            p.push(format!("service {name}: a plain-HTTP endpoint needs AWS_ALLOW_HTTP=true"));
        }
        for k in ["AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_REGION"] {
            if var(k).is_empty() {
                p.push(format!("service {name}: no {k}"));
            }
        }
        let replicas = svc
            .get("deploy")
            .and_then(|d| d.get("replicas"))
            .and_then(Node::scalar)
            .map_or(Ok(1), str::parse::<usize>)
            .unwrap_or(0);
        *roles.entry(role).or_insert(0) += replicas;
    }
    if roles.get("api").copied().unwrap_or(0) < 1 {
        p.push("compose.yaml: no API node (--role api)".into());
    }
    if roles.get("worker").copied().unwrap_or(0) < 2 {
        p.push(format!("compose.yaml: {} worker(s); the deployment shows two", roles.get("worker").unwrap_or(&0)));
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reader_takes_anchors_merges_lists_and_literal_blocks() {
        let listed = parse("c:\n  - source: g\n    target: /etc/g\n  - plain\n").unwrap();
        let items = match listed.get("c") {
            Some(Node::List(items)) => items.clone(),
            other => panic!("{other:?}"),
        };
        assert_eq!(items[0].get("target").and_then(Node::scalar), Some("/etc/g"));
        assert_eq!(items[1].scalar(), Some("plain"));
        let text = "x: &e\n  A: \"1\"\n  B: two\ns:\n  one:\n    environment:\n      <<: *e\n      C: 3\n    command: [\"--role\", \"api\"]\n    ports:\n      - \"8080:8080\"\n  two:\n    environment: *e\nc:\n  t:\n    content: |\n      a = 1\n      b = 2\n";
        let doc = parse(text).unwrap();
        let one = doc.get("s").unwrap().get("one").unwrap();
        let env = one.get("environment").unwrap();
        assert_eq!(env.get("A").and_then(Node::scalar), Some("1"));
        assert_eq!(env.get("C").and_then(Node::scalar), Some("3"));
        assert_eq!(
            one.get("command"),
            Some(&Node::List(vec![Node::Scalar("--role".into()), Node::Scalar("api".into())]))
        );
        assert_eq!(one.get("ports"), Some(&Node::List(vec![Node::Scalar("8080:8080".into())])));
        assert_eq!(
            doc.get("s").unwrap().get("two").unwrap().get("environment").unwrap().get("B").and_then(Node::scalar),
            Some("two")
        );
        assert_eq!(
            doc.get("c").unwrap().get("t").unwrap().get("content").and_then(Node::scalar),
            Some("a = 1\nb = 2\n")
        );
        assert!(parse("a: 1\na: 2\n").unwrap_err().contains("given twice"));
        assert!(parse("a: *missing\n").unwrap_err().contains("no anchor"));
    }
}
