//! The schema, brought to this binary's version at start-up by every node.
//!
//! Migrations are SQL files (`migrations/NNNN_name.sql`) compiled in. On a
//! connection of its own, under a session advisory lock (so nodes starting
//! together apply each migration once, one after the other), the runner
//! reads `radiance_migrations`, refuses a database whose applied migrations
//! differ from ours (one changed after it was applied, or one newer than
//! this binary knows), then applies each missing migration in its own
//! transaction together with its row. A migration that fails leaves the
//! ones before it applied and nothing of itself.
//!
//! Migrations must be additive: during a rolling upgrade old and new nodes
//! run against the same schema.

use sha2::{Digest, Sha256};
use tokio_postgres::Client;

use super::connect::Database;
use super::error::{PgError, chain};

/// A schema change: version `NNNN` and `name` of `migrations/NNNN_name.sql`.
#[derive(Clone, Copy, Debug)]
pub struct Migration {
    pub version: i32,
    pub name: &'static str,
    pub sql: &'static str,
}

impl Migration {
    /// The hex sha256 of its SQL, recorded when it is applied.
    pub fn sha256(&self) -> String {
        Sha256::digest(self.sql.as_bytes()).iter().map(|b| format!("{b:02x}")).collect()
    }
}

/// This binary's migrations, in order.
pub const MIGRATIONS: &[Migration] = &[
    Migration { version: 1, name: "init", sql: include_str!("migrations/0001_init.sql") },
    Migration { version: 2, name: "now_ms_floor", sql: include_str!("migrations/0002_now_ms_floor.sql") },
    Migration { version: 3, name: "bake_jobs", sql: include_str!("migrations/0003_bake_jobs.sql") },
];

/// The newest migration this binary knows: the schema it needs.
pub fn newest_version() -> i32 {
    MIGRATIONS.last().map_or(0, |m| m.version)
}

/// The session advisory lock the runner holds: "radiance" in ASCII.
pub const LOCK_KEY: i64 = 0x7261_6469_616e_6365;

/// Brings the database to [`MIGRATIONS`]; returns the versions it applied
/// (none when another node already had).
pub async fn migrate(db: &Database) -> Result<Vec<i32>, PgError> {
    apply(db, MIGRATIONS).await
}

/// Brings the database to `migrations` (versions 1, 2, 3... in order); see
/// the module comment. Returns the versions applied by this call.
pub async fn apply(db: &Database, migrations: &[Migration]) -> Result<Vec<i32>, PgError> {
    if let Some((i, m)) = migrations.iter().enumerate().find(|(i, m)| m.version != *i as i32 + 1) {
        return Err(PgError::Invalid(format!(
            "migration {} ({}) is at place {}: versions must run 1, 2, 3... in order",
            m.version,
            m.name,
            i + 1
        )));
    }
    // Its own connection: closing it (also when this task is dropped half
    // way) releases the lock, which a pooled connection would keep.
    let mut client = db.connect().await?;
    client.execute("SELECT pg_advisory_lock($1)", &[&LOCK_KEY]).await?;
    let applied = apply_locked(&mut client, migrations).await;
    // After a failed migration its transaction was rolled back: the
    // connection is usable, and the unlock is queued behind the rollback.
    let unlocked = client.execute("SELECT pg_advisory_unlock($1)", &[&LOCK_KEY]).await;
    let applied = applied?;
    unlocked?;
    Ok(applied)
}

async fn apply_locked(client: &mut Client, migrations: &[Migration]) -> Result<Vec<i32>, PgError> {
    client
        .batch_execute(
            "CREATE TABLE IF NOT EXISTS radiance_migrations (
               version int PRIMARY KEY,
               name text NOT NULL,
               sha256 text NOT NULL,
               applied_at timestamptz NOT NULL DEFAULT now())",
        )
        .await?;
    let rows = client.query("SELECT version, name, sha256 FROM radiance_migrations ORDER BY version", &[]).await?;
    let mut done = Vec::new();
    for row in &rows {
        let (version, name, sha): (i32, String, String) = (row.get(0), row.get(1), row.get(2));
        let Some(ours) = migrations.iter().find(|m| m.version == version) else {
            let newest = migrations.last().map_or(0, |m| m.version);
            return Err(PgError::Migration(if version > newest {
                format!(
                    "the database schema is newer than this binary: upgrade it (the database has migration \
                     {version} ({name}); this binary knows migrations up to {newest})"
                )
            } else {
                format!("the database has migration {version} ({name}), which this binary does not know")
            }));
        };
        if sha != ours.sha256() {
            return Err(PgError::Migration(format!(
                "migration {version} ({}) was changed after it was applied (sha256 {sha} in the database, {} in \
                 this binary): restore it, and put the change in a new migration",
                ours.name,
                ours.sha256()
            )));
        }
        done.push(version);
    }
    let mut applied = Vec::new();
    for m in migrations.iter().filter(|m| !done.contains(&m.version)) {
        let tx = client.transaction().await?;
        tx.batch_execute(m.sql)
            .await
            .map_err(|e| PgError::Migration(format!("migration {} ({}) failed: {}", m.version, m.name, chain(&e))))?;
        tx.execute(
            "INSERT INTO radiance_migrations (version, name, sha256) VALUES ($1, $2, $3)",
            &[&m.version, &m.name, &m.sha256()],
        )
        .await?;
        tx.commit().await?;
        tracing::info!(version = m.version, name = m.name, "database migration applied");
        applied.push(m.version);
    }
    Ok(applied)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn migrations_are_numbered_in_order_and_hashed_stably() {
        for (i, m) in MIGRATIONS.iter().enumerate() {
            assert_eq!(m.version, i as i32 + 1, "{}", m.name);
            assert_eq!(m.sha256().len(), 64);
            assert_eq!(m.sha256(), m.sha256());
        }
        // The sha256 of "abc" (FIPS 180-2, appendix B.1).
        let abc = Migration { version: 1, name: "t", sql: "abc" };
        assert_eq!(abc.sha256(), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    }

    #[test]
    fn the_lock_key_spells_radiance() {
        assert_eq!(LOCK_KEY.to_be_bytes(), *b"radiance");
    }
}
