//! radiance: train Neural Radiance Fields on CPUs and render novel views.
//!
//! `engine` knows nothing of HTTP or async; `media` encodes what the engine
//! renders; `cli` drives both from the command line; `api` serves them over
//! HTTP through the job and artifact stores of `backend`. Its embedded
//! backend (one node, the default) runs `jobs` (the queue, the scheduler
//! and the job bodies) over `datadir` (the data directory); in distributed
//! mode (`serve --database-url` and `--object-store`) the queue and the
//! records are in PostgreSQL (`backend::pg`), the files in an object store
//! (`backend::object`), and `worker` nodes run the jobs
//! (`docs/design/scale-out.md`). `records` are the scenes, models and
//! videos every backend stores.

// Index loops over small fixed-size arrays read more clearly in numeric code.
#![allow(clippy::needless_range_loop)]

pub mod api;
pub mod backend;
pub mod cli;
pub mod datadir;
pub mod engine;
pub mod jobs;
pub mod media;
pub mod poses;
pub mod records;
pub mod system;
pub mod worker;
