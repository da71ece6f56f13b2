//! The Isovox client library.
//!
//! It speaks only through the HTTP API and returns [`isovox_proto`] types. The HTTP calls, the
//! camera-distance streamer and the `isovox-load` binary come with the HTTP service; today the
//! crate re-exports the shared types so that client code and the server agree on one definition.

pub use isovox_proto as proto;
