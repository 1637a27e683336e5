//! The role a `radiance serve` node plays (docs/design/scale-out.md,
//! section 2.5). `all`, the default, serves the API and runs the jobs in
//! one process over the embedded stores: the only role built. `api` (the
//! API alone) and `worker` (the jobs alone) need the shared stores of
//! issue 16, PostgreSQL and an object store, which are not built yet; a
//! node asked to play them refuses to start, saying so.

use std::fmt;
use std::str::FromStr;

/// What a node does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Role {
    /// The API and the jobs, over the embedded stores.
    #[default]
    All,
    /// The API alone, over the shared stores (not built yet).
    Api,
    /// The jobs alone, over the shared stores (not built yet).
    Worker,
}

impl Role {
    /// The names `--role` takes.
    pub const NAMES: [&'static str; 3] = ["all", "api", "worker"];

    pub fn name(self) -> &'static str {
        match self {
            Role::All => "all",
            Role::Api => "api",
            Role::Worker => "worker",
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Role {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "all" => Ok(Role::All),
            "api" => Ok(Role::Api),
            "worker" => Ok(Role::Worker),
            _ => Err(format!("unknown role '{s}' (expected all, api or worker)")),
        }
    }
}

/// Why a node cannot play `role` yet.
pub fn not_built(role: Role) -> String {
    format!(
        "role '{role}' is not built yet: it needs the shared job and artifact stores of issue 16 (PostgreSQL \
         and an object store, docs/design/scale-out.md), which this version does not have. Run one node with \
         role 'all' (the default), which serves the API and runs the jobs over its data directory"
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_read_back_and_nothing_else_does() {
        for name in Role::NAMES {
            let role: Role = name.parse().unwrap();
            assert_eq!((role.name(), role.to_string()), (name, name.to_string()));
        }
        assert_eq!(Role::default(), Role::All);
        let e = "API".parse::<Role>().unwrap_err();
        assert!(e.contains("'API'") && e.contains("all, api or worker"), "{e}");
        assert!(not_built(Role::Worker).starts_with("role 'worker' is not built yet"));
    }
}
