//! A small Dockerfile reader: instructions of each stage, with continuation
//! lines joined and comments dropped (enough for this file; no heredocs).
//! And shell words, exec forms, `ENV` pairs, URLs and versions as the
//! Dockerfile writes them.

#[derive(Debug, Clone)]
pub struct Instr {
    pub cmd: String,
    pub args: String,
}

#[derive(Debug, Default)]
pub struct Stage {
    pub image: String,
    pub name: Option<String>,
    pub instrs: Vec<Instr>,
}

impl Stage {
    pub fn all(&self, cmd: &str) -> impl Iterator<Item = &Instr> {
        self.instrs.iter().filter(move |i| i.cmd == cmd)
    }
    /// The last instruction `cmd` (the one Docker uses for ENTRYPOINT, CMD, USER...).
    pub fn last(&self, cmd: &str) -> Option<&Instr> {
        self.all(cmd).last()
    }
}

pub fn parse_dockerfile(text: &str) -> Vec<Stage> {
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
pub fn shell_words(s: &str) -> Vec<String> {
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
pub fn command_words(args: &str) -> Vec<String> {
    if args.trim_start().starts_with('[') {
        serde_json::from_str(args).unwrap_or_else(|e| vec![format!("<invalid JSON array {args:?}: {e}>")])
    } else {
        vec!["/bin/sh".into(), "-c".into(), args.to_string()]
    }
}

/// `ENV K=V K2="V 2"` (or the legacy `ENV K V`).
pub fn env_pairs(args: &str) -> Vec<(String, String)> {
    let words = shell_words(args);
    if words.first().is_some_and(|w| !w.contains('=')) {
        return vec![(words[0].clone(), words[1..].join(" "))];
    }
    words.iter().filter_map(|w| w.split_once('=')).map(|(k, v)| (k.to_string(), v.to_string())).collect()
}

/// `(host, port, path)` of an `http://` URL.
pub fn http_url(url: &str) -> Option<(String, u16, String)> {
    let rest = url.strip_prefix("http://")?;
    let (authority, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    let (host, port) = authority.rsplit_once(':').unwrap_or((authority, "80"));
    let path = path.split(['?', '#']).next().unwrap_or("");
    Some((host.to_string(), port.parse().ok()?, if path.is_empty() { "/".into() } else { path.into() }))
}

pub fn version_of(s: &str) -> Option<(u32, u32)> {
    let mut it = s.split('.').map(|p| p.chars().take_while(char::is_ascii_digit).collect::<String>());
    Some((it.next()?.parse().ok()?, it.next()?.parse().ok()?))
}
