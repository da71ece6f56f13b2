//! End-to-end tests in one binary, one module per concern: the real `isovox` binary on real
//! files, and the HTTP service on a real socket. [`common`] holds what they share.
#![allow(clippy::unwrap_used)] // tests fail loudly on purpose

mod common;

mod corrupt;
mod http_read;
mod http_routes;
mod mesh_operands;
