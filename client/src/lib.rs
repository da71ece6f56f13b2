//! The Isovox client library: typed calls for every route of the HTTP API, and a
//! camera-distance streamer that follows other users' edits. (The `isovox-load` load tester
//! built on it is in the `tools` package.)
//!
//! It speaks only through the HTTP API and returns [`isovox_proto`] types.
//!
//! Layout:
//! - [`client`]: [`Client`], one typed async call per route, retries with backoff, errors that
//!   carry the server's problem details; [`Feed`], the change feed (server-sent events).
//! - [`streamer`]: [`Streamer`], the tiles (bricks or meshes) a camera needs, level k within
//!   radius r_k, nearest first, kept fresh as edits arrive.

#![warn(missing_docs)]

pub mod client;
pub mod streamer;

pub use client::{Brick, Client, ClientError, Feed, FeedEvent, Observer, RetryPolicy};
pub use isovox_proto as proto;
pub use streamer::{
    select_stitched_tiles, select_tiles, MeshTile, StreamEvent, Streamer, StreamerConfig,
    StreamerStats, TileData, TileKind,
};
