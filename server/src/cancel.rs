//! Stopping long CPU work from outside: a flag that whoever gives up on the work raises (the
//! client left, the server is shutting down) and an optional deadline, both checked by the
//! work's loops between steps of bounded size. Checking costs an atomic load, plus a clock read
//! when there is a deadline, so loops check once per row or brick, not per voxel.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Why work was stopped before it finished.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Stopped {
    /// Someone gave up on the work: its client left, or the server is shutting down.
    #[error("the work was cancelled (its client left, or the server is shutting down)")]
    Cancelled,
    /// The work ran past its deadline.
    #[error("the work took longer than its limit of {0:?}")]
    TimedOut(Duration),
}

/// A shared stop signal with an optional deadline. Clones share the flag.
#[derive(Debug, Clone, Default)]
pub struct CancelToken {
    flag: Arc<AtomicBool>,
    deadline: Option<(Instant, Duration)>,
}

impl CancelToken {
    /// A token nobody cancels and without a deadline (the CLI, tests, benchmarks).
    pub fn never() -> CancelToken {
        CancelToken::default()
    }

    /// A token that also stops the work `limit` from now.
    pub fn with_timeout(limit: Duration) -> CancelToken {
        CancelToken {
            flag: Arc::default(),
            deadline: Some((Instant::now() + limit, limit)),
        }
    }

    /// The same flag with the deadline started again from now (the same limit): for the next
    /// phase of the work, so time spent waiting between phases does not count.
    pub fn restarted(&self) -> CancelToken {
        CancelToken {
            flag: self.flag.clone(),
            deadline: self
                .deadline
                .map(|(_, limit)| (Instant::now() + limit, limit)),
        }
    }

    /// When the work must stop, and the limit that deadline came from (`None`: no deadline).
    pub fn deadline(&self) -> Option<(Instant, Duration)> {
        self.deadline
    }

    /// Raises the flag: every holder's next [`CancelToken::check`] fails.
    pub fn cancel(&self) {
        self.flag.store(true, Ordering::Release);
    }

    /// Whether [`CancelToken::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.flag.load(Ordering::Acquire)
    }

    /// A guard that cancels this token when dropped: held by a request's future, so that the
    /// work it started off the async runtime stops when the future is dropped (the client
    /// disconnected, or the server closed the connection at shutdown).
    pub fn cancel_on_drop(&self) -> CancelOnDrop {
        CancelOnDrop(self.clone())
    }

    /// # Errors
    /// [`Stopped`] once the token is cancelled or its deadline has passed.
    #[inline]
    pub fn check(&self) -> Result<(), Stopped> {
        if self.flag.load(Ordering::Relaxed) {
            return Err(Stopped::Cancelled);
        }
        match self.deadline {
            Some((at, limit)) if Instant::now() >= at => Err(Stopped::TimedOut(limit)),
            _ => Ok(()),
        }
    }
}

/// Cancels its token when dropped (see [`CancelToken::cancel_on_drop`]).
#[derive(Debug)]
pub struct CancelOnDrop(CancelToken);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cancel_reaches_every_clone_and_the_deadline_passes() {
        let token = CancelToken::never();
        let clone = token.clone();
        assert_eq!(clone.check(), Ok(()));
        drop(token.cancel_on_drop());
        assert_eq!(clone.check(), Err(Stopped::Cancelled));

        let timed = CancelToken::with_timeout(Duration::from_millis(1));
        std::thread::sleep(Duration::from_millis(5));
        assert_eq!(
            timed.check(),
            Err(Stopped::TimedOut(Duration::from_millis(1)))
        );
    }
}
