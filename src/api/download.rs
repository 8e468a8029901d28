//! Bounded memory for mesh downloads (`/result`, `/frames/{step}`, gRPC `DownloadResult`;
//! issue 25, item 6).
//!
//! A rendered mesh is built in memory (the writers in `willow::mesh` need the whole asset), and
//! before this module a client that asked for one and never read it kept it alive for as long
//! as its connection stayed: ~12 MB each, without bound. Now
//!
//! - a download is **streamed from storage**: the job core renders it once, stores it and
//!   hands out a reader (`Jobs::rendered`), so a download waiting for its client holds a
//!   chunk or two ([`STORED_HOLD_BYTES`]), not the file; only a rendering that could not be
//!   stored (storage full) is held whole;
//! - every download is **charged** what it holds against two byte budgets, the connection's
//!   (`--download-memory-per-connection-mib`) and the server's (`--download-memory-mib`); a
//!   download that does not fit answers 503 `downloads_busy` with `Retry-After` (gRPC:
//!   UNAVAILABLE) instead of being built, so the memory pinned by downloads is bounded per
//!   connection and in total; a download's first render holds its memory from the same
//!   server budget ([`crate::jobs::render_memory`]), so renders count in that total too;
//! - every download has a **deadline**: it must be taken by the client within
//!   `--write-timeout-secs` plus its length at `--write-min-rate-kib` (a floor: an honest reader
//!   at that rate always makes it). At the deadline a watchdog drops the buffer and releases the
//!   charge even if the connection is never polled again (an HTTP/2 stream with a zero window);
//!   the body then ends with an error, which resets the stream or closes the HTTP/1 connection;
//! - the body is handed to hyper a stored chunk at a time (a whole one in [`CHUNK_BYTES`]
//!   copies), so what hyper and h2 queue per stream is a chunk or two, never a slice that keeps
//!   a whole buffer alive after the watchdog dropped it.
//!
//! The connection's socket has its own write deadline (`conn::TimedIo`): a write that stays
//! blocked for `--write-timeout-secs` closes the connection, whatever the response.

use crate::jobs::render_memory::units;
use crate::jobs::{DownloadMemory, JobError, MeshDownload};
use axum::body::{Body, Bytes, HttpBody};
use futures::stream::BoxStream;
use http_body::{Frame, SizeHint};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::task::JoinHandle;

/// Size of the copies a download is handed out in: large enough that per-chunk overhead is
/// negligible, small enough that what hyper queues per stream stays small.
pub const CHUNK_BYTES: usize = 64 << 10;

/// `Retry-After` of a download refused for want of budget: a download in the budget is either
/// taken or dropped by its deadline, so a few seconds usually frees room.
pub const BUSY_RETRY_SECS: u64 = 5;

/// Bytes held by downloads in this process (all servers), for tests and metrics.
static HELD_BYTES: AtomicU64 = AtomicU64::new(0);

/// Bytes of rendered meshes currently held for clients in this process.
pub fn held_bytes() -> u64 {
    HELD_BYTES.load(Ordering::Relaxed)
}

/// The server-wide limits; one per `serve`.
#[derive(Debug)]
pub struct DownloadLimits {
    /// The server's budget, which renders draw on too ([`crate::jobs::render_memory`]).
    global: DownloadMemory,
    per_connection_units: u64,
    write_timeout: Duration,
    write_min_rate: u64,
}

impl DownloadLimits {
    /// `total` and `per_connection` in bytes (at least 1 KiB each); `write_min_rate` in bytes
    /// per second (0: only `write_timeout`).
    pub fn new(
        total: u64,
        per_connection: u64,
        write_timeout: Duration,
        write_min_rate: u64,
    ) -> Arc<Self> {
        Arc::new(DownloadLimits {
            global: DownloadMemory::new(total),
            per_connection_units: units(per_connection).min(Semaphore::MAX_PERMITS as u64),
            write_timeout,
            write_min_rate,
        })
    }

    /// A connection's budget (a request extension, set by `conn::handle`).
    pub fn for_connection(self: &Arc<Self>) -> DownloadBudget {
        DownloadBudget {
            limits: self.clone(),
            conn: Arc::new(Semaphore::new(self.per_connection_units as usize)),
        }
    }
}

/// One connection's share of the download budget.
#[derive(Debug, Clone)]
pub struct DownloadBudget {
    limits: Arc<DownloadLimits>,
    conn: Arc<Semaphore>,
}

/// No budget left for a download of this size right now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Busy {
    /// Which budget is exhausted: `"connection"` or `"server"`.
    pub scope: &'static str,
}

/// A download's hold on both budgets, released on drop.
#[derive(Debug)]
pub struct Charge {
    _global: OwnedSemaphorePermit,
    _conn: OwnedSemaphorePermit,
    bytes: u64,
}

impl Charge {
    /// Both permits of a charge of `len` bytes, counted as held until dropped.
    fn held(global: OwnedSemaphorePermit, conn: OwnedSemaphorePermit, len: usize) -> Charge {
        HELD_BYTES.fetch_add(len as u64, Ordering::Relaxed);
        Charge {
            _global: global,
            _conn: conn,
            bytes: len as u64,
        }
    }
}

impl Drop for Charge {
    fn drop(&mut self) {
        HELD_BYTES.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

impl DownloadBudget {
    /// Whether a download could start at all (checked before rendering, so a refused request
    /// costs no rendering). A server budget held in full by downloads waiting for their
    /// clients refuses at once; one that renders hold part of lets the request go on, to
    /// wait (bounded) for a render's room ([`crate::jobs::render_memory`]).
    pub fn check(&self) -> Result<(), Busy> {
        if self.conn.available_permits() == 0 {
            return Err(Busy {
                scope: "connection",
            });
        }
        let global = &self.limits.global;
        if global.available() == 0 && !global.renders_active() {
            return Err(Busy { scope: "server" });
        }
        Ok(())
    }

    /// The server's budget, for the renders of this connection's downloads.
    pub fn memory(&self) -> &DownloadMemory {
        &self.limits.global
    }

    /// Charge `len` bytes to this connection and the server. A download larger than a budget
    /// takes all of it (so it is served alone, never refused forever).
    pub fn charge(&self, len: usize) -> Result<Charge, Busy> {
        let conn = self.charge_connection(len)?;
        let global = self
            .limits
            .global
            .try_take(units(len as u64))
            .ok_or(Busy { scope: "server" })?;
        Ok(Charge::held(global, conn, len))
    }

    /// This connection's share of a charge of `len` bytes (at most its whole budget).
    fn charge_connection(&self, len: usize) -> Result<OwnedSemaphorePermit, Busy> {
        let conn_units = units(len as u64).min(self.limits.per_connection_units) as u32;
        self.conn
            .clone()
            .try_acquire_many_owned(conn_units)
            .map_err(|_| Busy {
                scope: "connection",
            })
    }

    /// [`DownloadBudget::charge`], but when the server's budget is short while renders hold
    /// part of it, wait for it as long as a render would
    /// ([`crate::jobs::render_memory::RENDER_WAIT`]): renders let go within a render's time,
    /// and a download whose own render just ended must not be refused for the next one's.
    pub async fn charge_or_wait(&self, len: usize) -> Result<Charge, Busy> {
        let busy = match self.charge(len) {
            Err(b) if b.scope == "server" && self.limits.global.renders_active() => b,
            other => return other,
        };
        let conn = self.charge_connection(len)?;
        let global = self
            .limits
            .global
            .take(units(len as u64), crate::jobs::render_memory::RENDER_WAIT)
            .await
            .ok_or(busy)?;
        Ok(Charge::held(global, conn, len))
    }

    /// The pace a client of this connection must keep on an event stream: the write timeout
    /// and the minimum rate, as for downloads.
    pub fn watch_floor(&self) -> crate::jobs::watch::WatchFloor {
        crate::jobs::watch::WatchFloor {
            timeout: self.limits.write_timeout,
            min_rate: self.limits.write_min_rate,
        }
    }

    /// How long a client may take to read `len` bytes: the write timeout plus `len` at the
    /// minimum rate.
    pub fn allowance(&self, len: usize) -> Duration {
        allowance(len, self.limits.write_timeout, self.limits.write_min_rate)
    }
}

/// `timeout + len / min_rate` (saturating; `min_rate` 0: `timeout` alone).
pub fn allowance(len: usize, timeout: Duration, min_rate: u64) -> Duration {
    if min_rate == 0 {
        return timeout;
    }
    let earned = Duration::try_from_secs_f64(len as f64 / min_rate as f64).unwrap_or(Duration::MAX);
    timeout.saturating_add(earned)
}

/// What a download streamed from storage is charged: the chunk being read from storage and
/// the one hyper is writing (a stored blob is read 64 KiB at a time on the embedded backend,
/// in the object store's 128 KiB chunks on NATS). What h2 queues per stream beyond that is
/// bounded by `conn`'s send buffer.
pub const STORED_HOLD_BYTES: u64 = 256 << 10;

/// A mesh on its way to a client, with its charge and deadline: streamed from its stored
/// rendering, or (when it could not be stored) held whole and handed out in copies.
pub struct Download {
    shared: Arc<Mutex<Option<Held>>>,
    len: u64,
    sent: u64,
    watchdog: Option<JoinHandle<()>>,
}

enum Source {
    Whole(Bytes),
    Stored(BoxStream<'static, Result<Bytes, JobError>>),
}

struct Held {
    source: Source,
    _charge: Option<Charge>,
}

impl Download {
    /// Hold `data` (charged by `charge`, if any) until it is read or `allowance` passes.
    pub fn new(data: MeshDownload, charge: Option<Charge>, allowance: Duration) -> Download {
        let len = data.len();
        let source = match data {
            MeshDownload::Whole(b) => Source::Whole(b),
            MeshDownload::Stored(r) => Source::Stored(r.chunks),
        };
        let shared = Arc::new(Mutex::new(Some(Held {
            source,
            _charge: charge,
        })));
        let held = shared.clone();
        let watchdog = tokio::spawn(async move {
            tokio::time::sleep(allowance).await;
            let dropped = lock(&held).take();
            if dropped.is_some() {
                tracing::info!(
                    bytes = len,
                    secs = allowance.as_secs_f64(),
                    "download not taken in time; dropped"
                );
            }
        });
        Download {
            shared,
            len,
            sent: 0,
            watchdog: Some(watchdog),
        }
    }

    /// The next chunk, `None` at the end, or an error once the deadline dropped it (or its
    /// storage failed, or gave other than its length).
    pub fn poll_chunk(
        &mut self,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Bytes, DownloadError>>> {
        if self.sent >= self.len {
            return Poll::Ready(None);
        }
        let mut guard = lock(&self.shared);
        let Some(held) = guard.as_mut() else {
            self.sent = self.len;
            return Poll::Ready(Some(Err(DownloadError::TooSlow)));
        };
        let chunk = match &mut held.source {
            Source::Whole(data) => {
                let start = self.sent as usize;
                let end = (start + CHUNK_BYTES).min(data.len());
                // A copy, not a slice: a slice queued in hyper would keep the whole buffer
                // alive after the watchdog dropped it.
                Ok(Bytes::copy_from_slice(&data[start..end]))
            }
            Source::Stored(chunks) => match chunks.as_mut().poll_next(cx) {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(Some(Ok(c))) if self.sent + c.len() as u64 <= self.len => Ok(c),
                Poll::Ready(Some(Ok(_))) => Err(DownloadError::Storage(format!(
                    "the stored download is longer than its {} bytes",
                    self.len
                ))),
                Poll::Ready(Some(Err(e))) => Err(DownloadError::Storage(e.to_string())),
                Poll::Ready(None) => Err(DownloadError::Storage(format!(
                    "the stored download ended at byte {} of {}",
                    self.sent, self.len
                ))),
            },
        };
        match chunk {
            Ok(c) => {
                self.sent += c.len() as u64;
                if self.sent == self.len {
                    // All handed out: free the source and the charge now, not when hyper drops
                    // us.
                    guard.take();
                    if let Some(w) = self.watchdog.take() {
                        w.abort();
                    }
                }
                Poll::Ready(Some(Ok(c)))
            }
            Err(e) => {
                tracing::warn!(error = %e, "download failed");
                guard.take();
                self.sent = self.len;
                Poll::Ready(Some(Err(e)))
            }
        }
    }

    /// [`Download::poll_chunk`] as a future.
    pub async fn next_chunk(&mut self) -> Option<Result<Bytes, DownloadError>> {
        std::future::poll_fn(|cx| self.poll_chunk(cx)).await
    }

    /// The total length.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether there is nothing to send.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// As a response body with an exact length (so HTTP/1 sends `Content-Length`).
    pub fn into_body(self) -> Body {
        Body::new(self)
    }
}

fn lock(m: &Mutex<Option<Held>>) -> std::sync::MutexGuard<'_, Option<Held>> {
    // A panic while holding this lock cannot leave the Option half-written.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Drop for Download {
    fn drop(&mut self) {
        if let Some(w) = self.watchdog.take() {
            w.abort();
        }
    }
}

/// Why a download ended before its last byte.
#[derive(Debug, Clone, thiserror::Error)]
pub enum DownloadError {
    /// The client did not take it in time: its deadline dropped it.
    #[error("the client did not read the download in time (write deadline)")]
    TooSlow,
    /// Reading it from storage failed.
    #[error("reading the download from storage failed: {0}")]
    Storage(String),
}

impl HttpBody for Download {
    type Data = Bytes;
    type Error = DownloadError;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, DownloadError>>> {
        self.get_mut()
            .poll_chunk(cx)
            .map(|o| o.map(|r| r.map(Frame::data)))
    }

    fn is_end_stream(&self) -> bool {
        self.sent >= self.len
    }

    fn size_hint(&self) -> SizeHint {
        SizeHint::with_exact(self.len - self.sent)
    }
}

impl Busy {
    /// What the client is told.
    pub fn detail(&self) -> String {
        format!(
            "too many downloads are waiting to be read on this {}; retry in {BUSY_RETRY_SECS} s",
            self.scope
        )
    }
}

impl From<Busy> for super::problem::Problem {
    fn from(b: Busy) -> Self {
        let mut p = super::problem::Problem::new(
            axum::http::StatusCode::SERVICE_UNAVAILABLE,
            "downloads_busy",
            b.detail(),
        )
        .with("scope", b.scope)
        .with("retry_after_secs", BUSY_RETRY_SECS);
        p.retry_after = Some(BUSY_RETRY_SECS);
        p
    }
}

/// What a download holds in memory while it waits for its client: all of it when held whole,
/// a chunk or two when streamed from storage.
pub fn held(data: &MeshDownload) -> u64 {
    match data {
        MeshDownload::Whole(b) => b.len() as u64,
        MeshDownload::Stored(r) => r.len.min(STORED_HOLD_BYTES),
    }
}

/// Start a download of `data` under `budget` (none: the router is used without `conn::serve`,
/// as in some tests, and nothing is charged; the deadline is then the default write timeout).
pub async fn start(budget: Option<&DownloadBudget>, data: MeshDownload) -> Result<Download, Busy> {
    let len = usize::try_from(data.len()).unwrap_or(usize::MAX);
    match budget {
        Some(b) => {
            let held = usize::try_from(held(&data)).unwrap_or(usize::MAX);
            let charge = b.charge_or_wait(held).await?;
            let allowance = b.allowance(len);
            Ok(Download::new(data, Some(charge), allowance))
        }
        None => {
            let d = super::conn::ConnLimits::default();
            let allowance = allowance(len, d.write_timeout, d.write_min_rate);
            Ok(Download::new(data, None, allowance))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::render_memory::UNIT;
    use futures::StreamExt;

    #[test]
    fn allowance_is_timeout_plus_length_at_the_floor() {
        let t = Duration::from_secs(30);
        assert_eq!(allowance(64 << 10, t, 32 << 10), Duration::from_secs(32));
        assert_eq!(allowance(usize::MAX, t, 0), t);
        assert_eq!(allowance(usize::MAX, Duration::MAX, 1), Duration::MAX);
    }

    #[tokio::test]
    async fn budgets_bound_what_is_held_and_free_it_on_drop() {
        let limits = DownloadLimits::new(10 << 10, 4 << 10, Duration::from_secs(60), 0);
        let a = limits.for_connection();
        let b = limits.for_connection();
        let c1 = a.charge(3 << 10).expect("fits the connection");
        assert_eq!(a.charge(2 << 10).unwrap_err().scope, "connection");
        let c2 = b.charge(4 << 10).expect("another connection");
        let c = limits.for_connection();
        let c3 = c.charge(3 << 10).expect("fits the server");
        // 3 + 4 + 3 = 10 KiB: the server is full, a fresh connection is refused.
        let d = limits.for_connection();
        assert_eq!(d.check().unwrap_err().scope, "server");
        drop((c1, c2, c3));
        // Larger than the connection's budget: takes all of it, served alone.
        let big = d
            .charge(100 << 10)
            .expect("an oversized download takes the whole budget");
        assert_eq!(d.check().unwrap_err().scope, "connection");
        drop(big);
        assert!(d.check().is_ok());
    }

    #[tokio::test]
    async fn a_download_comes_back_whole_in_chunks() {
        let data: Vec<u8> = (0..(3 * CHUNK_BYTES + 17))
            .map(|i| (i % 251) as u8)
            .collect();
        let mut d = Download::new(
            MeshDownload::Whole(data.clone().into()),
            None,
            Duration::from_secs(60),
        );
        let mut out = Vec::new();
        while let Some(c) = d.next_chunk().await {
            let c = c.expect("in time");
            assert!(c.len() <= CHUNK_BYTES);
            out.extend_from_slice(&c);
        }
        assert_eq!(out, data);
    }

    fn stored(chunks: Vec<Result<Bytes, JobError>>, len: u64) -> MeshDownload {
        MeshDownload::Stored(crate::jobs::ports::BlobReader {
            len,
            chunks: futures::stream::iter(chunks).boxed(),
        })
    }

    #[tokio::test]
    async fn a_stored_download_is_charged_a_chunk_or_two_and_comes_back_whole() {
        let data: Vec<u8> = (0..(5 * CHUNK_BYTES + 3))
            .map(|i| (i % 241) as u8)
            .collect();
        let chunks = data
            .chunks(CHUNK_BYTES)
            .map(|c| Ok(Bytes::copy_from_slice(c)))
            .collect();
        let source = stored(chunks, data.len() as u64);
        assert_eq!(held(&source), STORED_HOLD_BYTES);
        assert_eq!(
            held(&MeshDownload::Whole(data.clone().into())),
            data.len() as u64
        );
        let limits = DownloadLimits::new(1 << 20, 1 << 20, Duration::from_secs(60), 0);
        let mut d = start(Some(&limits.for_connection()), source)
            .await
            .expect("fits");
        assert_eq!(
            limits.global.available(),
            limits.global.units() - STORED_HOLD_BYTES / UNIT
        );
        let mut out = Vec::new();
        while let Some(c) = d.next_chunk().await {
            out.extend_from_slice(&c.expect("read"));
        }
        assert_eq!(out, data);
        assert_eq!(limits.global.available(), limits.global.units());
    }

    #[tokio::test]
    async fn a_stored_download_shorter_or_longer_than_announced_ends_with_an_error() {
        let short = stored(vec![Ok(Bytes::from_static(b"abc"))], 5);
        let mut d = Download::new(short, None, Duration::from_secs(60));
        assert_eq!(d.next_chunk().await.expect("a chunk").expect("ok").len(), 3);
        assert!(matches!(
            d.next_chunk().await,
            Some(Err(DownloadError::Storage(_)))
        ));
        assert!(d.next_chunk().await.is_none());
        let long = stored(vec![Ok(Bytes::from_static(b"abcdef"))], 5);
        let mut d = Download::new(long, None, Duration::from_secs(60));
        assert!(matches!(
            d.next_chunk().await,
            Some(Err(DownloadError::Storage(_)))
        ));
        let failing = stored(vec![Err(JobError::Unavailable("nats away".into()))], 5);
        let mut d = Download::new(failing, None, Duration::from_secs(60));
        let e = d
            .next_chunk()
            .await
            .expect("an item")
            .expect_err("an error");
        assert!(e.to_string().contains("nats away"), "{e}");
    }

    #[tokio::test]
    async fn the_deadline_drops_an_unread_download_and_its_charge() {
        let limits = DownloadLimits::new(1 << 20, 1 << 20, Duration::from_secs(60), 0);
        let budget = limits.for_connection();
        let charge = budget.charge(300 << 10).expect("fits");
        let mut d = Download::new(
            MeshDownload::Whole(vec![7; 300 << 10].into()),
            Some(charge),
            Duration::from_millis(50),
        );
        let first = d.next_chunk().await.expect("a chunk").expect("in time");
        assert_eq!(first.len(), CHUNK_BYTES);
        // Nobody polls the body: the watchdog frees the charge on its own.
        let freed = async {
            while limits.global.available() < limits.global.units() {
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        };
        tokio::time::timeout(Duration::from_secs(10), freed)
            .await
            .expect("charge released by the deadline");
        assert!(matches!(
            d.next_chunk().await,
            Some(Err(DownloadError::TooSlow))
        ));
        assert!(d.next_chunk().await.is_none());
    }
}
