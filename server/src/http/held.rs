//! The memory of the responses CPU jobs build (levels, batches, mesh tiles, change lists),
//! bounded by one budget of bytes.
//!
//! A body is built whole in memory (up to 64 MiB for a level's voxels) and then sent as fast as
//! the client reads. Were its memory released when the job ends, clients that read slowly would
//! each keep a body alive, and memory would grow with their number. So a body holds its size of
//! the [`ResponseMemory`] budget until its last byte has left for the socket: the reservation
//! travels inside the body's bytes ([`Bytes::from_owner`]) and returns to the budget when hyper
//! drops them. A job reserves what its answer will take before it starts when that is known
//! (a level's voxels, a batch), and its answer's exact size when it ends; a request that does
//! not fit now gets 503 with Retry-After, one larger than the whole budget 413.

use super::ApiError;
use bytes::{Buf, Bytes};
use hyper::body::{Body as HttpBody, Frame, SizeHint};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The budget is counted in KiB: a semaphore takes at most 2^32 permits at once.
const UNIT: usize = 1024;

/// A body is handed to hyper in frames of at most this many bytes, so that the response stays
/// in progress (and its connection busy, see `connections.rs`) until its last frame is taken.
const FRAME: usize = 256 << 10;

/// Bytes of response bodies that may be held at once (see the module documentation).
#[derive(Debug)]
pub struct ResponseMemory {
    units: Arc<Semaphore>,
    total: usize,
}

impl ResponseMemory {
    /// A budget of `bytes` (at least one KiB).
    pub fn new(bytes: usize) -> Self {
        let total = bytes.div_ceil(UNIT).clamp(1, Semaphore::MAX_PERMITS);
        ResponseMemory {
            units: Arc::new(Semaphore::new(total)),
            total,
        }
    }

    /// Bytes held by bodies now (and reserved by jobs running or waiting).
    pub fn held(&self) -> usize {
        (self.total - self.units.available_permits()) * UNIT
    }

    /// Reserves `bytes` for an answer.
    ///
    /// # Errors
    /// 413 when `bytes` exceed the whole budget; 503 when the budget cannot hold them now.
    pub fn reserve(&self, bytes: usize) -> Result<Reservation, ApiError> {
        let permit = self.take(bytes.div_ceil(UNIT))?;
        Ok(Reservation { permit })
    }

    fn take(&self, units: usize) -> Result<OwnedSemaphorePermit, ApiError> {
        if units > self.total {
            return Err(ApiError::TooLarge(format!(
                "the answer needs {} MiB; this server holds at most {} MiB of answers at once (serve --response-memory-mb)",
                (units * UNIT).div_ceil(1 << 20),
                (self.total * UNIT) >> 20
            )));
        }
        let units = u32::try_from(units).map_err(|_| ApiError::Overloaded(1))?;
        self.units
            .clone()
            .try_acquire_many_owned(units)
            .map_err(|_| ApiError::Overloaded(1))
    }
}

/// A part of the [`ResponseMemory`] budget, returned when dropped.
#[derive(Debug)]
pub struct Reservation {
    permit: OwnedSemaphorePermit,
}

impl Reservation {
    /// Makes the reservation exactly `bytes` (rounded up to a KiB): the excess goes back to the
    /// budget, a shortfall is taken from it.
    ///
    /// # Errors
    /// As [`ResponseMemory::reserve`], for the shortfall.
    pub fn fit(&mut self, budget: &ResponseMemory, bytes: usize) -> Result<(), ApiError> {
        let (want, have) = (bytes.div_ceil(UNIT), self.permit.num_permits());
        if want < have {
            drop(self.permit.split(have - want));
        } else if want > have {
            self.permit.merge(budget.take(want - have)?);
        }
        Ok(())
    }

    /// `bytes` as a response body that holds this reservation until hyper has dropped the
    /// last of them.
    pub fn body(self, bytes: Vec<u8>) -> axum::body::Body {
        axum::body::Body::new(Frames(Bytes::from_owner(Held {
            bytes,
            _reservation: self,
        })))
    }
}

/// A body's bytes and the reservation they hold.
struct Held {
    bytes: Vec<u8>,
    _reservation: Reservation,
}

impl AsRef<[u8]> for Held {
    fn as_ref(&self) -> &[u8] {
        &self.bytes
    }
}

/// Bytes sent in frames of at most [`FRAME`] bytes (slices of one buffer, not copies).
struct Frames(Bytes);

impl HttpBody for Frames {
    type Data = Bytes;
    type Error = std::convert::Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        _: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        if self.0.is_empty() {
            return Poll::Ready(None);
        }
        let n = self.0.len().min(FRAME);
        let frame = self.0.split_to(n);
        Poll::Ready(Some(Ok(Frame::data(frame))))
    }

    fn is_end_stream(&self) -> bool {
        !self.0.has_remaining()
    }

    fn size_hint(&self) -> SizeHint {
        SizeHint::with_exact(self.0.len() as u64)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn reservations_are_counted_against_the_budget() {
        let budget = ResponseMemory::new(1 << 20);
        let mut r = budget.reserve(600 << 10).unwrap();
        assert_eq!(budget.held(), 600 << 10);
        r.fit(&budget, 700 << 10).unwrap();
        assert_eq!(budget.held(), 700 << 10);
        // 324 KiB are left: 400 do not fit now (503), 2 MiB never (413).
        assert!(matches!(
            budget.reserve(400 << 10),
            Err(ApiError::Overloaded(_))
        ));
        assert!(matches!(
            budget.reserve(2 << 20),
            Err(ApiError::TooLarge(_))
        ));
        r.fit(&budget, 100 << 10).unwrap();
        assert_eq!(budget.held(), 100 << 10);
        let other = budget.reserve(400 << 10).unwrap();
        assert_eq!(budget.held(), 500 << 10);
        drop((r, other));
        assert_eq!(budget.held(), 0);
    }

    #[tokio::test]
    async fn a_body_holds_its_reservation_until_its_last_bytes_are_dropped() {
        let budget = ResponseMemory::new(4 << 20);
        let bytes: Vec<u8> = (0..(700u32 << 10)).map(|i| (i % 251) as u8).collect();
        let mut body = budget.reserve(bytes.len()).unwrap().body(bytes.clone());
        assert_eq!(body.size_hint().exact(), Some(bytes.len() as u64));
        let mut frames = Vec::new();
        while let Some(frame) = std::future::poll_fn(|cx| Pin::new(&mut body).poll_frame(cx)).await
        {
            let data = frame.unwrap().into_data().unwrap();
            assert!(!data.is_empty() && data.len() <= FRAME, "{}", data.len());
            frames.push(data);
        }
        assert_eq!(frames.concat(), bytes);
        drop(body);
        // The last frames may still be on their way to the socket: the buffer is still held.
        assert_eq!(budget.held(), 700 << 10);
        drop(frames);
        assert_eq!(budget.held(), 0);
    }
}
