//! The object store as the storage engine calls it: blocking calls (the engine's reads are
//! synchronous, from request handlers, rayon and the blocking pool) carried out on a small
//! runtime of their own, so a call works from any thread, inside or outside tokio.

use super::super::StoreError;
use bytes::Bytes;
use object_store::path::Path as ObjectPath;
use object_store::{GetOptions, ObjectStore, PutMode, PutOptions, PutPayload, UpdateVersion};
use std::cell::Cell;
use std::future::Future;
use std::ops::Range;
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant, SystemTime};

/// A place in an object store: a bucket and a key prefix (`s3://bucket/prefix`).
#[derive(Debug, Clone)]
pub struct Bucket {
    store: Arc<dyn ObjectStore>,
    prefix: String,
    url: String,
}

/// An object's listing entry.
#[derive(Debug, Clone)]
pub struct Listed {
    /// Its key below the bucket's prefix.
    pub key: String,
    /// When it was last written.
    pub modified: SystemTime,
}

/// What a conditional read or write found.
#[derive(Debug)]
pub enum Conditional<T> {
    /// Done (or read): the object's new (or current) ETag, and what was read.
    Done(T, String),
    /// The condition did not hold: on a read, unchanged since the ETag given; on a write,
    /// another writer changed (or created) the object first.
    Refused,
}

/// The default size of an object above which it goes up as a multipart upload, and of each
/// part: large enough that a volume of a few GB takes tens of requests, small enough that a
/// part lost to a broken connection is cheap to send again.
pub const MULTIPART_DEFAULT_BYTES: u64 = 64 << 20;

/// The smallest part S3 accepts (but for the last one).
pub const MULTIPART_MIN_BYTES: u64 = 5 << 20;

/// Parts of one multipart upload sent at once (memory: this many parts).
pub const MULTIPART_IN_FLIGHT: usize = 4;

/// The multipart threshold and part size: `ISOVOX_MULTIPART_BYTES` if set (tests use a small
/// one), else [`MULTIPART_DEFAULT_BYTES`]; never below [`MULTIPART_MIN_BYTES`].
///
/// # Errors
/// The variable is set to something other than a number of bytes.
pub fn multipart_part_bytes() -> Result<u64, StoreError> {
    let bytes = match std::env::var("ISOVOX_MULTIPART_BYTES") {
        Err(_) => MULTIPART_DEFAULT_BYTES,
        Ok(v) => v.trim().parse::<u64>().map_err(|_| {
            StoreError::BadInput(format!(
                "ISOVOX_MULTIPART_BYTES={v:?}: the multipart threshold is a number of bytes"
            ))
        })?,
    };
    Ok(bytes.max(MULTIPART_MIN_BYTES))
}

/// The runtime that carries out store calls (two workers: the calls are network waits).
fn io_runtime() -> Result<&'static tokio::runtime::Runtime, StoreError> {
    static RUNTIME: OnceLock<Result<tokio::runtime::Runtime, String>> = OnceLock::new();
    RUNTIME
        .get_or_init(|| {
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .thread_name("isovox-store-io")
                .enable_all()
                .build()
                .map_err(|e| e.to_string())
        })
        .as_ref()
        .map_err(|e| StoreError::Internal(format!("cannot start the store's runtime: {e}")))
}

thread_local! {
    /// The deadline of the work this thread does for (an edit), and its limit: store calls
    /// made on this thread are given up then. See [`bound_store_waits`].
    static DEADLINE: Cell<Option<(Instant, Duration)>> = const { Cell::new(None) };
}

/// Until the guard is dropped, store calls made on this thread wait no later than `deadline`
/// (`None`: as long as the store takes), then fail with [`StoreError::Stalled`].
///
/// An edit's evaluation checks its deadline between bricks, but a store call that stalls (the
/// store stopped answering) never returns to a check: without this the edit waited out the
/// client's retries (minutes), and the check that followed called the store's stall the edit's
/// own cost (422). A call given up this way keeps running on the store's runtime and its
/// answer is dropped.
pub fn bound_store_waits(deadline: Option<(Instant, Duration)>) -> StoreWaitBound {
    StoreWaitBound(DEADLINE.replace(deadline))
}

/// Restores the thread's previous bound when dropped (see [`bound_store_waits`]).
#[derive(Debug)]
pub struct StoreWaitBound(Option<(Instant, Duration)>);

impl Drop for StoreWaitBound {
    fn drop(&mut self) {
        DEADLINE.set(self.0);
    }
}

/// Runs `fut` on the store's runtime and blocks this thread until it is done, or until this
/// thread's deadline if it has one ([`bound_store_waits`]). Callers are threads that may wait:
/// the server's store-read, CPU, blocking and rayon threads, never an async runtime's worker (a
/// connection thread serves all its connections on one thread, and would stall them all for the
/// round trip: debug builds check it).
fn wait<T: Send + 'static>(fut: impl Future<Output = T> + Send + 'static) -> Result<T, StoreError> {
    debug_assert!(
        !std::thread::current()
            .name()
            .is_some_and(|n| n.starts_with("isovox-conn-")),
        "a store call on a connection thread: read remote volumes through AppState::read_volume"
    );
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    io_runtime()?.spawn(async move {
        let _ = tx.send(fut.await);
    });
    let got = match DEADLINE.get() {
        None => rx.recv().map_err(|_| None),
        Some((at, limit)) => rx
            .recv_timeout(at.saturating_duration_since(Instant::now()))
            .map_err(|e| match e {
                std::sync::mpsc::RecvTimeoutError::Timeout => Some(limit),
                std::sync::mpsc::RecvTimeoutError::Disconnected => None,
            }),
    };
    got.map_err(|stalled| match stalled {
        Some(limit) => StoreError::Stalled { limit },
        None => StoreError::Internal("a store call was dropped unfinished".into()),
    })
}

fn failed(what: String) -> impl FnOnce(object_store::Error) -> StoreError {
    move |source| StoreError::ObjectStore {
        context: what,
        source: Box::new(source),
    }
}

impl Bucket {
    /// The bucket of an `s3://bucket/prefix` URL. Endpoint, region and credentials come from
    /// the `AWS_*` environment variables (`AWS_ENDPOINT`, `AWS_ACCESS_KEY_ID`,
    /// `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ALLOW_HTTP` for a plain-HTTP endpoint, ...).
    ///
    /// # Errors
    /// The URL is not `s3://bucket[/prefix]`, or the configuration is incomplete.
    pub fn from_url(url: &str) -> Result<Bucket, StoreError> {
        Self::from_url_at(url, None)
    }

    /// [`Bucket::from_url`] with the endpoint given here rather than by `AWS_ENDPOINT` (several
    /// stores in one process: tests, tools).
    ///
    /// # Errors
    /// See [`Bucket::from_url`].
    pub fn from_url_at(url: &str, endpoint: Option<&str>) -> Result<Bucket, StoreError> {
        let rest = url.strip_prefix("s3://").ok_or_else(|| {
            StoreError::BadInput(format!("{url}: a store is named s3://bucket/prefix"))
        })?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let prefix = prefix.trim_matches('/');
        if bucket.is_empty() || prefix.split('/').any(|p| p == "." || p == "..") {
            return Err(StoreError::BadInput(format!(
                "{url}: a store is named s3://bucket/prefix"
            )));
        }
        // TLS (for https endpoints) runs on rustls with ring, as the HTTPS listener does.
        crate::client_tls::install_provider();
        let mut builder = object_store::aws::AmazonS3Builder::from_env().with_bucket_name(bucket);
        if let Some(endpoint) = endpoint {
            builder = builder
                .with_endpoint(endpoint)
                .with_allow_http(endpoint.starts_with("http://"));
        }
        let s3 = builder.build().map_err(|e| {
            StoreError::BadInput(format!(
                "{url}: cannot configure the store from the AWS_* environment: {e}"
            ))
        })?;
        Ok(Bucket {
            store: Arc::new(s3),
            prefix: prefix.to_string(),
            url: format!("s3://{bucket}/{prefix}"),
        })
    }

    /// The same bucket, `sub` further down (`s3://bucket/prefix/sub`).
    pub fn child(&self, sub: &str) -> Bucket {
        let prefix = if self.prefix.is_empty() {
            sub.to_string()
        } else {
            format!("{}/{sub}", self.prefix)
        };
        Bucket {
            store: self.store.clone(),
            url: format!("{}/{sub}", self.url.trim_end_matches('/')),
            prefix,
        }
    }

    /// `s3://bucket/prefix`.
    pub fn url(&self) -> &str {
        &self.url
    }

    fn path(&self, key: &str) -> ObjectPath {
        if self.prefix.is_empty() {
            ObjectPath::from(key)
        } else {
            ObjectPath::from(format!("{}/{key}", self.prefix))
        }
    }

    /// Bytes `range` of object `key`.
    ///
    /// # Errors
    /// The store fails or the object is missing.
    pub fn get_range(&self, key: &str, range: Range<u64>) -> Result<Bytes, StoreError> {
        let (store, path) = (self.store.clone(), self.path(key));
        let what = format!("cannot read bytes {range:?} of {}/{key}", self.url);
        wait(async move {
            let options = GetOptions::new().with_range(Some(range));
            store.get_opts(&path, options).await?.bytes().await
        })?
        .map_err(failed(what))
    }

    /// The whole object `key`, or `None` when there is none.
    ///
    /// # Errors
    /// The store fails.
    pub fn get(&self, key: &str) -> Result<Option<Bytes>, StoreError> {
        match self.get_if_changed(key, None)? {
            Conditional::Done(Some(b), _) => Ok(Some(b)),
            _ => Ok(None),
        }
    }

    /// Object `key` unless its ETag is still `etag` ([`Conditional::Refused`]: unchanged);
    /// `Done(None, _)` when there is no such object.
    ///
    /// # Errors
    /// The store fails.
    pub fn get_if_changed(
        &self,
        key: &str,
        etag: Option<&str>,
    ) -> Result<Conditional<Option<Bytes>>, StoreError> {
        let (store, path) = (self.store.clone(), self.path(key));
        let options = GetOptions {
            if_none_match: etag.map(str::to_string),
            ..Default::default()
        };
        let what = format!("cannot read {}/{key}", self.url);
        let got = wait(async move {
            match store.get_opts(&path, options).await {
                Ok(r) => {
                    let etag = r.meta.e_tag.clone().unwrap_or_default();
                    r.bytes().await.map(|b| Conditional::Done(Some(b), etag))
                }
                Err(object_store::Error::NotModified { .. }) => Ok(Conditional::Refused),
                Err(object_store::Error::NotFound { .. }) => {
                    Ok(Conditional::Done(None, String::new()))
                }
                Err(e) => Err(e),
            }
        })?
        .map_err(failed(what))?;
        // A store that ignores If-None-Match answers in full: the same ETag is no change.
        match (got, etag) {
            (Conditional::Done(Some(_), new), Some(old)) if new == old => Ok(Conditional::Refused),
            (got, _) => Ok(got),
        }
    }

    /// Writes object `key` unconditionally.
    ///
    /// # Errors
    /// The store fails.
    pub fn put(&self, key: &str, body: Bytes) -> Result<(), StoreError> {
        let (store, path) = (self.store.clone(), self.path(key));
        let what = format!("cannot write {}/{key}", self.url);
        wait(async move {
            let options = PutOptions::default();
            store.put_opts(&path, PutPayload::from(body), options).await
        })?
        .map_err(failed(what))?;
        Ok(())
    }

    /// Writes object `key` from the first `len` bytes of the file at `path`: one PUT up to
    /// [`multipart_part_bytes`], above that a multipart upload in parts of that size, up to
    /// [`MULTIPART_IN_FLIGHT`] at a time (a single PUT is limited to 5 GB on S3, and one lost
    /// connection would send the whole object again), read from the file as they are sent.
    /// `progress` counts the bytes sent. Returns how many parts the object went up in (1 for a
    /// single PUT).
    ///
    /// # Errors
    /// The file cannot be read, or the store fails (a multipart upload that failed is aborted,
    /// so its parts are not kept).
    pub fn put_file(
        &self,
        key: &str,
        path: &std::path::Path,
        len: u64,
        progress: &dyn crate::progress::Progress,
    ) -> Result<u32, StoreError> {
        use std::io::Read;
        let mut file =
            std::fs::File::open(path).map_err(StoreError::io_path("cannot open", path))?;
        let mut read = |n: u64| -> Result<Bytes, StoreError> {
            let mut buf = vec![0u8; n as usize];
            file.read_exact(&mut buf)
                .map_err(StoreError::io_path("cannot read", path))?;
            Ok(Bytes::from(buf))
        };
        self.put_in_parts(key, len, &mut read, progress)
    }

    /// [`Bucket::put_file`] for bytes in memory (a multipart upload above the threshold, its
    /// parts slices of `body`).
    ///
    /// # Errors
    /// The store fails.
    pub fn put_large(&self, key: &str, body: Bytes) -> Result<u32, StoreError> {
        let mut at = 0usize;
        let mut next = |n: u64| -> Result<Bytes, StoreError> {
            let part = body.slice(at..at + n as usize);
            at += n as usize;
            Ok(part)
        };
        self.put_in_parts(key, body.len() as u64, &mut next, &crate::progress::Silent)
    }

    /// Writes object `key`, `len` bytes taken in order from `next` (asked for a number of
    /// bytes each time): one PUT, or a multipart upload above the threshold.
    fn put_in_parts(
        &self,
        key: &str,
        len: u64,
        next: &mut dyn FnMut(u64) -> Result<Bytes, StoreError>,
        progress: &dyn crate::progress::Progress,
    ) -> Result<u32, StoreError> {
        let part = multipart_part_bytes()?;
        progress.start(len);
        if len <= part {
            self.put(key, next(len)?)?;
            progress.advance(len);
            progress.finish();
            return Ok(1);
        }
        let (store, object) = (self.store.clone(), self.path(key));
        let what = format!("cannot write {}/{key} (multipart)", self.url);
        let mut upload = wait(async move {
            store
                .put_multipart_opts(&object, object_store::PutMultipartOptions::default())
                .await
        })?
        .map_err(failed(what.clone()))?;
        let mut send = || -> Result<u32, StoreError> {
            let (mut sent, mut parts, mut reported) = (0u64, 0u32, 0u64);
            let mut in_flight = Vec::new();
            while sent < len {
                let n = part.min(len - sent);
                in_flight.push(upload.put_part(PutPayload::from(next(n)?)));
                sent += n;
                parts += 1;
                if in_flight.len() >= MULTIPART_IN_FLIGHT || sent == len {
                    let batch = futures_util::future::try_join_all(std::mem::take(&mut in_flight));
                    wait(batch)?.map_err(failed(what.clone()))?;
                    progress.advance(sent - reported);
                    reported = sent;
                }
            }
            Ok(parts)
        };
        let sent = send();
        progress.finish();
        match sent {
            Ok(parts) => {
                wait(async move { upload.complete().await })?.map_err(failed(what))?;
                Ok(parts)
            }
            Err(e) => {
                // The parts already sent cost storage until the upload is aborted.
                let _ = wait(async move { upload.abort().await });
                Err(e)
            }
        }
    }

    /// Writes object `key` only if its ETag is still `etag` (`If-Match`), or, with `None`,
    /// only if there is no such object yet (`If-None-Match: *`).
    ///
    /// # Errors
    /// The store fails (a refused condition is [`Conditional::Refused`], not an error).
    pub fn put_if(
        &self,
        key: &str,
        body: Bytes,
        etag: Option<&str>,
    ) -> Result<Conditional<()>, StoreError> {
        let (store, path) = (self.store.clone(), self.path(key));
        let mode = match etag {
            Some(e) => PutMode::Update(UpdateVersion {
                e_tag: Some(e.to_string()),
                version: None,
            }),
            None => PutMode::Create,
        };
        let what = format!("cannot write {}/{key}", self.url);
        wait(async move {
            let options = PutOptions {
                mode,
                ..Default::default()
            };
            match store.put_opts(&path, PutPayload::from(body), options).await {
                Ok(r) => Ok(Conditional::Done((), r.e_tag.unwrap_or_default())),
                Err(
                    object_store::Error::Precondition { .. }
                    | object_store::Error::AlreadyExists { .. },
                ) => Ok(Conditional::Refused),
                Err(e) => Err(e),
            }
        })?
        .map_err(failed(what))
    }

    /// Every object whose key starts with `under/`, with its write time.
    ///
    /// # Errors
    /// The store fails.
    pub fn list(&self, under: &str) -> Result<Vec<Listed>, StoreError> {
        use futures_util::StreamExt;
        let (store, path) = (self.store.clone(), self.path(under));
        let strip = format!("{}/", self.path("").as_ref().trim_end_matches('/'));
        let strip = if self.prefix.is_empty() {
            String::new()
        } else {
            strip
        };
        let what = format!("cannot list {}/{under}", self.url);
        wait(async move {
            let mut out = Vec::new();
            let mut stream = store.list(Some(&path));
            while let Some(meta) = stream.next().await {
                let meta = meta?;
                let key = meta.location.as_ref();
                out.push(Listed {
                    key: key.strip_prefix(strip.as_str()).unwrap_or(key).to_string(),
                    modified: meta.last_modified.into(),
                });
            }
            Ok(out)
        })?
        .map_err(failed(what))
    }

    /// The names just below the prefix (`prefix/NAME/...` gives `NAME`).
    ///
    /// # Errors
    /// The store fails.
    pub fn list_dirs(&self) -> Result<Vec<String>, StoreError> {
        let store = self.store.clone();
        let prefix = (!self.prefix.is_empty()).then(|| ObjectPath::from(self.prefix.as_str()));
        let what = format!("cannot list {}", self.url);
        let listed = wait(async move { store.list_with_delimiter(prefix.as_ref()).await })?
            .map_err(failed(what))?;
        Ok(listed
            .common_prefixes
            .iter()
            .filter_map(|p| p.filename().map(str::to_string))
            .collect())
    }

    /// Deletes object `key` (no error when it is already gone).
    ///
    /// # Errors
    /// The store fails.
    pub fn delete(&self, key: &str) -> Result<(), StoreError> {
        let (store, path) = (self.store.clone(), self.path(key));
        let what = format!("cannot delete {}/{key}", self.url);
        let deleted = wait(async move {
            use futures_util::StreamExt;
            let one = futures_util::stream::once(async move { Ok(path) }).boxed();
            store
                .delete_stream(one)
                .next()
                .await
                .transpose()
                .map(|_| ())
        })?;
        match deleted {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(failed(what)(e)),
        }
    }
}
