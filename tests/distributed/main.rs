//! Distributed mode end to end (issue 16, docs/design/scale-out.md): API
//! nodes and workers as separate processes of the built binary over a
//! real PostgreSQL (a throwaway cluster) and a shared object store (a
//! `file://` folder, `RADIANCE_TEST_OBJECT_STORE`, or a real S3 server of
//! the test's own), one cluster at a time (`cluster`): a worker killed
//! mid-training (`failover`, on `file://` and on S3), what API nodes serve
//! and a cancel reaching the worker (`api_nodes`, on `file://` and on S3),
//! SIGTERM and a frozen worker's self-fence (`fencing`), readiness and
//! start-up (`ready`), an API node killed mid-upload to S3 (`upload`), a
//! training job's bake run by a worker on S3 (`bake`); and,
//! run by hand, the "Scaling out" measurements of docs/benchmarks.md (`bench`).

#[path = "../common/mod.rs"]
mod common;

mod api_nodes;
mod bake;
mod bench;
mod cluster;
mod failover;
mod fencing;
mod ready;
mod upload;
