//! A database named by a `postgres://` URL: a pool of connections for the
//! queue's statements, and dedicated connections for what must not share
//! one (the migration lock, LISTEN).
//!
//! Errors name the server as `host:port` with its database and user, never
//! the password, so they can be logged and shown as they are.

use std::time::Duration;

use deadpool_postgres::{Manager, ManagerConfig, Pool, RecyclingMethod, Runtime};
use tokio_postgres::config::Host;
use tokio_postgres::tls::NoTlsStream;
use tokio_postgres::{Client, Config, Connection, NoTls, Socket};

use super::error::{PgError, chain};

/// How long a connection may take to open when the URL does not say
/// (`connect_timeout`).
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);

/// How long a statement waits for a pooled connection while all are busy.
pub const POOL_WAIT: Duration = Duration::from_secs(30);

/// The server a URL names, and how to reach it.
#[derive(Clone)]
pub struct Database {
    config: Config,
    /// `host:port (database D, user U)`: for messages.
    target: String,
}

impl std::fmt::Debug for Database {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Not `Config`'s Debug: it would print the password.
        f.debug_struct("Database").field("target", &self.target).finish_non_exhaustive()
    }
}

impl Database {
    /// Reads a `postgres://user:password@host:port/database?option=value`
    /// URL (`postgresql://` too; libpq's options, e.g. `connect_timeout`).
    /// Nothing is connected yet.
    pub fn parse(url: &str) -> Result<Self, PgError> {
        if !(url.starts_with("postgres://") || url.starts_with("postgresql://")) {
            let scheme = url.split_once("://").map(|(s, _)| s);
            // Quoting the rest could show a password.
            return Err(PgError::BadUrl(match scheme {
                Some(s) => format!("the scheme is '{s}': expected postgres:// or postgresql://"),
                None => "expected postgres://user:password@host:port/database".into(),
            }));
        }
        let mut config: Config = url.parse().map_err(|e: tokio_postgres::Error| PgError::BadUrl(chain(&e)))?;
        if config.get_hosts().is_empty() {
            return Err(PgError::BadUrl("no host: expected postgres://user:password@host:port/database".into()));
        }
        if config.get_connect_timeout().is_none() {
            config.connect_timeout(CONNECT_TIMEOUT);
        }
        let target = describe(&config);
        Ok(Self { config, target })
    }

    /// The server as messages name it: `host:port (database D, user U)`.
    pub fn target(&self) -> &str {
        &self.target
    }

    /// A pool of up to `size` connections. One is opened at once, so a wrong
    /// URL, a server that is down or refused credentials are an error here,
    /// at start-up, rather than at the first request.
    pub async fn pool(&self, size: usize) -> Result<Pool, PgError> {
        if size == 0 {
            return Err(PgError::Invalid("the database pool needs at least one connection".into()));
        }
        let manager =
            Manager::from_config(self.config.clone(), NoTls, ManagerConfig { recycling_method: RecyclingMethod::Fast });
        let timeout = self.config.get_connect_timeout().copied().unwrap_or(CONNECT_TIMEOUT);
        let pool = Pool::builder(manager)
            .max_size(size)
            .runtime(Runtime::Tokio1)
            .create_timeout(Some(timeout))
            .wait_timeout(Some(POOL_WAIT))
            .build()
            .map_err(|e| PgError::Invalid(format!("cannot build the database pool: {e}")))?;
        // Back into the pool at once, ready for the first statement.
        drop(pool.get().await.map_err(|e| self.connect_error(e, timeout))?);
        Ok(pool)
    }

    /// A connection of its own, driven by a task of the current runtime
    /// (which logs how it ended); closed when the client is dropped.
    pub async fn connect(&self) -> Result<Client, PgError> {
        let (client, connection) = self.connect_raw().await?;
        let target = self.target.clone();
        tokio::spawn(async move {
            if let Err(e) = connection.await {
                tracing::warn!(database = %target, error = %chain(&e), "database connection ended");
            }
        });
        Ok(client)
    }

    /// A connection whose messages (notifications) the caller reads.
    pub(super) async fn connect_raw(&self) -> Result<(Client, Connection<Socket, NoTlsStream>), PgError> {
        self.config
            .connect(NoTls)
            .await
            .map_err(|e| PgError::Connect { target: self.target.clone(), reason: chain(&e) })
    }

    fn connect_error(&self, e: deadpool_postgres::PoolError, timeout: Duration) -> PgError {
        let reason = match e {
            deadpool_postgres::PoolError::Backend(e) => chain(&e),
            deadpool_postgres::PoolError::Timeout(_) => format!("no answer within {} s", timeout.as_secs_f64()),
            e => e.to_string(),
        };
        PgError::Connect { target: self.target.clone(), reason }
    }
}

/// `host:port, host:port (database D, user U)`, the password left out.
fn describe(config: &Config) -> String {
    let ports = config.get_ports();
    let hosts: Vec<String> = config
        .get_hosts()
        .iter()
        .enumerate()
        .map(|(i, h)| {
            // libpq's rule: one port for every host, or one each; 5432 by default.
            let port = ports.get(i).or(ports.first()).copied().unwrap_or(5432);
            match h {
                Host::Tcp(name) if name.contains(':') => format!("[{name}]:{port}"),
                Host::Tcp(name) => format!("{name}:{port}"),
                Host::Unix(path) => format!("{}:{port}", path.display()),
            }
        })
        .collect();
    let mut about = Vec::new();
    if let Some(db) = config.get_dbname() {
        about.push(format!("database {db}"));
    }
    if let Some(user) = config.get_user() {
        about.push(format!("user {user}"));
    }
    let about = if about.is_empty() { String::new() } else { format!(" ({})", about.join(", ")) };
    format!("{}{about}", hosts.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_url_is_described_by_host_port_database_and_user_without_its_password() {
        let db = Database::parse("postgres://radiance:s3cr3t-pw@db.example:6543/queue").unwrap();
        assert_eq!(db.target(), "db.example:6543 (database queue, user radiance)");
        assert!(!format!("{db:?}").contains("s3cr3t-pw"), "{db:?}");
        let db = Database::parse("postgresql://u@h1,h2/x").unwrap();
        assert_eq!(db.target(), "h1:5432, h2:5432 (database x, user u)");
    }

    #[test]
    fn bad_urls_are_refused_without_quoting_the_password() {
        for url in [
            "mysql://root:s3cr3t-pw@localhost/db",
            "host=localhost password=s3cr3t-pw",
            "postgres://u:s3cr3t-pw@localhost:notaport/db",
            "postgres://u:s3cr3t-pw@localhost/db?bogus_option=1",
            "postgres://u:s3cr3t-pw@/db",
        ] {
            let e = Database::parse(url).expect_err(url).to_string();
            assert!(e.starts_with("invalid database URL: "), "{url}: {e}");
            assert!(!e.contains("s3cr3t"), "{url}: {e}");
        }
    }

    #[tokio::test]
    async fn an_unreachable_server_is_named_by_host_and_port_and_not_by_password() {
        // A port nothing listens on: bound, then closed.
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let db = Database::parse(&format!("postgres://radiance:s3cr3t-pw@127.0.0.1:{port}/radiance")).unwrap();
        let e = db.pool(2).await.expect_err("nothing listens there").to_string();
        assert!(e.starts_with(&format!("cannot connect to PostgreSQL at 127.0.0.1:{port} (database radiance")), "{e}");
        assert!(e.to_lowercase().contains("refused"), "the reason is given: {e}");
        assert!(!e.contains("s3cr3t"), "{e}");
        let e = db.connect().await.expect_err("nothing listens there").to_string();
        assert!(e.contains(&format!("127.0.0.1:{port}")) && !e.contains("s3cr3t"), "{e}");
        assert!(db.pool(0).await.is_err(), "an empty pool is refused");
    }
}
