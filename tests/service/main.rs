//! The REST service end to end: the real server on 127.0.0.1:0 with a
//! temporary data directory and a tiny generated scene; one module per
//! concern, in one test binary.

#[path = "../common/mod.rs"]
mod common;

mod appearance;
mod auth;
mod hostile;
mod jobs;
mod openapi;
mod poses;
mod ready;
mod restart;
mod uploads;
mod web;
