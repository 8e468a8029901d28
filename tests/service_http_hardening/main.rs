//! Connection hardening (issue 12, item 3) and the CORS allow-list (item 2), end to end on the
//! real server (`serve_with`) with small timeouts: slowloris headers and bodies are cut within
//! the configured time while normal clients are served, half-open connections are closed, the
//! connection and per-connection request limits hold, and long responses (SSE, gRPC server
//! streams) outlive every one of those timeouts.
//!
//! Margins are generous (a cut must come within the timeout + 3 s) for a loaded 2-core machine.
//!
//! One file a theme: `slow` (slowloris headers and bodies, gRPC upload trickling),
//! `connections` (half-open connections, the connection and per-connection request limits,
//! long streams), `cors`, `flags` (serve flags and request ids).

#[path = "../service_http_support/mod.rs"]
mod service_http_support;

mod connections;
mod cors;
mod flags;
mod slow;

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
