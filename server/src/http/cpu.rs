//! CPU work off the async runtime: decoding many bricks, meshing, reading levels and change
//! lists run on threads of their own, never on tokio's workers, so a slow request does not hold
//! up the brick routes.
//!
//! Three bounds keep that work from growing with the load:
//! - places: jobs running or waiting for a thread. When all are taken, a request gets 503 with
//!   Retry-After at once rather than waiting in a queue without bound; the default scales with
//!   the cores, so a full queue is worked off in a few hundred milliseconds
//!   ([`default_queue`]).
//! - threads: jobs run on a fixed set of threads, one per core by default, in the order they
//!   came. (On tokio's blocking pool every job took a thread of its own, and a thread that
//!   had just finished one was often not yet idle when the next came, so the pool grew to its
//!   limit of 512 threads, each keeping its own allocator caches: gigabytes.)
//! - memory: the bodies jobs build hold their size of the response budget until they are sent
//!   (`held.rs`).
//!
//! Reads of volumes kept in an object store have a pool of their own ([`StoreReads`]): such a
//! read may fetch pages from the store and wait for them, which no connection thread may do
//! (one waiting connection thread stalls all its connections), and which should not take the
//! CPU threads from CPU work. Handlers run a volume's reads through
//! [`AppState::read_volume`](super::AppState::read_volume): in place for a local volume
//! (mapped memory: nothing to wait for), on that pool for a remote one.

use super::compression::Body;
use super::held::ResponseMemory;
use super::ApiError;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{mpsc, Arc, Mutex, OnceLock};
use tokio::sync::{oneshot, Semaphore};

/// Places per core by default: a full queue holds about this many jobs per thread.
const PLACES_PER_CORE: usize = 8;

/// Store-read threads per core by default: their reads mostly wait on the network (a cold
/// read is one store round trip), so several per core keep several fetches in flight.
const STORE_READ_THREADS_PER_CORE: usize = 8;

/// Store reads running or waiting per store-read thread by default: a read that finds its
/// pages cached takes microseconds, one that fetches them a round trip to the store, so a
/// full queue waits a few round trips.
const STORE_READ_PLACES_PER_THREAD: usize = 8;

/// The cores this process may use.
pub fn cores() -> usize {
    std::thread::available_parallelism().map_or(2, usize::from)
}

/// The default number of places: [`PLACES_PER_CORE`] per core. A cold mesh tile of a large
/// world takes tens of milliseconds of one core, so a full queue waits a few hundred
/// milliseconds at most; a much longer queue lets the 99th percentile grow to seconds before
/// the first 503 tells a client to back off.
pub fn default_queue() -> usize {
    PLACES_PER_CORE * cores()
}

/// The default number of store-read threads ([`StoreReads`]).
pub fn default_store_read_threads() -> usize {
    STORE_READ_THREADS_PER_CORE * cores()
}

/// The default number of store-read places ([`StoreReads`]).
pub fn default_store_read_queue() -> usize {
    STORE_READ_PLACES_PER_THREAD * default_store_read_threads()
}

/// How a job gets to the CPU threads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Admission {
    /// With one of the queue's places, held until the job is done; 503 at once when every
    /// place is taken.
    Place,
    /// With one of the queue's places, waiting up to this long for one; 503 after. For jobs
    /// far smaller than the queue is sized for (a view's chunk to compress: a fraction of a
    /// millisecond, where a mesh tile takes 10-50 ms), which clients ask for in bursts: a
    /// burst of them waits moments for places instead of being refused.
    WaitFor(std::time::Duration),
    /// Without a place: the job waits for a thread however long the queue is. For work another
    /// bound already limits (a change feed reads its backlog one page at a time, one page per
    /// subscriber).
    Wait,
}

/// The bound on CPU work (meshing, batches, levels, change lists) and on the memory of what it
/// answers; see the module documentation.
#[derive(Debug)]
pub struct CpuQueue {
    places: Arc<Semaphore>,
    size: usize,
    pool: Pool,
    /// The memory of the bodies jobs build, until they are sent.
    pub memory: ResponseMemory,
}

impl CpuQueue {
    /// Room for `size` jobs running or waiting, `threads` running at once, and `memory` bytes
    /// of response bodies.
    pub fn new(size: usize, threads: usize, memory: usize) -> Self {
        CpuQueue {
            places: Arc::new(Semaphore::new(size)),
            size,
            pool: Pool::new(threads.max(1), "isovox-cpu"),
            memory: ResponseMemory::new(memory),
        }
    }

    /// Jobs running or waiting now.
    pub fn depth(&self) -> usize {
        self.size - self.places.available_permits()
    }

    /// Runs `work` on the CPU threads, admitted as `admission` says.
    ///
    /// # Errors
    /// 503 when `admission` needs a place and the queue is full (for [`Admission::WaitFor`]:
    /// stays full that long); whatever `work` fails with;
    /// 500 if it panicked.
    pub async fn run<T, E>(
        &self,
        admission: Admission,
        work: impl FnOnce() -> Result<T, E> + Send + 'static,
    ) -> Result<T, ApiError>
    where
        T: Send + 'static,
        E: Send + 'static,
        ApiError: From<E>,
    {
        let place = match admission {
            Admission::Place => Some(
                self.places
                    .clone()
                    .try_acquire_owned()
                    .map_err(|_| ApiError::Overloaded(1))?,
            ),
            Admission::WaitFor(patience) => Some(
                tokio::time::timeout(patience, self.places.clone().acquire_owned())
                    .await
                    .ok()
                    .and_then(Result::ok)
                    .ok_or(ApiError::Overloaded(1))?,
            ),
            Admission::Wait => None,
        };
        // The place is held until the job is done, or dropped with it when it is skipped.
        let done = self.pool.run(move || {
            let _place = place;
            work()
        });
        match done.await? {
            Ok(done) => Ok(done?),
            Err(panic) => Err(ApiError::Internal(format!(
                "a CPU job panicked: {}",
                panic_message(&*panic)
            ))),
        }
    }

    /// Runs `work`, which builds a response body, with a place in the queue
    /// ([`Admission::Place`]) and `reserve` bytes of the response budget set aside first (what
    /// the body will take, when that is known beforehand; 0 otherwise). The body holds its
    /// exact size of the budget until it has been sent.
    ///
    /// # Errors
    /// As [`CpuQueue::run`]; 503 when the budget cannot hold the body now, 413 when it never
    /// could.
    pub(super) async fn answer<E>(
        &self,
        reserve: usize,
        work: impl FnOnce() -> Result<Body, E> + Send + 'static,
    ) -> Result<Body, ApiError>
    where
        E: Send + 'static,
        ApiError: From<E>,
    {
        let mut reservation = self.memory.reserve(reserve)?;
        let body = self.run(Admission::Place, work).await?;
        reservation.fit(&self.memory, body.len())?;
        Ok(body.hold(reservation))
    }
}

/// The bound on reads of volumes kept in an object store, which may wait on the network: a
/// pool of threads of their own (`isovox-store-read-{i}`, started at the first such read) and
/// places, taken by reads running or waiting for a thread; when every place is taken a read is
/// refused at once (503 with Retry-After). See the module documentation.
#[derive(Debug)]
pub struct StoreReads {
    places: Arc<Semaphore>,
    size: usize,
    threads: usize,
    pool: OnceLock<Pool>,
}

impl StoreReads {
    /// Room for `size` reads running or waiting, `threads` running at once.
    pub fn new(size: usize, threads: usize) -> Self {
        StoreReads {
            places: Arc::new(Semaphore::new(size)),
            size,
            threads: threads.max(1),
            pool: OnceLock::new(),
        }
    }

    /// Reads running or waiting now.
    pub fn depth(&self) -> usize {
        self.size - self.places.available_permits()
    }

    /// Runs `read` on the store-read threads, with a place. A read whose caller has gone
    /// before a thread took it is skipped, and its place freed. A read that panics unwinds
    /// where it is awaited, as it would have run in place (a local volume's read).
    ///
    /// # Errors
    /// 503 when every place is taken; whatever `read` fails with.
    pub async fn run<T, E>(
        &self,
        read: impl FnOnce() -> Result<T, E> + Send + 'static,
    ) -> Result<T, ApiError>
    where
        T: Send + 'static,
        E: Send + 'static,
        ApiError: From<E>,
    {
        let place = self
            .places
            .clone()
            .try_acquire_owned()
            .map_err(|_| ApiError::Overloaded(1))?;
        let pool = self
            .pool
            .get_or_init(|| Pool::new(self.threads, "isovox-store-read"));
        let done = pool.run(move || {
            let _place = place;
            read()
        });
        match done.await? {
            Ok(done) => Ok(done?),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    }
}

type Job = Box<dyn FnOnce() + Send>;

/// Threads that take jobs from one channel, in the order they were sent.
#[derive(Debug)]
struct Pool {
    jobs: mpsc::Sender<Job>,
}

impl Pool {
    /// `threads` threads named `{name}-{i}`; they end when the pool is dropped.
    fn new(threads: usize, name: &str) -> Pool {
        let (jobs, queue) = mpsc::channel::<Job>();
        let queue = Arc::new(Mutex::new(queue));
        for i in 0..threads {
            let queue = queue.clone();
            let started = std::thread::Builder::new()
                .name(format!("{name}-{i}"))
                .spawn(move || loop {
                    // Jobs catch their own panics, so the lock is never poisoned; should it
                    // be, this thread ends like the others do when the pool is dropped.
                    let job = match queue.lock() {
                        Ok(queue) => queue.recv(),
                        Err(_) => return,
                    };
                    match job {
                        Ok(job) => job(),
                        Err(mpsc::RecvError) => return,
                    }
                });
            // Without any thread, the queue's receiver is gone and jobs fail with a 500.
            if let Err(e) = started {
                tracing::error!("cannot start thread {name}-{i}: {e}");
            }
        }
        Pool { jobs }
    }

    /// `work`'s result, or its panic, computed on one of the pool's threads. A job whose
    /// caller has gone (the client left, the route timed out) before a thread took it is
    /// skipped.
    async fn run<T: Send + 'static>(
        &self,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> Result<std::thread::Result<T>, ApiError> {
        let (tx, rx) = oneshot::channel();
        let job: Job = Box::new(move || {
            if !tx.is_closed() {
                let _ = tx.send(catch_unwind(AssertUnwindSafe(work)));
            }
        });
        self.jobs
            .send(job)
            .map_err(|_| ApiError::Internal("no thread of the pool is running".into()))?;
        rx.await
            .map_err(|_| ApiError::Internal("a job of a pool was dropped".into()))
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Runs `work` on the blocking pool of `runtime`, the server's main runtime
/// ([`super::AppState::main_runtime`]; never a connection thread's: each has one, and a
/// connection runtime waits for its blocking tasks without a limit when it stops), without a
/// place in the [`CpuQueue`]: for work another bound already limits and that may wait on I/O
/// or on a lock (edits wait in their volume's writer queue; a compaction holds the writer; a
/// mesh upload needs a write token).
///
/// # Errors
/// Whatever `work` fails with; 500 if it panicked.
pub async fn blocking<T, E>(
    runtime: tokio::runtime::Handle,
    work: impl FnOnce() -> Result<T, E> + Send + 'static,
) -> Result<T, ApiError>
where
    T: Send + 'static,
    E: Send + 'static,
    ApiError: From<E>,
{
    Ok(runtime.spawn_blocking(work).await??)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    #[tokio::test]
    async fn jobs_run_on_the_pools_threads_only() {
        let queue = Arc::new(CpuQueue::new(64, 2, 1 << 20));
        let (running, most) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
        let mut jobs = Vec::new();
        for _ in 0..64 {
            let (queue, running, most) = (queue.clone(), running.clone(), most.clone());
            jobs.push(tokio::spawn(async move {
                queue
                    .run(Admission::Place, move || {
                        let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                        most.fetch_max(now, Ordering::SeqCst);
                        std::thread::sleep(Duration::from_millis(2));
                        running.fetch_sub(1, Ordering::SeqCst);
                        let name = std::thread::current().name().map(str::to_owned);
                        Ok::<_, ApiError>(name)
                    })
                    .await
            }));
        }
        for job in jobs {
            let name = job.await.unwrap().unwrap().unwrap();
            assert!(name.starts_with("isovox-cpu-"), "{name}");
        }
        assert!(most.load(Ordering::SeqCst) <= 2);
        assert_eq!(queue.depth(), 0);
    }

    /// Fills the one place of `queue` with a job that runs until the returned sender sends;
    /// checks that a job needing a place is then refused.
    async fn fill_the_one_place(
        queue: &Arc<CpuQueue>,
    ) -> (
        std::sync::mpsc::Sender<()>,
        tokio::task::JoinHandle<Result<bool, ApiError>>,
    ) {
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let holder = {
            let queue = queue.clone();
            tokio::spawn(async move {
                queue
                    .run(Admission::Place, move || {
                        Ok::<_, ApiError>(wait.recv().is_ok())
                    })
                    .await
            })
        };
        while queue.depth() == 0 {
            tokio::task::yield_now().await;
        }
        let refused = queue.run(Admission::Place, || Ok::<_, ApiError>(())).await;
        assert!(
            matches!(refused, Err(ApiError::Overloaded(1))),
            "{refused:?}"
        );
        (release, holder)
    }

    #[tokio::test]
    async fn a_full_queue_answers_503_and_a_panic_500() {
        let queue = Arc::new(CpuQueue::new(1, 1, 1 << 20));
        let (release, holder) = fill_the_one_place(&queue).await;
        release.send(()).unwrap();
        assert!(holder.await.unwrap().unwrap());
        let panicked = queue
            .run(Admission::Place, || -> Result<(), ApiError> {
                panic!("on purpose")
            })
            .await;
        assert!(
            matches!(&panicked, Err(ApiError::Internal(m)) if m.contains("on purpose")),
            "{panicked:?}"
        );
        // The thread survived its job's panic.
        assert_eq!(
            queue
                .run(Admission::Place, || Ok::<_, ApiError>(7))
                .await
                .unwrap(),
            7
        );
    }

    #[tokio::test]
    async fn a_job_without_a_place_runs_while_the_queue_is_full() {
        let queue = Arc::new(CpuQueue::new(1, 2, 1 << 20));
        let (release, holder) = fill_the_one_place(&queue).await;
        // The queue is full, the other thread free: a job without a place runs, and takes none.
        let ran = queue.run(Admission::Wait, || Ok::<_, ApiError>(8));
        assert_eq!(ran.await.unwrap(), 8);
        assert_eq!(queue.depth(), 1);
        release.send(()).unwrap();
        assert!(holder.await.unwrap().unwrap());
        assert_eq!(queue.depth(), 0);
    }

    #[tokio::test]
    async fn a_patient_job_waits_for_a_place_within_its_patience_only() {
        let queue = Arc::new(CpuQueue::new(1, 2, 1 << 20));
        let (release, holder) = fill_the_one_place(&queue).await;
        // No place frees within the patience: refused.
        let refused = queue
            .run(Admission::WaitFor(Duration::from_millis(50)), || {
                Ok::<_, ApiError>(())
            })
            .await;
        assert!(
            matches!(refused, Err(ApiError::Overloaded(1))),
            "{refused:?}"
        );
        // A place frees while it waits: it runs, in that place.
        let patient = {
            let queue = queue.clone();
            tokio::spawn(async move {
                queue
                    .run(Admission::WaitFor(Duration::from_secs(30)), || {
                        Ok::<_, ApiError>(9)
                    })
                    .await
            })
        };
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!patient.is_finished());
        release.send(()).unwrap();
        assert!(holder.await.unwrap().unwrap());
        assert_eq!(patient.await.unwrap().unwrap(), 9);
        assert_eq!(queue.depth(), 0);
    }

    /// A store read that holds the one thread of `reads` until the returned sender sends.
    async fn hold_the_thread(
        reads: &Arc<StoreReads>,
    ) -> (
        std::sync::mpsc::Sender<()>,
        tokio::task::JoinHandle<Result<String, ApiError>>,
    ) {
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let (started, running) = tokio::sync::oneshot::channel();
        let holder = {
            let reads = reads.clone();
            tokio::spawn(async move {
                reads
                    .run(move || {
                        let _ = started.send(());
                        let _ = wait.recv();
                        let name = std::thread::current().name().map(str::to_owned);
                        Ok::<_, ApiError>(name.unwrap_or_default())
                    })
                    .await
            })
        };
        running.await.unwrap();
        (release, holder)
    }

    #[tokio::test]
    async fn store_reads_run_on_their_threads_and_a_full_pool_answers_503() {
        let reads = Arc::new(StoreReads::new(2, 1));
        let (release, holder) = hold_the_thread(&reads).await;
        // One place left: a second read waits for the thread, a third is refused.
        let waiting = {
            let reads = reads.clone();
            tokio::spawn(async move { reads.run(|| Ok::<_, ApiError>(5)).await })
        };
        while reads.depth() < 2 {
            tokio::task::yield_now().await;
        }
        let refused = reads.run(|| Ok::<_, ApiError>(6)).await;
        assert!(
            matches!(refused, Err(ApiError::Overloaded(1))),
            "{refused:?}"
        );
        release.send(()).unwrap();
        let name = holder.await.unwrap().unwrap();
        assert!(name.starts_with("isovox-store-read-"), "{name}");
        assert_eq!(waiting.await.unwrap().unwrap(), 5);
        assert_eq!(reads.depth(), 0);
    }

    /// What replaced the routed requests of remote volumes (`fast_path.rs` ran them as tasks
    /// of the main runtime, aborted with their response): a read whose response is no longer
    /// awaited (its connection closed) is not run, and gives its place back.
    #[tokio::test]
    async fn a_store_read_is_cancelled_with_its_response() {
        let reads = Arc::new(StoreReads::new(4, 1));
        let (release, holder) = hold_the_thread(&reads).await;
        let ran = Arc::new(AtomicUsize::new(0));
        // Queued behind the held thread, then dropped, as a request is when its client goes.
        let answer = {
            let (reads, ran) = (reads.clone(), ran.clone());
            tokio::spawn(async move {
                reads
                    .run(move || {
                        ran.fetch_add(1, Ordering::SeqCst);
                        Ok::<_, ApiError>(())
                    })
                    .await
            })
        };
        while reads.depth() < 2 {
            tokio::task::yield_now().await;
        }
        answer.abort();
        assert!(answer.await.unwrap_err().is_cancelled());
        release.send(()).unwrap();
        holder.await.unwrap().unwrap();
        // The thread has taken (and skipped) the dropped read once this one has run.
        assert_eq!(reads.run(|| Ok::<_, ApiError>(1)).await.unwrap(), 1);
        assert_eq!(ran.load(Ordering::SeqCst), 0, "a dropped read ran");
        assert_eq!(reads.depth(), 0);
    }

    /// A read of a remote volume that panics unwinds the task awaiting it, as a local volume's
    /// read (run in place) does, and as the routed requests of remote volumes did.
    #[tokio::test]
    async fn a_store_reads_panic_unwinds_where_it_is_awaited() {
        let reads = Arc::new(StoreReads::new(4, 1));
        let answer = {
            let reads = reads.clone();
            tokio::spawn(async move {
                reads
                    .run(|| -> Result<(), ApiError> { panic!("on purpose") })
                    .await
            })
        };
        let awaited = answer.await.unwrap_err();
        assert!(awaited.is_panic());
        let panic = awaited.into_panic();
        assert_eq!(panic.downcast_ref::<&str>(), Some(&"on purpose"));
        // The thread survived it, and the place was given back.
        assert_eq!(reads.run(|| Ok::<_, ApiError>(2)).await.unwrap(), 2);
        assert_eq!(reads.depth(), 0);
    }
}
