//! `Content-Encoding: zstd` for the responses that are built per request and compress well:
//! mesh tiles (the compact encoding's positions and indices shrink by about half), brick
//! batches, level grids and change lists (JSON). Browsers send `Accept-Encoding: zstd` and
//! decode it themselves; other clients get the bytes as before.
//!
//! Bricks are not recompressed here: the brick and blob routes already send a stored zstd frame
//! as it is (`handlers::brick_response`), and compressing their raw bodies per request would
//! cost the brick routes' throughput for little. The layer wraps only the routes it helps
//! (`Router::route_layer` on them), so the brick fast path never passes through it.

use tower_http::compression::predicate::{NotForContentType, Predicate, SizeAbove};
use tower_http::compression::{CompressionLayer, CompressionLevel};

/// Below this many bytes a response is sent as it is (the frame header would eat the gain).
const MIN_BYTES: u16 = 512;

/// The compression layer for the routes that build their bodies per request.
pub(super) fn layer() -> CompressionLayer<impl Predicate> {
    CompressionLayer::new()
        .no_br()
        .no_deflate()
        .no_gzip()
        .quality(CompressionLevel::Default)
        .compress_when(
            SizeAbove::new(MIN_BYTES)
                // The change feed stays a stream (a compressor would hold its events back).
                .and(NotForContentType::const_new("text/event-stream")),
        )
}
