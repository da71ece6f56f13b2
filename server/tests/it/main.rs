//! The server crate's integration tests, in one binary: each module is one concern, and the
//! helpers they share are modules of their own. One binary links the server once, where one
//! binary per file linked it thirty times over.
//!
//! Shared helpers:
//! - [`common`]: deterministic volumes and an independent downsampling to compare against;
//! - [`server_process`]: a real `isovox serve` process on an ephemeral port;
//! - [`raw_http`]: requests written byte by byte, for what a client library would hide;
//! - [`tls`]: self-signed certificates and a TLS client;
//! - [`random_terms`]: random ICVG terms for the property tests.
//!
//! libtest starts tests in the order of their names, three at a time in `.ci/run`: the longest,
//! Schemathesis against the API document (minutes of Python on one core), is in the module that
//! sorts first, and the viewer's pages in chromium (over a minute) in the one after, so
//! that they run beside the others instead of alone at the end.
#![allow(clippy::unwrap_used)] // tests fail loudly on purpose

mod api_document;
mod browser;

mod channel_volumes;
mod common;
mod random_terms;
mod raw_http;
mod server_process;
mod tls;

mod channels;
mod checkpoints;
mod cli;
mod connection_limits;
mod dedup_and_versions;
mod durability;
mod edit_cost;
mod formats_clients;
mod formats_views;
mod grid_summaries;
mod hostile;
mod icvg_edits;
mod icvg_golden;
mod icvg_laws;
mod icvg_morphology;
mod import_hostile;
mod live_volume;
mod memory_bound;
mod mesh_closed;
mod mesh_encodings;
mod mesh_kernel;
mod mesh_materials;
mod mesh_strips;
mod object_store;
mod oidc;
mod overload;
mod people;
mod recovery;
mod roundtrip;
mod segments;
mod shared_editing;
mod shutdown;
mod split_import;
mod stitched;
mod transitions;
mod vod1;
mod voxelize;
mod web;
mod wide_labels;
