//! The accept loop of `willow serve`: hyper-util's auto builder (HTTP/1.1 and h2c prior
//! knowledge, so gRPC keeps working) with the connection limits `axum::serve` does not offer.
//!
//! What happens at each limit (`--…` are the `willow serve` flags, see [`ConnLimits`]):
//!
//! - **Connections** (`--max-connections`): a permit is taken *before* `accept`, so at the limit
//!   new connections wait in the kernel's listen backlog (1024) until one closes; they are then
//!   served normally. Their clocks (header read, idle) start when they are accepted.
//! - **Waiting for a request** (`--header-read-timeout-secs`): a new connection must deliver
//!   its first request head within this time. For HTTP/1 hyper's `header_read_timeout` runs
//!   from the moment the connection waits for a request head until the head is complete, for
//!   the first request and every keep-alive request after it, so a client trickling header
//!   bytes is cut (hyper answers 408 where it can, then closes). For a connection that sends
//!   nothing at all (HTTP/1, or before the h2 preface) this module closes it at the same time.
//! - **Idle** (`--idle-timeout-secs`): a connection with no request in flight (no open
//!   HTTP/2 stream, no HTTP/1 request being read or answered) for this long is closed
//!   gracefully (HTTP/2: GOAWAY). For HTTP/1 the header-read timeout above also runs while
//!   waiting for the next request, so a keep-alive connection is closed after the *smaller*
//!   of the two. HTTP/2 connections are also pinged every `--keepalive-interval-secs` and
//!   closed when a ping is not answered within [`KEEPALIVE_TIMEOUT`] (a vanished peer, even
//!   with streams open).
//! - **Request bodies** (`--body-timeout-secs`, `--body-min-rate-kib`): see `TimedBody`.
//!   A body that stalls for the timeout, or whose average rate falls below the minimum once
//!   the timeout has passed, ends with an error: REST answers 408 (problem+json) and, on
//!   HTTP/1, closes the connection; gRPC answers DEADLINE_EXCEEDED on that stream only.
//! - **Requests per connection** (`--max-requests-per-connection`): on HTTP/1 the Nth
//!   response carries `Connection: close` and the connection closes after it; on HTTP/2 the
//!   Nth request starts a graceful GOAWAY (streams already open finish; clients reconnect).
//! - **Streams per HTTP/2 connection** (`--max-streams-per-connection`): the
//!   SETTINGS_MAX_CONCURRENT_STREAMS the server announces.
//!
//! - **Writes** (`--write-timeout-secs`): a write to the socket that stays blocked this long
//!   (the client stopped reading and the kernel's send buffer is full) closes the connection;
//!   see [`TimedIo`].
//! - **Downloads** (`--download-memory-mib`, `--download-memory-per-connection-mib`,
//!   `--write-min-rate-kib`): the memory a mesh download holds (a chunk or two: downloads are
//!   streamed from their stored rendering) is charged to the connection and the server and must be taken within the write timeout plus its length at the
//!   minimum rate; see `api::download`.
//!
//! None of these limits the *length* of a response: an SSE stream or a gRPC server stream runs
//! as long as it has something to say and its client reads it (a request in flight is never
//! idle). Its client must keep the write floor, though: a watcher that does not take its
//! events within `--write-timeout-secs` plus their bytes at `--write-min-rate-kib` is cut off
//! (`jobs::watch::WatchFloor`).
//!
//! Shutdown: the listener is closed, every connection is told to finish gracefully (HTTP/1:
//! after its current response; HTTP/2: GOAWAY) and the loop returns once all have closed.

use axum::body::{Body, Bytes, HttpBody};
use axum::http::{header, HeaderValue, Request, Response, StatusCode, Version};
use axum::response::IntoResponse;
use axum::Router;
use http_body::{Frame, SizeHint};
use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpListener;
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::ServiceExt;

use super::download::{DownloadBudget, DownloadLimits};
use super::problem::Problem;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// How long an HTTP/2 keep-alive ping may go unanswered before the connection is closed.
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

/// Largest header block an HTTP/2 client may send, pseudo-headers (`:path`) included: above
/// the server's own limits on the request target and the header fields
/// (`http::MAX_URI_BYTES` + `http::MAX_HEADER_BYTES`, 48 KiB), so that a head between the two
/// is answered by `http::refuse_oversized_head` with a problem, not by h2 with an empty 431.
const MAX_HEADER_LIST_BYTES: u32 = 64 << 10;

/// hyper's HTTP/1 header count (its default is 100): above `http::MAX_HEADERS`, for the
/// same reason. hyper parses a head into this many slots, ~50 bytes each.
const MAX_H1_HEADERS: usize = 2 * super::http::MAX_HEADERS;

/// Bytes h2 may queue per stream beyond what the peer's window lets it send (h2's default is
/// ~400 KiB): with 128 streams on a connection whose client opened no window, this is what
/// one connection can pin in send queues (16 MiB instead of 50).
const MAX_SEND_BUF_BYTES: usize = 128 << 10;

/// After a connection was told to close gracefully with no request in flight, how long it
/// gets to do so (an HTTP/2 GOAWAY waits for the client's ping answer) before it is dropped.
const CLOSE_GRACE: Duration = Duration::from_secs(5);

/// The connection limits; `Default` gives `willow serve`'s defaults.
#[derive(Debug, Clone)]
pub struct ConnLimits {
    /// Time to deliver a complete request head (see the module docs).
    pub header_read_timeout: Duration,
    /// A request body may stall this long; also the grace period before the minimum rate
    /// applies.
    pub body_timeout: Duration,
    /// Minimum average request-body rate in bytes per second once `body_timeout` has passed
    /// (0: no minimum rate, only the stall limit).
    pub body_min_rate: u64,
    /// A connection with no request in flight is closed after this.
    pub idle_timeout: Duration,
    /// HTTP/2 keep-alive ping interval.
    pub keepalive_interval: Duration,
    /// Connections served at once; more wait in the listen backlog.
    pub max_connections: usize,
    /// Requests one connection may carry (0: no limit).
    pub max_requests_per_connection: u64,
    /// HTTP/2 streams open at once on one connection.
    pub max_streams_per_connection: u32,
    /// A socket write may stay blocked this long; also the grace period of a download.
    pub write_timeout: Duration,
    /// Minimum rate (bytes per second) at which a client must take a download once
    /// `write_timeout` has passed (0: only the timeout).
    pub write_min_rate: u64,
    /// Bytes held for downloads at once, server-wide (a streamed download is charged
    /// `download::STORED_HOLD_BYTES`).
    pub download_memory: u64,
    /// Bytes of rendered downloads held at once on one connection.
    pub download_memory_per_connection: u64,
}

impl Default for ConnLimits {
    fn default() -> Self {
        ConnLimits {
            header_read_timeout: Duration::from_secs(10),
            body_timeout: Duration::from_secs(30),
            body_min_rate: 32 << 10,
            idle_timeout: Duration::from_secs(60),
            keepalive_interval: Duration::from_secs(30),
            max_connections: 1024,
            max_requests_per_connection: 1000,
            max_streams_per_connection: 128,
            write_timeout: Duration::from_secs(30),
            write_min_rate: 64 << 10,
            download_memory: 256 << 20,
            download_memory_per_connection: 32 << 20,
        }
    }
}

/// Serve `app` on `listener` within `limits` until `stop` is cancelled; then stop accepting,
/// close every connection gracefully and return once all are closed.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: ConnLimits,
    stop: CancellationToken,
) -> std::io::Result<()> {
    let limits = Arc::new(limits);
    let downloads = DownloadLimits::new(
        limits.download_memory,
        limits.download_memory_per_connection,
        limits.write_timeout,
        limits.write_min_rate,
    );
    let builder = Arc::new(builder(&limits));
    let permits = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let tracker = TaskTracker::new();
    loop {
        // The permit first: at the limit, connections wait in the backlog, not in our memory.
        let permit = tokio::select! {
            p = permits.clone().acquire_owned() => match p {
                Ok(p) => p,
                Err(_) => break, // never closed
            },
            _ = stop.cancelled() => break,
        };
        let (tcp, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(c) => c,
                Err(e) if is_connection_error(&e) => continue,
                Err(e) => {
                    // Out of file descriptors and the like: back off rather than spin.
                    tracing::error!(error = %e, "accept failed; retrying in 1 s");
                    tokio::select! {
                        _ = tokio::time::sleep(Duration::from_secs(1)) => continue,
                        _ = stop.cancelled() => break,
                    }
                }
            },
            _ = stop.cancelled() => break,
        };
        // TCP_NODELAY: SSE writes one small event at a time; with Nagle's algorithm each event
        // after the first waits for the client's delayed ACK (~40 ms).
        let _ = tcp.set_nodelay(true);
        tracker.spawn(connection(
            tcp,
            app.clone(),
            builder.clone(),
            limits.clone(),
            downloads.for_connection(),
            stop.clone(),
            permit,
        ));
        tracing::trace!(%peer, "connection accepted");
    }
    drop(listener);
    tracker.close();
    tracker.wait().await;
    Ok(())
}

fn builder(limits: &ConnLimits) -> auto::Builder<TokioExecutor> {
    let mut b = auto::Builder::new(TokioExecutor::new());
    b.http1()
        .timer(TokioTimer::new())
        .header_read_timeout(limits.header_read_timeout)
        .max_headers(MAX_H1_HEADERS)
        .keep_alive(true);
    b.http2()
        .timer(TokioTimer::new())
        .keep_alive_interval(limits.keepalive_interval)
        .keep_alive_timeout(KEEPALIVE_TIMEOUT)
        .max_concurrent_streams(limits.max_streams_per_connection)
        .max_header_list_size(MAX_HEADER_LIST_BYTES)
        .max_send_buf_size(MAX_SEND_BUF_BYTES);
    b
}

/// Errors of one connection that `accept` reports and that say nothing about the listener.
fn is_connection_error(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        ConnectionRefused | ConnectionAborted | ConnectionReset
    )
}

/// What the connection task needs to know about the requests on its connection.
#[derive(Debug, Clone)]
struct Activity {
    /// Requests dispatched and not yet answered to the end (response body included).
    in_flight: usize,
    /// Requests dispatched so far.
    requests: u64,
    /// When `in_flight` last became 0 (or the connection was accepted).
    idle_since: Instant,
    /// Close gracefully now (HTTP/2 request limit reached).
    close: bool,
}

struct ConnState {
    activity: watch::Sender<Activity>,
    limits: Arc<ConnLimits>,
    downloads: DownloadBudget,
}

/// A request in flight; dropped when its response body ends (or the request is abandoned).
struct InFlight(Arc<ConnState>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.activity.send_modify(|a| {
            a.in_flight = a.in_flight.saturating_sub(1);
            if a.in_flight == 0 {
                a.idle_since = Instant::now();
            }
        });
    }
}

async fn connection(
    tcp: tokio::net::TcpStream,
    app: Router,
    builder: Arc<auto::Builder<TokioExecutor>>,
    limits: Arc<ConnLimits>,
    downloads: DownloadBudget,
    stop: CancellationToken,
    // Released when the connection is gone.
    _permit: OwnedSemaphorePermit,
) {
    let (tx, mut rx) = watch::channel(Activity {
        in_flight: 0,
        requests: 0,
        idle_since: Instant::now(),
        close: false,
    });
    let state = Arc::new(ConnState {
        activity: tx,
        limits: limits.clone(),
        downloads,
    });
    let svc =
        tower::service_fn(move |req: Request<Incoming>| handle(req, app.clone(), state.clone()));
    let io = TokioIo::new(TimedIo::new(tcp, limits.write_timeout));
    let conn = builder.serve_connection(io, TowerToHyperService::new(svc));
    tokio::pin!(conn);
    // When the connection was told to close gracefully.
    let mut closing: Option<Instant> = None;
    let mut watching = true;
    loop {
        let a = rx.borrow_and_update().clone();
        if closing.is_none() && a.close {
            conn.as_mut().graceful_shutdown();
            closing = Some(Instant::now());
        }
        // Before the first request the header-read timeout applies, then the idle timeout.
        let wait = if a.requests == 0 {
            limits.header_read_timeout
        } else {
            limits.idle_timeout
        };
        let idle_deadline = (a.in_flight == 0 && closing.is_none()).then(|| a.idle_since + wait);
        let drop_deadline = closing
            .filter(|_| a.in_flight == 0)
            .map(|t| t.max(a.idle_since) + CLOSE_GRACE);
        tokio::select! {
            r = conn.as_mut() => {
                if let Err(e) = r {
                    tracing::debug!(error = %e, "connection ended with an error");
                }
                break;
            }
            _ = sleep_until_some(idle_deadline) => {
                tracing::debug!(in_flight = a.in_flight, "closing an idle connection");
                conn.as_mut().graceful_shutdown();
                closing = Some(Instant::now());
            }
            _ = sleep_until_some(drop_deadline) => {
                tracing::debug!("connection did not close gracefully in time; dropping it");
                break;
            }
            r = rx.changed(), if watching => {
                if r.is_err() {
                    watching = false;
                }
            }
            _ = stop.cancelled(), if closing.is_none() => {
                conn.as_mut().graceful_shutdown();
                closing = Some(Instant::now());
            }
        }
    }
}

async fn sleep_until_some(deadline: Option<Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

/// One request: counted, its body under the body timeout, its response marked as the
/// connection's last when the request limit is reached.
async fn handle(
    req: Request<Incoming>,
    app: Router,
    conn: Arc<ConnState>,
) -> Result<Response<Body>, Infallible> {
    let mut number = 0;
    conn.activity.send_modify(|a| {
        a.in_flight += 1;
        a.requests += 1;
        number = a.requests;
    });
    let in_flight = InFlight(conn.clone());
    let limits = &conn.limits;
    let http1 = req.version() <= Version::HTTP_11;
    let last =
        limits.max_requests_per_connection > 0 && number >= limits.max_requests_per_connection;
    if last && !http1 {
        // HTTP/2: a graceful GOAWAY; this stream and the others already open finish.
        conn.activity.send_modify(|a| a.close = true);
    }
    let grpc = req
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"));
    let timed_out = Arc::new(AtomicBool::new(false));
    let mut req = req;
    req.extensions_mut().insert(conn.downloads.clone());
    let req = req.map(|body| {
        if body.is_end_stream() {
            Body::new(body)
        } else {
            Body::new(TimedBody::new(
                body,
                limits.body_timeout,
                limits.body_min_rate,
                timed_out.clone(),
            ))
        }
    });
    let mut response = match app.oneshot(req).await {
        Ok(r) => r,
        Err(never) => match never {},
    };
    let timed_out = timed_out.load(Ordering::Acquire);
    if timed_out && !grpc {
        // Whatever the handler made of the failed read (a 400 about a broken body, a
        // multipart error), the truth is a timeout. gRPC has its status from the body error.
        let request_id = response.headers().get("x-request-id").cloned();
        response = Problem::new(
            StatusCode::REQUEST_TIMEOUT,
            "body_timeout",
            format!(
                "the request body arrived too slowly: it stalled for {} s or fell below {} \
                 bytes/s on average",
                limits.body_timeout.as_secs_f64(),
                limits.body_min_rate
            ),
        )
        .into_response();
        if let Some(id) = request_id {
            response.headers_mut().insert("x-request-id", id);
        }
    }
    if http1 && (last || timed_out) {
        // hyper closes the connection after this response (and does not wait for the rest
        // of an unread body).
        response
            .headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    Ok(response.map(|body| {
        Body::new(Tracked {
            inner: body,
            _in_flight: in_flight,
        })
    }))
}

/// A response body that keeps its request counted as in flight until it ends.
struct Tracked {
    inner: Body,
    _in_flight: InFlight,
}

impl HttpBody for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A request body with a deadline for its bytes. Reading starts the clock; the body fails
/// when either
///
/// - no byte arrived for `timeout` (a stalled upload), or
/// - after `timeout`, fewer than `min_rate` bytes per second arrived on average since the
///   read began: having received `n` bytes, the body must be complete by
///   `start + timeout + n / min_rate`. A client trickling 1 byte/s is cut right after
///   `timeout`; one uploading at least `min_rate` is never cut, however large the body.
///
/// A total deadline would have to allow the largest upload at the slowest honest rate and
/// would then hold a trickling connection for as long; a rate needs no such compromise.
struct TimedBody<B> {
    inner: B,
    timeout: Duration,
    min_rate: u64,
    start: Option<Instant>,
    last: Instant,
    received: u64,
    sleep: Pin<Box<Sleep>>,
    timed_out: Arc<AtomicBool>,
    failed: bool,
}

/// The error a [`TimedBody`] ends with. A tonic `Status`, so that a gRPC request whose body
/// timed out answers DEADLINE_EXCEEDED (tonic looks for a status in the error's source chain).
fn body_timeout_error() -> BoxError {
    Box::new(tonic::Status::deadline_exceeded(
        "the request body arrived too slowly",
    ))
}

impl<B> TimedBody<B> {
    fn new(inner: B, timeout: Duration, min_rate: u64, timed_out: Arc<AtomicBool>) -> Self {
        let now = Instant::now();
        TimedBody {
            inner,
            timeout,
            min_rate,
            start: None,
            last: now,
            received: 0,
            sleep: Box::pin(tokio::time::sleep_until(now + timeout)),
            timed_out,
            failed: false,
        }
    }

    fn deadline(&self, start: Instant) -> Instant {
        let stalled = self.last + self.timeout;
        if self.min_rate == 0 {
            return stalled;
        }
        // Saturating: no byte count may overflow the clock (that would panic).
        let earned = Duration::try_from_secs_f64(self.received as f64 / self.min_rate as f64)
            .unwrap_or(Duration::MAX);
        match start
            .checked_add(self.timeout)
            .and_then(|t| t.checked_add(earned))
        {
            Some(rate) => stalled.min(rate),
            None => stalled,
        }
    }
}

impl<B> HttpBody for TimedBody<B>
where
    B: HttpBody<Data = Bytes> + Unpin,
    B::Error: Into<BoxError>,
{
    type Data = Bytes;
    type Error = BoxError;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, BoxError>>> {
        let this = self.get_mut();
        if this.failed {
            return Poll::Ready(None);
        }
        let start = match this.start {
            Some(s) => s,
            None => {
                let now = Instant::now();
                this.start = Some(now);
                this.last = now;
                let d = this.deadline(now);
                this.sleep.as_mut().reset(d);
                now
            }
        };
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if !data.is_empty() {
                        this.received = this.received.saturating_add(data.len() as u64);
                        this.last = Instant::now();
                        let d = this.deadline(start);
                        this.sleep.as_mut().reset(d);
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(e.into()))),
            Poll::Ready(None) => Poll::Ready(None),
            Poll::Pending => {
                if this.sleep.as_mut().poll(cx).is_ready() {
                    this.failed = true;
                    this.timed_out.store(true, Ordering::Release);
                    tracing::info!(
                        received = this.received,
                        secs = start.elapsed().as_secs_f64(),
                        "request body too slow; cut"
                    );
                    return Poll::Ready(Some(Err(body_timeout_error())));
                }
                Poll::Pending
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.failed || self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// A connection's socket with a write deadline: a write (or flush) that stays blocked for
/// `timeout` without a byte going out fails with `TimedOut`, which ends the connection. A
/// client that stops reading fills the kernel's send buffer, and without this its response
/// (and all it holds) would wait for it forever; hyper has no write timeout of its own.
///
/// The clock runs only while a write is blocked and restarts with every byte the kernel
/// accepts, so a slow but reading client is never cut here (the download deadline in
/// `api::download` is what enforces a minimum rate, where the bytes at stake are large).
pub struct TimedIo<T> {
    inner: T,
    timeout: Duration,
    /// Armed when a write first blocks; `None` while writes go through.
    blocked: Option<Pin<Box<Sleep>>>,
}

impl<T> TimedIo<T> {
    pub fn new(inner: T, timeout: Duration) -> Self {
        TimedIo {
            inner,
            timeout,
            blocked: None,
        }
    }

    /// A write is blocked: start or check the clock (registering its wake-up with `cx`, so
    /// the connection is polled again at the deadline even if the socket never frees up).
    fn blocked<R>(&mut self, cx: &mut Context<'_>) -> Poll<std::io::Result<R>> {
        let timeout = self.timeout;
        let sleep = self
            .blocked
            .get_or_insert_with(|| Box::pin(tokio::time::sleep(timeout)));
        if sleep.as_mut().poll(cx).is_ready() {
            tracing::info!(
                secs = timeout.as_secs_f64(),
                "client stopped reading; connection closed"
            );
            return Poll::Ready(Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                "write timed out: the client stopped reading",
            )));
        }
        Poll::Pending
    }

    /// The write went through (or failed on its own): the clock stops.
    fn done<R>(&mut self, r: Poll<std::io::Result<R>>) -> Poll<std::io::Result<R>> {
        self.blocked = None;
        r
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for TimedIo<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for TimedIo<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write(cx, buf) {
            Poll::Pending => self.blocked(cx),
            r => self.done(r),
        }
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write_vectored(cx, bufs) {
            Poll::Pending => self.blocked(cx),
            r => self.done(r),
        }
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match Pin::new(&mut self.inner).poll_flush(cx) {
            Poll::Pending => self.blocked(cx),
            r => self.done(r),
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match Pin::new(&mut self.inner).poll_shutdown(cx) {
            Poll::Pending => self.blocked(cx),
            r => self.done(r),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn a_write_blocked_past_the_timeout_fails_and_a_reader_keeps_it_going() {
        // Generous against a loaded machine: the reader below pauses 2 ms between reads.
        let timeout = Duration::from_secs(2);
        // A 1 KiB pipe: the second KiB blocks until the peer reads.
        let (ours, mut peer) = tokio::io::duplex(1024);
        let mut io = TimedIo::new(ours, timeout);
        let data = vec![7u8; 64 << 10];
        // The peer reads slowly but steadily: every write goes through eventually.
        let reader = tokio::spawn(async move {
            let mut got = 0;
            let mut buf = [0u8; 1024];
            while got < 64 << 10 {
                tokio::time::sleep(Duration::from_millis(2)).await;
                match peer.read(&mut buf).await {
                    Ok(0) | Err(_) => break,
                    Ok(n) => got += n,
                }
            }
            (got, peer)
        });
        io.write_all(&data)
            .await
            .expect("a reading peer is never cut");
        let (got, _peer) = reader.await.expect("reader");
        assert_eq!(got, data.len());
        // Now nobody reads: the pipe fills and the write fails with TimedOut.
        let err = io
            .write_all(&data)
            .await
            .expect_err("a peer that stopped reading is cut");
        assert_eq!(err.kind(), std::io::ErrorKind::TimedOut);
    }
}
