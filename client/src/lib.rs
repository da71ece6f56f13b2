//! The Isovox client library: typed calls for every route of the HTTP API, a camera-distance
//! streamer that follows other users' edits, and the `isovox-load` load tester.
//!
//! It speaks only through the HTTP API and returns [`isovox_proto`] types.
//!
//! Layout:
//! - [`client`]: [`Client`], one typed async call per route, retries with backoff, errors that
//!   carry the server's problem details; [`Feed`], the change feed (server-sent events).

pub mod client;
pub mod streamer;

pub use client::{Brick, Client, ClientError, Feed, FeedEvent, Observer, RetryPolicy};
pub use isovox_proto as proto;
pub use streamer::{
    select_tiles, StreamEvent, Streamer, StreamerConfig, StreamerStats, TileData, TileKind,
};

pub mod load;
