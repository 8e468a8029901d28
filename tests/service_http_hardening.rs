//! Connection hardening (issue 12, item 3) and the CORS allow-list (item 2), end to end on the
//! real server (`serve_with`) with small timeouts: slowloris headers and bodies are cut within
//! the configured time while normal clients are served, half-open connections are closed, the
//! connection and per-connection request limits hold, and long responses (SSE, gRPC server
//! streams) outlive every one of those timeouts.
//!
//! Margins are generous (a cut must come within the timeout + 3 s) for a loaded 2-core machine.

mod service_http_support;

use service_http_support::{read_sse, slow_obj, small_obj, start_with, TestServer};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use willow_service::api::conn::ConnLimits;
use willow_service::api::server::{parse_origin, AppOptions, ServeOptions};

/// Extra time a cut may take beyond its timeout.
const MARGIN: Duration = Duration::from_secs(3);

fn limits(tweak: impl FnOnce(&mut ConnLimits)) -> ServeOptions {
    let mut conn = ConnLimits {
        header_read_timeout: Duration::from_secs(2),
        body_timeout: Duration::from_secs(2),
        idle_timeout: Duration::from_secs(2),
        ..ConnLimits::default()
    };
    tweak(&mut conn);
    ServeOptions {
        app: AppOptions::default(),
        conn,
    }
}

async fn start(options: ServeOptions) -> TestServer {
    start_with(tempfile::tempdir().expect("temp dir"), |_| {}, options).await
}

fn addr(srv: &TestServer) -> String {
    srv.base.trim_start_matches("http://").to_string()
}

/// A client with no connection pool: every request on a fresh connection, so a connection the
/// server closed for idleness is never reused (that race is the client's, not under test).
fn fresh_client() -> reqwest::Client {
    reqwest::Client::builder()
        .pool_max_idle_per_host(0)
        .build()
        .expect("client")
}

/// A parsed HTTP/1.1 response read from a raw socket (Content-Length bodies only).
#[derive(Debug)]
struct Raw {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Raw {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// Read one response; `None` when the connection ends (EOF or reset) before a full one.
async fn read_response(s: &mut TcpStream) -> Option<Raw> {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    let head_end = loop {
        if let Some(p) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break p + 4;
        }
        match s.read(&mut chunk).await {
            Ok(0) | Err(_) => return None,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
        }
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|c| c.parse().ok())
        .expect("a status line");
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let len: usize = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse().ok())
        .unwrap_or(0);
    let mut body = buf[head_end..].to_vec();
    while body.len() < len {
        match s.read(&mut chunk).await {
            Ok(0) | Err(_) => return None,
            Ok(n) => body.extend_from_slice(&chunk[..n]),
        }
    }
    Some(Raw {
        status,
        headers,
        body,
    })
}

/// Read until the server ends the connection; the bytes it sent and when it ended (`None`:
/// still open after `patience`).
async fn read_until_closed(s: &mut TcpStream, patience: Duration) -> (Vec<u8>, Option<Instant>) {
    let mut out = Vec::new();
    let mut chunk = [0u8; 4096];
    let reading = async {
        loop {
            match s.read(&mut chunk).await {
                Ok(0) | Err(_) => return,
                Ok(n) => out.extend_from_slice(&chunk[..n]),
            }
        }
    };
    let closed = tokio::time::timeout(patience, reading).await.is_ok();
    (out, closed.then(Instant::now))
}

/// Send `prefix`, then `trickle` one byte per second, until the server closes the connection.
/// Returns what the server sent and how long after `prefix` it closed.
async fn trickle_until_cut(
    stream: TcpStream,
    prefix: &[u8],
    trickle: &'static [u8],
    patience: Duration,
) -> (Vec<u8>, Duration) {
    let (mut read, mut write) = stream.into_split();
    write.write_all(prefix).await.expect("prefix sent");
    let sent = Instant::now();
    let writer = tokio::spawn(async move {
        for b in trickle.iter().cycle() {
            tokio::time::sleep(Duration::from_secs(1)).await;
            if write.write_all(&[*b]).await.is_err() {
                return;
            }
        }
    });
    let mut out = Vec::new();
    let mut chunk = [0u8; 4096];
    let reading = async {
        loop {
            match read.read(&mut chunk).await {
                Ok(0) | Err(_) => return,
                Ok(n) => out.extend_from_slice(&chunk[..n]),
            }
        }
    };
    let cut = tokio::time::timeout(patience, reading).await;
    writer.abort();
    assert!(
        cut.is_ok(),
        "the trickling client was not cut in {patience:?}"
    );
    (out, sent.elapsed())
}

/// Whatever the server sent a cut client is nothing, or a 408.
fn assert_nothing_or_408(sent: &[u8]) {
    let text = String::from_utf8_lossy(sent);
    assert!(
        sent.is_empty() || text.starts_with("HTTP/1.1 408"),
        "a cut client gets nothing or 408, got {text:?}"
    );
}

/// Ten normal requests, each on its own connection; the slowest one's latency.
async fn normal_clients(base: &str) -> Duration {
    let mut slowest = Duration::ZERO;
    for _ in 0..10 {
        let t = Instant::now();
        let res = fresh_client()
            .get(format!("{base}/healthz"))
            .timeout(Duration::from_secs(10))
            .send()
            .await
            .expect("a normal client is served");
        assert_eq!(res.status(), 200);
        assert_eq!(res.text().await.expect("body"), "ok");
        slowest = slowest.max(t.elapsed());
    }
    slowest
}

const HEALTHZ: &[u8] = b"GET /healthz HTTP/1.1\r\nHost: willow\r\n\r\n";

#[tokio::test]
async fn slowloris_headers_are_cut_while_normal_clients_are_served() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    let slow = trickle_until_cut(
        stream,
        b"GET /healthz HTTP/1.1\r\nHost: willow\r\n",
        b"X-Slow: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa",
        timeout + MARGIN + Duration::from_secs(5),
    );
    let (slow, slowest) = tokio::join!(slow, normal_clients(&srv.base));
    let (sent, after) = slow;
    eprintln!("slowloris (headers) cut after {after:?}, timeout {timeout:?}; slowest normal request {slowest:?}");
    assert!(
        after >= timeout - Duration::from_millis(500),
        "cut at {after:?}: before the timeout"
    );
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");
    assert_nothing_or_408(&sent);
    assert!(
        slowest < Duration::from_secs(2),
        "normal requests took {slowest:?}"
    );

    // The same on a keep-alive connection: the second request's head is trickled.
    let mut stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    stream.write_all(HEALTHZ).await.expect("send");
    let first = read_response(&mut stream).await.expect("first response");
    assert_eq!(first.status, 200);
    assert_eq!(first.body, b"ok");
    let (sent, after) = trickle_until_cut(
        stream,
        b"GET /healthz HTTP/1.1\r\n",
        b"Host: willowwwwwwwwwwwwwwwwwwwwww",
        timeout + MARGIN + Duration::from_secs(5),
    )
    .await;
    eprintln!("slowloris (keep-alive headers) cut after {after:?}, timeout {timeout:?}");
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");
    assert_nothing_or_408(&sent);
    srv.stop().await;
}

#[tokio::test]
async fn slow_and_stalled_bodies_are_cut_and_real_uploads_work() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let head = "POST /v1/jobs?steps=1 HTTP/1.1\r\nHost: willow\r\nContent-Type: model/obj\r\n\
                Content-Length: 100000\r\n\r\nv 0 0 0\n";

    // 1 byte a second.
    let stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    let (sent, after) = trickle_until_cut(
        stream,
        head.as_bytes(),
        b"v 1 1 1\n",
        timeout + MARGIN + Duration::from_secs(5),
    )
    .await;
    let text = String::from_utf8_lossy(&sent).to_string();
    eprintln!("slow body cut after {after:?}, body timeout {timeout:?}");
    assert!(
        text.starts_with("HTTP/1.1 408"),
        "a trickled body gets 408: {text}"
    );
    assert!(
        text.to_ascii_lowercase().contains("connection: close"),
        "{text}"
    );
    assert!(text.contains("body_timeout"), "{text}");
    assert!(
        after >= timeout - Duration::from_millis(500),
        "cut at {after:?}: before the timeout"
    );
    assert!(after <= timeout + MARGIN, "cut only after {after:?}");

    // A body that stops half-way.
    let mut stream = TcpStream::connect(addr(&srv)).await.expect("connect");
    stream.write_all(head.as_bytes()).await.expect("send");
    stream
        .write_all("v 1 2 3\n".repeat(1000).as_bytes())
        .await
        .expect("send");
    let t = Instant::now();
    let res = tokio::time::timeout(timeout + MARGIN, read_response(&mut stream))
        .await
        .expect("answered within the body timeout")
        .expect("a response");
    eprintln!("stalled body answered after {:?}", t.elapsed());
    assert_eq!(res.status, 408);
    assert_eq!(res.header("connection"), Some("close"));
    let (_, closed) = read_until_closed(&mut stream, MARGIN).await;
    assert!(closed.is_some(), "the connection closes after the 408");

    // A real upload, at loopback speed, is untouched; so are normal clients meanwhile.
    let obj = slow_obj();
    let (status, _, job) = srv.submit_obj(&obj, "steps=2").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("job id").to_string();
    let done = srv
        .poll_until(
            &id,
            Duration::from_secs(120),
            service_http_support::is_terminal,
        )
        .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    eprintln!("real upload of {} bytes accepted and run", obj.len());
    srv.stop().await;
}

#[tokio::test]
async fn grpc_upload_trickling_is_deadline_exceeded() {
    use willow_service::api::grpc::pb::willow::v1;
    use willow_service::api::grpc::pb::willow::v1::upload_mesh_chunk::Part;
    let srv = start(limits(|_| {})).await;
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut client = v1::fairing_client::FairingClient::new(channel);
    let header = v1::UploadMeshChunk {
        part: Some(Part::Header(v1::UploadHeader {
            format: v1::MeshFormat::Obj as i32,
            size_bytes: 1_000_000,
        })),
    };
    // One small chunk a second, forever.
    let chunks = futures::stream::unfold(true, |first| async move {
        if !first {
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        Some((
            v1::UploadMeshChunk {
                part: Some(Part::Data(bytes::Bytes::from_static(b"v 0 0 0\n"))),
            },
            false,
        ))
    });
    let t = Instant::now();
    let result = tokio::time::timeout(
        Duration::from_secs(2) + MARGIN + Duration::from_secs(5),
        client.upload_mesh(futures::stream::once(async { header }).chain_with(chunks)),
    )
    .await
    .expect("the trickled upload is ended by the server");
    eprintln!("gRPC trickled upload ended after {:?}", t.elapsed());
    let status = result.expect_err("a trickled upload fails");
    assert_eq!(status.code(), tonic::Code::DeadlineExceeded, "{status:?}");
    assert!(t.elapsed() <= Duration::from_secs(2) + MARGIN);
    // The connection (other streams) is untouched: the same channel still works.
    let res = client
        .get_job(v1::GetJobRequest {
            name: "jobs/00000000000000000000000000000000".into(),
        })
        .await;
    assert!(
        matches!(&res, Err(s) if s.code() == tonic::Code::NotFound || s.code() == tonic::Code::InvalidArgument),
        "{res:?}"
    );
    srv.stop().await;
}

/// `futures::StreamExt::chain`, spelled so the two streams' types need not match exactly.
trait ChainWith: futures::Stream + Sized {
    fn chain_with<S: futures::Stream<Item = Self::Item>>(
        self,
        other: S,
    ) -> futures::stream::Chain<Self, S> {
        futures::StreamExt::chain(self, other)
    }
}
impl<T: futures::Stream> ChainWith for T {}

#[tokio::test]
async fn forty_half_open_connections_are_closed_and_do_not_block_others() {
    let srv = start(limits(|_| {})).await;
    let timeout = Duration::from_secs(2);
    let opened = Instant::now();
    let mut idle = Vec::new();
    for _ in 0..40 {
        idle.push(TcpStream::connect(addr(&srv)).await.expect("connect"));
    }
    let slowest = normal_clients(&srv.base).await;
    eprintln!("with 40 half-open connections, slowest normal request {slowest:?}");
    assert!(
        slowest < Duration::from_secs(2),
        "normal requests took {slowest:?}"
    );
    let mut last = opened;
    for s in &mut idle {
        let left = (opened + timeout + MARGIN).saturating_duration_since(Instant::now());
        let (sent, closed) = read_until_closed(s, left).await;
        let closed = closed.expect("a half-open connection is closed within the timeout");
        assert!(sent.is_empty() || String::from_utf8_lossy(&sent).starts_with("HTTP/1.1 408"));
        last = last.max(closed);
    }
    let all = last - opened;
    eprintln!("40 half-open connections all closed {all:?} after opening (timeout {timeout:?})");
    assert!(
        all >= timeout - Duration::from_millis(500),
        "closed at {all:?}"
    );
    assert!(all <= timeout + MARGIN);
    srv.stop().await;
}

#[tokio::test]
async fn at_the_connection_limit_new_connections_wait_until_one_closes() {
    let srv = start(limits(|c| {
        c.max_connections = 3;
        c.header_read_timeout = Duration::from_secs(60);
        c.idle_timeout = Duration::from_secs(60);
    }))
    .await;
    let mut held = Vec::new();
    for _ in 0..3 {
        held.push(TcpStream::connect(addr(&srv)).await.expect("connect"));
    }
    // The fourth connects (the kernel's backlog) but is not served…
    let mut fourth = TcpStream::connect(addr(&srv)).await.expect("connect");
    fourth
        .write_all(b"GET /healthz HTTP/1.1\r\nHost: willow\r\nConnection: close\r\n\r\n")
        .await
        .expect("send");
    let mut byte = [0u8; 1];
    let early = tokio::time::timeout(Duration::from_millis(1500), fourth.peek(&mut byte)).await;
    assert!(early.is_err(), "served beyond the connection limit");
    // …until one of the three closes.
    drop(held.remove(0));
    let t = Instant::now();
    let res = tokio::time::timeout(Duration::from_secs(10), read_response(&mut fourth))
        .await
        .expect("served once a connection closed")
        .expect("a response");
    eprintln!(
        "queued connection served {:?} after a slot freed",
        t.elapsed()
    );
    assert_eq!(res.status, 200);
    srv.stop().await;
}

#[tokio::test]
async fn requests_per_connection_are_limited() {
    let srv = start(limits(|c| {
        c.max_requests_per_connection = 3;
        c.header_read_timeout = Duration::from_secs(30);
        c.idle_timeout = Duration::from_secs(30);
    }))
    .await;
    let mut s = TcpStream::connect(addr(&srv)).await.expect("connect");
    for n in 1..=3 {
        s.write_all(HEALTHZ).await.expect("send");
        let res = read_response(&mut s).await.expect("a response");
        assert_eq!(res.status, 200);
        if n < 3 {
            assert_eq!(res.header("connection"), None, "request {n}");
        } else {
            assert_eq!(res.header("connection"), Some("close"), "request {n}");
        }
    }
    let (_, closed) = read_until_closed(&mut s, MARGIN).await;
    assert!(
        closed.is_some(),
        "the connection closes after the 3rd response"
    );

    // HTTP/2 (gRPC): the 3rd request starts a graceful GOAWAY; the channel reconnects and
    // every call succeeds.
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut health = HealthClient::new(channel);
    for n in 0..10 {
        health
            .check(HealthCheckRequest {
                service: String::new(),
            })
            .await
            .unwrap_or_else(|e| panic!("call {n}: {e:?}"));
    }
    srv.stop().await;
}

#[tokio::test]
async fn sse_and_grpc_streams_outlive_the_timeouts() {
    use willow_service::api::grpc::pb::willow::v1;
    use willow_service::api::grpc::pb::willow::v1::stream_frames_response::Event;
    let srv = start(limits(|c| {
        c.header_read_timeout = Duration::from_secs(1);
        c.body_timeout = Duration::from_secs(1);
        c.idle_timeout = Duration::from_secs(1);
        c.keepalive_interval = Duration::from_secs(1);
    }))
    .await;
    // The only worker is busy with a long job; the job under test waits behind it.
    let (status, _, blocker) = srv
        .submit_obj(&slow_obj(), "steps=10000&until_converged=false")
        .await;
    assert_eq!(status, 202, "{blocker}");
    let blocker = blocker["id"].as_str().expect("id").to_string();
    srv.poll_until(&blocker, Duration::from_secs(60), |v| {
        v["state"] == "running"
    })
    .await;
    let (status, _, job) = srv
        .submit_obj(&small_obj(), "steps=4&frame_interval=1")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();

    let opened = Instant::now();
    let sse = fresh_client()
        .get(srv.url(&format!("/v1/jobs/{id}/events")))
        .send()
        .await
        .expect("SSE");
    assert_eq!(sse.status(), 200);
    let channel = tonic::transport::Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("h2c");
    let mut grpc = v1::fairing_client::FairingClient::new(channel)
        .stream_frames(v1::StreamFramesRequest {
            name: format!("jobs/{id}"),
            from_step: 0,
        })
        .await
        .expect("StreamFrames")
        .into_inner();

    // Well past every timeout, then let the job run.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let res = fresh_client()
        .post(srv.url(&format!("/v1/jobs/{blocker}/cancel")))
        .send()
        .await
        .expect("cancel");
    assert!(res.status().is_success(), "{}", res.status());

    let grpc_events = async {
        let mut events = Vec::new();
        while let Some(m) = grpc.message().await.expect("the gRPC stream stays healthy") {
            events.push(m.event.expect("an event"));
        }
        events
    };
    let (events, grpc_events) = tokio::join!(read_sse(sse, Duration::from_secs(120)), async {
        tokio::time::timeout(Duration::from_secs(120), grpc_events)
            .await
            .expect("the gRPC stream ends")
    });
    let open = opened.elapsed();
    eprintln!(
        "SSE and gRPC streams open {open:?} (idle/header/body timeouts 1 s): {} SSE events, {} gRPC events",
        events.len(),
        grpc_events.len()
    );
    assert!(open >= Duration::from_secs(3));
    let done = events.last().expect("SSE events");
    assert_eq!(done.event, "done", "{events:?}");
    assert!(events.iter().any(|e| e.event == "frame"), "{events:?}");
    assert!(grpc_events.iter().any(|e| matches!(e, Event::Frame(_))));
    match grpc_events.last() {
        Some(Event::Job(job)) => {
            assert_eq!(job.state, v1::job::State::Succeeded as i32, "{job:?}")
        }
        other => panic!("the gRPC stream ends with the job, got {other:?}"),
    }
    srv.stop().await;
}

#[tokio::test]
async fn cors_is_an_allow_list() {
    let allowed = "https://app.example";
    let mut options = limits(|_| {});
    options.app.cors_origins = vec![parse_origin(allowed).expect("origin")];
    let srv = start(options).await;
    let client = fresh_client();

    // An allowed origin: its own origin echoed, Vary: Origin, the exposed headers.
    let res = client
        .post(srv.url("/v1/jobs?steps=1"))
        .header("origin", allowed)
        .header("content-type", "model/obj")
        .body(small_obj())
        .send()
        .await
        .expect("post");
    assert_eq!(res.status(), 202);
    assert_eq!(res.headers()["access-control-allow-origin"], allowed);
    let vary = res.headers()["vary"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(vary.contains("origin"), "{vary}");
    let exposed = res.headers()["access-control-expose-headers"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(
        exposed.contains("location") && exposed.contains("retry-after"),
        "{exposed}"
    );
    let preflight = |origin: &'static str| {
        client
            .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .header(
                "access-control-request-headers",
                "idempotency-key,content-type",
            )
            .send()
    };
    let res = preflight(allowed).await.expect("preflight");
    assert!(res.status().is_success());
    assert_eq!(res.headers()["access-control-allow-origin"], allowed);
    let headers = res.headers()["access-control-allow-headers"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(headers.contains("idempotency-key"), "{headers}");

    // Any other origin: no grant, on the request or the preflight.
    for origin in [
        "https://evil.example",
        "https://app.example.evil",
        "http://app.example",
    ] {
        let res = client
            .get(srv.url("/healthz"))
            .header("origin", origin)
            .send()
            .await
            .expect("get");
        assert_eq!(res.status(), 200);
        assert!(
            res.headers().get("access-control-allow-origin").is_none(),
            "{origin}"
        );
        assert!(res
            .headers()
            .get("access-control-allow-credentials")
            .is_none());
        let res = preflight(origin).await.expect("preflight");
        assert!(
            res.headers().get("access-control-allow-origin").is_none(),
            "{origin}"
        );
    }
    srv.stop().await;

    // The default: no origin allowed, no CORS headers at all; the built-in page is served
    // from the same origin and needs none.
    let srv = start(limits(|_| {})).await;
    let res = client
        .get(srv.url("/healthz"))
        .header("origin", allowed)
        .send()
        .await
        .expect("get");
    assert_eq!(res.status(), 200);
    assert!(
        !res.headers()
            .keys()
            .any(|k| k.as_str().starts_with("access-control-")),
        "{:?}",
        res.headers()
    );
    let res = preflight_to(&client, &srv, allowed).await;
    assert!(
        !res.headers()
            .keys()
            .any(|k| k.as_str().starts_with("access-control-")),
        "{:?}",
        res.headers()
    );
    let page = client.get(srv.url("/")).send().await.expect("page");
    assert_eq!(page.status(), 200);
    srv.stop().await;
}

async fn preflight_to(
    client: &reqwest::Client,
    srv: &TestServer,
    origin: &str,
) -> reqwest::Response {
    client
        .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
        .header("origin", origin)
        .header("access-control-request-method", "POST")
        .send()
        .await
        .expect("preflight")
}

#[test]
fn cors_origins_are_validated_and_normalised() {
    let ok = |s: &str| {
        parse_origin(s)
            .expect(s)
            .to_str()
            .expect("ascii")
            .to_string()
    };
    assert_eq!(ok("https://app.example"), "https://app.example");
    assert_eq!(ok("HTTPS://App.Example:443"), "https://app.example");
    assert_eq!(ok("http://localhost:5173"), "http://localhost:5173");
    assert_eq!(ok("http://127.0.0.1:80"), "http://127.0.0.1");
    for bad in [
        "*",
        "null",
        "app.example",
        "https://app.example/",
        "https://app.example/path",
        "ftp://app.example",
        "https://user@app.example",
        "https://",
        "https://app.example:port",
    ] {
        let e = parse_origin(bad).expect_err(bad);
        assert!(e.contains("--cors-origin"), "{e}");
    }
}

#[test]
fn serve_flags_have_defaults_and_are_validated() {
    use clap::Parser;
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        serve: willow_service::api::server::ServeArgs,
    }
    let parse = |args: &[&str]| {
        let mut all = vec!["willow"];
        all.extend_from_slice(args);
        Cli::try_parse_from(all)
            .expect("flags parse")
            .serve
            .serve_options()
    };
    let o = parse(&[]).expect("the defaults are valid");
    assert!(o.app.cors_origins.is_empty());
    assert_eq!(o.conn.header_read_timeout, Duration::from_secs(10));
    assert_eq!(o.conn.body_timeout, Duration::from_secs(30));
    assert_eq!(o.conn.body_min_rate, 32 * 1024);
    assert_eq!(o.conn.idle_timeout, Duration::from_secs(60));
    assert_eq!(o.conn.max_connections, 1024);
    assert_eq!(o.conn.max_requests_per_connection, 1000);
    assert_eq!(o.conn.max_streams_per_connection, 128);
    let o = parse(&[
        "--cors-origin",
        "https://a.example",
        "--cors-origin",
        "http://localhost:5173",
        "--idle-timeout-secs",
        "1.5",
        "--max-requests-per-connection",
        "0",
    ])
    .expect("valid");
    assert_eq!(o.app.cors_origins.len(), 2);
    assert_eq!(o.conn.idle_timeout, Duration::from_millis(1500));
    for (flag, value) in [
        ("--header-read-timeout-secs", "0"),
        ("--body-timeout-secs=-1", ""),
        ("--idle-timeout-secs", "NaN"),
        ("--keepalive-interval-secs", "1e300"),
        ("--max-connections", "0"),
        ("--max-streams-per-connection", "0"),
        ("--cors-origin", "*"),
    ] {
        let args: Vec<&str> = [flag, value]
            .into_iter()
            .filter(|a| !a.is_empty())
            .collect();
        let e = parse(&args).expect_err(flag);
        let name = flag.split('=').next().unwrap_or(flag);
        assert!(e.contains(name), "{flag} {value}: {e}");
    }
}

/// A client's `X-Request-Id` is echoed when it is a plausible id, and replaced by a fresh one
/// when it is long (8 KB was seen echoed and logged) or carries other characters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn implausible_request_ids_are_replaced_not_echoed() {
    let srv = start(ServeOptions::default()).await;
    let client = reqwest::Client::new();
    let id_for = |given: Option<String>| {
        let mut req = client.get(srv.url("/healthz"));
        if let Some(g) = given {
            req = req.header("x-request-id", g);
        }
        async move {
            let res = req.send().await.expect("healthz");
            assert_eq!(res.status(), 200);
            res.headers()["x-request-id"]
                .to_str()
                .expect("ascii")
                .to_string()
        }
    };
    let fine = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01".to_string();
    assert_eq!(id_for(Some(fine.clone())).await, fine);
    let longest = "a".repeat(willow_service::api::server::MAX_REQUEST_ID_LEN);
    assert_eq!(id_for(Some(longest.clone())).await, longest);
    for bad in [
        "a".repeat(8192),
        "a".repeat(willow_service::api::server::MAX_REQUEST_ID_LEN + 1),
        "id with spaces".to_string(),
        "id\"quoted\"".to_string(),
    ] {
        let got = id_for(Some(bad.clone())).await;
        assert_ne!(got, bad);
        assert_eq!(got.len(), 36, "a fresh UUID: {got}");
    }
    srv.stop().await;
}
