//! radiance: train Neural Radiance Fields on CPUs and render novel views.
//!
//! `engine` knows nothing of HTTP or async; `media` encodes what the engine
//! renders; `cli` drives both from the command line; `api` serves them over
//! HTTP through `store`'s job and artifact stores, whose embedded pair runs
//! `jobs` (the training queue) over `storage` (the data directory);
//! `serve --database-url` and `--object-store` put the queue and records in
//! PostgreSQL (`store::pg`) and the files in an object store
//! (`store::object`), whose `worker` nodes run the jobs
//! (`docs/design/scale-out.md`).

// Index loops over small fixed-size arrays read more clearly in numeric code.
#![allow(clippy::needless_range_loop)]

pub mod api;
pub mod cli;
pub mod engine;
pub mod jobs;
pub mod media;
pub mod poses;
pub mod storage;
pub mod store;
pub mod system;
pub mod worker;
