//! Distributed mode end to end (issue 16, docs/design/scale-out.md): API
//! nodes and workers as separate processes of the built binary over a
//! real PostgreSQL (a throwaway cluster) and a shared object store (a
//! `file://` folder, or `RADIANCE_TEST_OBJECT_STORE`). One cluster at a
//! time (`cluster::serial`).

#[path = "../common/mod.rs"]
mod common;

mod api_nodes;
mod cluster;
mod failover;
mod fencing;
mod ready;
