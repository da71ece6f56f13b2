//! Progress of long jobs (builds, exports, compactions, meshing a level), told to whoever
//! watches: the command line draws a bar on a terminal; a server and the tests watch nothing.

/// Receives a job's progress. Called from several threads at once.
pub trait Progress: Send + Sync {
    /// The job has `total` steps.
    fn start(&self, total: u64) {
        let _ = total;
    }

    /// `steps` more steps are done.
    fn advance(&self, steps: u64) {
        let _ = steps;
    }

    /// The job is over (successfully or not).
    fn finish(&self) {}
}

/// Nobody watches.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {}
