//! The role a `radiance serve` node plays (docs/design/scale-out.md,
//! section 2.5). `all`, the default, serves the API and runs the jobs in
//! one process: over the embedded stores, or over the shared ones. `api`
//! (the API alone) and `worker` (the jobs alone) need the shared stores,
//! PostgreSQL and an object store; a node asked to play them without those
//! refuses to start, saying so.

use std::fmt;
use std::str::FromStr;

/// What a node does.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Role {
    /// The API and the jobs, over the embedded stores or the shared ones.
    #[default]
    All,
    /// The API alone, over the shared stores.
    Api,
    /// The jobs alone, over the shared stores (and health and metrics).
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

/// Why a node cannot play `role` over the embedded stores.
pub fn needs_stores(role: Role) -> String {
    format!(
        "role '{role}' needs the shared job and artifact stores (a PostgreSQL database and an object store, \
         docs/design/scale-out.md); over its own data directory a node plays role 'all' (the default), which \
         serves the API and runs the jobs"
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
        assert!(needs_stores(Role::Worker).starts_with("role 'worker' needs the shared job and artifact stores"));
    }
}
