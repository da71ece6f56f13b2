//! `Content-Encoding: zstd` for the responses that are built per request and compress well:
//! mesh tiles (the compact encoding's positions and indices shrink by about half), brick
//! batches, levels (grids and voxels) and change lists. Browsers send `Accept-Encoding: zstd`
//! and decode it themselves; other clients get the bytes as before.
//!
//! Compressing is CPU work, so it runs inside the job that built the body (`cpu.rs`), never on
//! the async runtime: a handler asks [`accepts_zstd`] before its job, and the job ends with
//! [`Body::new`]. (The job's runner then has the body hold its size of the response memory
//! budget until it is sent: `cpu.rs`, `held.rs`.) The change feed stays uncompressed (a compressor would hold its events back),
//! and bricks are not recompressed: the brick and blob routes already send a stored zstd frame
//! as it is (`bricks.rs`).

use super::held::Reservation;
use axum::http::{header, HeaderMap, HeaderValue};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;

/// Below this many bytes a body is sent as it is (the frame header would eat the gain).
const MIN_BYTES: usize = 512;

/// zstd's default level: about half the bytes of a mesh tile, at hundreds of MB/s.
const LEVEL: i32 = 3;

/// Whether the request's `Accept-Encoding` takes zstd.
pub(super) fn accepts_zstd(headers: &HeaderMap) -> bool {
    super::bricks::accepts(headers, header::ACCEPT_ENCODING, "zstd")
}

/// A response body, zstd-compressed when the client takes it and that makes it smaller.
#[derive(Debug)]
pub(super) struct Body {
    bytes: Vec<u8>,
    zstd: bool,
    held: Option<Reservation>,
}

impl Body {
    /// `bytes`, compressed when `zstd` (see [`accepts_zstd`]) and worth it. CPU work: call it
    /// in the job that made `bytes`.
    pub(super) fn new(bytes: Vec<u8>, zstd: bool) -> Body {
        if zstd && bytes.len() >= MIN_BYTES {
            if let Ok(packed) = zstd::bulk::compress(&bytes, LEVEL) {
                if packed.len() < bytes.len() {
                    return Body {
                        bytes: packed,
                        zstd: true,
                        held: None,
                    };
                }
            }
        }
        Body {
            bytes,
            zstd: false,
            held: None,
        }
    }

    /// Bytes of the body as sent.
    pub(super) fn len(&self) -> usize {
        self.bytes.len()
    }

    /// The body, holding `reservation` (of at least its length) until it has been sent.
    pub(super) fn hold(self, reservation: Reservation) -> Body {
        Body {
            held: Some(reservation),
            ..self
        }
    }

    /// `value` as JSON, as [`Body::new`].
    pub(super) fn json<T: serde::Serialize>(value: &T, zstd: bool) -> Body {
        // The API's types serialize without error (no maps with non-string keys, no failing
        // Serialize impls); an empty body would be the visible symptom of a bug here.
        Body::new(serde_json::to_vec(value).unwrap_or_default(), zstd)
    }

    /// The response: `headers` plus `Content-Type: media`, `Vary: Accept-Encoding` (caches must
    /// keep the two forms apart) and, when compressed, `Content-Encoding: zstd`.
    pub(super) fn respond(self, media: &'static str, mut headers: HeaderMap) -> Response {
        content_headers(&mut headers, media, self.zstd);
        match self.held {
            Some(held) => (headers, held.body(self.bytes)).into_response(),
            None => (headers, self.bytes).into_response(),
        }
    }

    /// A copy of the body to keep and send again ([`SharedBody`]).
    pub(super) fn share(&self) -> SharedBody {
        SharedBody {
            bytes: Bytes::copy_from_slice(&self.bytes),
            zstd: self.zstd,
        }
    }
}

/// A body kept to be sent again, as [`Body::new`] made it: each response shares its bytes.
#[derive(Debug)]
pub(super) struct SharedBody {
    bytes: Bytes,
    zstd: bool,
}

impl SharedBody {
    /// Bytes of the body as sent.
    pub(super) fn len(&self) -> usize {
        self.bytes.len()
    }

    /// The response, as [`Body::respond`] makes it.
    pub(super) fn respond(&self, media: &'static str, mut headers: HeaderMap) -> Response {
        content_headers(&mut headers, media, self.zstd);
        (headers, self.bytes.clone()).into_response()
    }
}

/// `Content-Type: media`, `Vary: Accept-Encoding` and, for a compressed body,
/// `Content-Encoding: zstd`.
fn content_headers(headers: &mut HeaderMap, media: &'static str, zstd: bool) {
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
    headers.insert(header::VARY, HeaderValue::from_static("Accept-Encoding"));
    if zstd {
        headers.insert(header::CONTENT_ENCODING, HeaderValue::from_static("zstd"));
    }
}
