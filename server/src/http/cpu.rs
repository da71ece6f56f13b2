//! CPU work off the async runtime: decoding many bricks, meshing, compiling and applying edits
//! run on the blocking pool, never on tokio's workers, so a slow request does not hold up the
//! brick routes.

use super::ApiError;
use std::sync::Arc;
use tokio::sync::Semaphore;

/// A bound on the CPU work (meshing, batches, levels) running or queued at once: when it is
/// reached, a request gets 503 with Retry-After at once instead of waiting in a queue without
/// bound.
#[derive(Debug)]
pub struct CpuQueue {
    permits: Arc<Semaphore>,
    size: usize,
}

impl CpuQueue {
    /// Room for `size` jobs.
    pub fn new(size: usize) -> Self {
        CpuQueue {
            permits: Arc::new(Semaphore::new(size)),
            size,
        }
    }

    /// Jobs running or queued now.
    pub fn depth(&self) -> usize {
        self.size - self.permits.available_permits()
    }

    /// Runs `work` on the blocking pool, holding one of the queue's places until it is done.
    ///
    /// # Errors
    /// 503 when the queue is full; whatever `work` fails with.
    pub async fn run<T, E>(
        &self,
        work: impl FnOnce() -> Result<T, E> + Send + 'static,
    ) -> Result<T, ApiError>
    where
        T: Send + 'static,
        E: Send + 'static,
        ApiError: From<E>,
    {
        let permit = self
            .permits
            .clone()
            .try_acquire_owned()
            .map_err(|_| ApiError::Overloaded(1))?;
        blocking(move || {
            let _permit = permit;
            work()
        })
        .await
    }
}

/// Runs `work` on the blocking pool without a place in the [`CpuQueue`]: for work another
/// bound already limits (edits wait in their volume's writer queue; a compaction holds the
/// writer; a feed reads its backlog one page at a time).
///
/// # Errors
/// Whatever `work` fails with; 500 if it panicked.
pub async fn blocking<T, E>(
    work: impl FnOnce() -> Result<T, E> + Send + 'static,
) -> Result<T, ApiError>
where
    T: Send + 'static,
    E: Send + 'static,
    ApiError: From<E>,
{
    Ok(tokio::task::spawn_blocking(work).await??)
}
