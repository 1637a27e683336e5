//! The contract of the job store and the artifact store
//! (`radiance::backend`): what every pair of stores does alike, written once
//! as async checks over how a pair is opened (`contract`), and run here on
//! the embedded pair (`embedded`) and on the PostgreSQL job store with the
//! embedded artifact store (`pg`; `pg_jobs` checks what it does beyond the
//! contract), and on the embedded job store with the object artifact store
//! over `file://` and over a real S3 server (`object`; `objects` checks
//! what it does beyond the contract, on both, in the stores of `bucket`;
//! `s3_settings` how it reaches the server).
//! Another backend runs the same checks with `contract_tests!(its_opener)`.

#[path = "../common/mod.rs"]
mod common;
#[macro_use]
mod contract;
mod bucket;
mod embedded;
mod object;
mod objects;
mod pg;
mod pg_jobs;
mod s3_settings;
