//! Slow readers against a real server process (issue 25, item 6, "How it is shown"): 60
//! clients request a large result and never read it, while the server's resident memory
//! (`VmRSS` of the spawned `willow serve`) is sampled. Downloads are streamed from storage, so
//! what each hanging client pins is a chunk or two, not the ~4 MB file: the growth stays far
//! below the 60 × 4 MB the clients would pin if each held its own rendering. A normal client
//! is served meanwhile, and gets the same bytes as before the hangers came.
//!
//! `WILLOW_SERVER_BIN` runs the test against another build of `willow` (to measure a build
//! from before this change: it then fails, and says how far the memory grew).

mod service_http_support;

use service_http_support::{obj_text, obj_vertices, poll_until, submit_obj_to};
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use willow::mesh::generate;

/// Clients that request the result and never read it (the count).
const HANGERS: usize = 60;

/// What the hangers may add to the server's RSS. Holding each download whole, 60 of these
/// results pin 60 × ~4 MB ≈ 240 MB; streamed, each pins a 64 KiB chunk plus hyper's buffers.
const MAX_GROWTH_BYTES: u64 = 150 << 20;

/// A spawned `willow serve`, killed on drop.
struct Server {
    child: Child,
    base: String,
    addr: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn spawn_server(data_dir: &std::path::Path) -> Server {
    let bin = std::env::var("WILLOW_SERVER_BIN")
        .unwrap_or_else(|_| env!("CARGO_BIN_EXE_willow").to_string());
    let mut child = Command::new(bin)
        .args(["serve", "--addr", "127.0.0.1:0", "--workers", "1"])
        .arg("--data-dir")
        .arg(data_dir)
        .args(["--log-format", "json"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn willow serve");
    let stdout = child.stdout.take().expect("piped stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("listening on ") {
                let _ = tx.send(url.trim().to_string());
            }
        }
    });
    let base = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("the server says where it listens");
    let addr = base.trim_start_matches("http://").to_string();
    Server { child, base, addr }
}

/// The resident set of process `pid` in bytes (`VmRSS` in `/proc/{pid}/status`).
fn rss_bytes(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    let kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS in kB");
    kib * 1024
}

/// A client with a tiny receive buffer, so the server's writes block after a few KiB.
async fn stingy_connect(addr: &str) -> TcpStream {
    let socket = TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    socket
        .connect(addr.parse().expect("socket address"))
        .await
        .expect("connect")
}

/// Send a GET and read only the response head; its status.
async fn request_head(s: &mut TcpStream, path: &str) -> u16 {
    let req = format!("GET {path} HTTP/1.1\r\nHost: willow\r\n\r\n");
    s.write_all(req.as_bytes()).await.expect("request sent");
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        let n = s.read(&mut byte).await.expect("head read");
        assert_eq!(n, 1, "connection closed inside the head");
        head.push(byte[0]);
    }
    String::from_utf8_lossy(&head)
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .expect("a status line")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixty_clients_that_never_read_a_large_result_leave_the_servers_memory_bounded() {
    let dir = tempfile::tempdir().expect("temp dir");
    let server = spawn_server(dir.path());
    let pid = server.child.id();
    let client = reqwest::Client::new();
    // 40 962 vertices: about 4 MB of OBJ.
    let obj = obj_text(&generate::bumpy_sphere(6, 0.1));
    let id = submit_obj_to(&client, &server.base, "steps=1", &obj).await;
    let done = poll_until(&client, &server.base, &id, Duration::from_secs(180), |v| {
        v["state"] != "queued" && v["state"] != "running"
    })
    .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let path = format!("/v1/jobs/{id}/result?format=obj");
    let whole = client
        .get(format!("{}{path}", server.base))
        .send()
        .await
        .expect("GET result")
        .bytes()
        .await
        .expect("the result");
    assert!(
        whole.len() > 3_000_000,
        "a large result: {} bytes",
        whole.len()
    );
    let text = String::from_utf8_lossy(&whole);
    assert_eq!(obj_vertices(&text).len(), 40962);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let baseline = rss_bytes(pid);

    let mut hanging = Vec::new();
    let mut peak = baseline;
    for _ in 0..HANGERS {
        let mut s = stingy_connect(&server.addr).await;
        assert_eq!(request_head(&mut s, &path).await, 200);
        hanging.push(s);
        peak = peak.max(rss_bytes(pid));
    }
    // While they hang (the default write deadline is 30 s), a normal client is served, and
    // gets the same bytes.
    let status = client
        .get(format!("{}/v1/jobs/{id}", server.base))
        .send()
        .await
        .expect("GET job");
    assert_eq!(status.status(), 200);
    let again = client
        .get(format!("{}{path}", server.base))
        .send()
        .await
        .expect("GET result while they hang");
    assert_eq!(again.status(), 200);
    assert_eq!(again.bytes().await.expect("the result"), whole);
    for _ in 0..20 {
        tokio::time::sleep(Duration::from_millis(250)).await;
        peak = peak.max(rss_bytes(pid));
    }
    let growth = peak.saturating_sub(baseline);
    eprintln!(
        "RSS: baseline {:.1} MB, peak with {HANGERS} hanging clients {:.1} MB (+{:.1} MB); \
         result {} bytes",
        baseline as f64 / 1e6,
        peak as f64 / 1e6,
        growth as f64 / 1e6,
        whole.len()
    );
    assert!(
        growth < MAX_GROWTH_BYTES,
        "{HANGERS} clients that never read grew the server by {:.1} MB",
        growth as f64 / 1e6
    );
    drop(hanging);
}
