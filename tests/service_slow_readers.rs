//! Slow readers (issue 25, item 6): clients that request a large result and never read it are
//! cut off after the write deadline, the memory their downloads hold (a chunk or two each: a
//! download is streamed from its stored rendering) stays within the budget (beyond it they get
//! 503 `downloads_busy` + `Retry-After`), and a normal client is served while they hang.
//! Watchers of an event stream (SSE, gRPC) that stop reading are cut off at the same floor.
//! `service_slow_readers_rss` measures the server's RSS with 60 such clients.
//!
//! Alone in its binary: it asserts on `download::held_bytes()`, the process-wide count of bytes
//! held for downloads, which other tests' downloads would disturb.

mod service_http_support;

use service_http_support::slow_socket::start;
use service_http_support::{obj_text, obj_vertices, poll_until, submit_obj_to};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use willow::mesh::generate;
use willow_service::api::conn::ConnLimits;
use willow_service::api::download::{held_bytes, STORED_HOLD_BYTES};
use willow_service::api::server::{AppOptions, ServeOptions};

/// The write timeout under test (the default is 30 s).
const WRITE_TIMEOUT: Duration = Duration::from_secs(2);

/// The rate floor under test: 1 MiB/s, so a ~1 MB result must be taken within ~3 s.
const MIN_RATE: u64 = 1 << 20;

/// Clients that ask for the result and never read.
const HANGERS: usize = 8;

/// A client whose receive buffer is tiny, so the server's writes block after a few KiB
/// instead of filling megabytes of loopback buffers.
async fn stingy_connect(addr: &str) -> TcpStream {
    let addr = addr.parse().expect("socket address");
    let socket = TcpSocket::new_v4().expect("socket");
    socket.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    socket.connect(addr).await.expect("connect")
}

/// Send a GET and read only the response head: (status, content-length, retry-after).
async fn request_head(s: &mut TcpStream, path: &str) -> (u16, Option<usize>, Option<String>) {
    let req = format!("GET {path} HTTP/1.1\r\nHost: willow\r\n\r\n");
    s.write_all(req.as_bytes()).await.expect("request sent");
    let mut buf = Vec::new();
    let mut byte = [0u8; 1];
    // One byte at a time: the client must not read past the head.
    while !buf.ends_with(b"\r\n\r\n") {
        let n = s.read(&mut byte).await.expect("head read");
        assert!(n == 1, "connection closed inside the head: {buf:?}");
        buf.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&buf).to_string();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .expect("a status line");
    let header = |name: &str| {
        head.split("\r\n")
            .filter_map(|l| l.split_once(':'))
            .find(|(k, _)| k.trim().eq_ignore_ascii_case(name))
            .map(|(_, v)| v.trim().to_string())
    };
    let len = header("content-length").and_then(|v| v.parse().ok());
    (status, len, header("retry-after"))
}

/// Read until the server ends the connection (or `patience` passes): bytes read, and whether
/// it ended.
async fn drain(s: &mut TcpStream, patience: Duration) -> (usize, bool) {
    let mut total = 0;
    let mut chunk = vec![0u8; 64 << 10];
    let reading = async {
        loop {
            match s.read(&mut chunk).await {
                Ok(0) | Err(_) => return,
                Ok(n) => total += n,
            }
        }
    };
    let ended = tokio::time::timeout(patience, reading).await.is_ok();
    (total, ended)
}

async fn succeeded_job(client: &reqwest::Client, base: &str, obj: &str) -> String {
    let id = submit_obj_to(client, base, "steps=1", obj).await;
    let done = poll_until(client, base, &id, Duration::from_secs(120), |v| {
        v["state"] != "queued" && v["state"] != "running"
    })
    .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    id
}

/// The tests here assert on the process-wide `held_bytes()`: one at a time.
static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_that_never_read_are_cut_and_their_memory_is_bounded() {
    let _serial = SERIAL.lock().await;
    // 10242 vertices: a result of about a megabyte as OBJ, far more than the client's
    // receive buffer.
    let obj = obj_text(&generate::bumpy_sphere(5, 0.1));
    let client = reqwest::Client::new();
    let probe = {
        let (addr, stop, _) = start(ServeOptions::default()).await;
        let base = format!("http://{addr}");
        let id = succeeded_job(&client, &base, &obj).await;
        let res = client
            .get(format!("{base}/v1/jobs/{id}/result?format=obj"))
            .send()
            .await
            .expect("GET result");
        assert_eq!(res.status(), 200);
        let len = res.bytes().await.expect("result").len();
        let _ = stop.send(());
        len
    };
    assert!(
        probe > 500_000,
        "the result should be large, is {probe} bytes"
    );
    // Room for three hanging downloads on the server: each holds a chunk or two, not the
    // whole result.
    let budget = 3 * STORED_HOLD_BYTES + STORED_HOLD_BYTES / 2;
    let options = ServeOptions {
        app: AppOptions::default(),
        conn: ConnLimits {
            write_timeout: WRITE_TIMEOUT,
            write_min_rate: MIN_RATE,
            download_memory: budget,
            download_memory_per_connection: 2 * probe as u64,
            ..ConnLimits::default()
        },
    };
    let (addr, stop, jobs) = start(options).await;
    let base = format!("http://{addr}");
    let id = succeeded_job(&client, &base, &obj).await;
    let path = format!("/v1/jobs/{id}/result?format=obj");
    assert_eq!(held_bytes(), 0, "nothing held before the downloads");
    // What the mesh writer renders in memory (the path downloads took before they were
    // stored): the streamed download must be the same bytes.
    let caller = willow_service::jobs::Caller::anonymous();
    let rendered = jobs
        .result(&caller, &id, willow::mesh::io::Format::Obj)
        .await
        .expect("rendered in memory");
    assert_eq!(rendered.len(), probe);

    let mut hanging = Vec::new();
    let mut refused = 0;
    for _ in 0..HANGERS {
        let mut s = stingy_connect(&addr).await;
        let (status, len, retry_after) = request_head(&mut s, &path).await;
        match status {
            200 => {
                assert_eq!(len, Some(probe), "the full length is announced");
                hanging.push(s);
            }
            503 => {
                let secs: u64 = retry_after
                    .expect("503 carries Retry-After")
                    .parse()
                    .expect("Retry-After in seconds");
                assert!(secs >= 1);
                refused += 1;
            }
            other => panic!("unexpected status {other}"),
        }
        // The budget bounds what the hanging clients pin.
        assert!(
            held_bytes() <= budget,
            "held {} > budget {budget}",
            held_bytes()
        );
    }
    let started = Instant::now();
    assert_eq!(hanging.len(), 3, "exactly the budget's worth are served");
    assert_eq!(refused, HANGERS - 3);
    assert_eq!(held_bytes(), 3 * STORED_HOLD_BYTES);

    // While they hang, a normal client is answered.
    let asked = Instant::now();
    let res = client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .expect("GET job");
    assert_eq!(res.status(), 200);
    let v: serde_json::Value = res.json().await.expect("job json");
    eprintln!("status answered in {:?} while they hang", asked.elapsed());
    assert_eq!(v["state"], "succeeded");

    // The deadline (timeout + length at the floor) frees their memory without their help…
    let allowance = WRITE_TIMEOUT + Duration::from_secs_f64(probe as f64 / MIN_RATE as f64);
    let patience = allowance + Duration::from_secs(10);
    while held_bytes() > 0 {
        assert!(
            started.elapsed() < patience,
            "still held after {:?}: {}",
            started.elapsed(),
            held_bytes()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // …and their connections are closed: what remains in the pipes is less than the result.
    for mut s in hanging {
        let (got, ended) = drain(&mut s, Duration::from_secs(10)).await;
        assert!(ended, "a hanging connection was not closed");
        assert!(
            got < probe,
            "a cut download arrived whole ({got} of {probe} bytes)"
        );
    }

    // With the budget free again, a reading client gets the whole result, intact.
    let res = client
        .get(format!("{base}{path}"))
        .send()
        .await
        .expect("GET result");
    assert_eq!(res.status(), 200);
    let text = res.text().await.expect("result text");
    assert_eq!(text.len(), probe);
    assert_eq!(
        text.as_bytes(),
        &rendered[..],
        "streamed = rendered in memory"
    );
    assert_eq!(obj_vertices(&text).len(), 10242);
    assert_eq!(held_bytes(), 0, "a finished download holds nothing");
    let _ = stop.send(());
}

/// The same against HTTP/2 clients that open no flow-control window: the server can send them
/// no byte, so no socket write ever blocks; the per-connection budget and the download deadline
/// still bound and free what they pin.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http2_streams_with_a_zero_window_are_bounded_and_released() {
    let _serial = SERIAL.lock().await;
    let obj = obj_text(&generate::bumpy_sphere(5, 0.1));
    let client = reqwest::Client::new();
    const PER_CONNECTION: u64 = 1 << 20;
    // A generous server budget: here the connection's budget is the one that binds.
    let options = ServeOptions {
        app: AppOptions::default(),
        conn: ConnLimits {
            write_timeout: WRITE_TIMEOUT,
            write_min_rate: MIN_RATE,
            download_memory: 64 << 20,
            download_memory_per_connection: PER_CONNECTION,
            ..ConnLimits::default()
        },
    };
    let (addr, stop, _) = start(options).await;
    let base = format!("http://{addr}");
    let id = succeeded_job(&client, &base, &obj).await;
    let path = format!("/v1/jobs/{id}/result?format=obj");
    assert_eq!(held_bytes(), 0);

    const CONNECTIONS: usize = 2;
    const STREAMS: usize = 10;
    let mut kept = Vec::new();
    let mut served = 0;
    let mut refused = 0;
    let mut len = 0;
    for _ in 0..CONNECTIONS {
        let tcp = TcpStream::connect(&addr).await.expect("connect");
        let (h2, conn) = h2::client::Builder::new()
            .initial_window_size(0)
            .handshake::<_, bytes::Bytes>(tcp)
            .await
            .expect("h2 handshake");
        tokio::spawn(conn);
        for _ in 0..STREAMS {
            let mut h2 = h2.clone().ready().await.expect("stream slot");
            let req = axum::http::Request::get(format!("{base}{path}"))
                .body(())
                .expect("request");
            let (response, _) = h2.send_request(req, true).expect("request sent");
            let response = response.await.expect("response head");
            match response.status().as_u16() {
                200 => {
                    served += 1;
                    len = response
                        .headers()
                        .get("content-length")
                        .and_then(|v| v.to_str().ok())
                        .and_then(|v| v.parse::<usize>().ok())
                        .expect("content-length");
                    kept.push(response);
                }
                503 => {
                    assert!(response.headers().contains_key("retry-after"));
                    refused += 1;
                }
                other => panic!("unexpected status {other}"),
            }
            assert!(
                held_bytes() <= CONNECTIONS as u64 * PER_CONNECTION,
                "held {} beyond the connections' budgets",
                held_bytes()
            );
        }
        drop(h2);
    }
    assert!(len > 500_000, "the result should be large, is {len} bytes");
    // 1 MiB per connection holds four streamed downloads of a chunk or two each.
    let per_connection = (PER_CONNECTION / STORED_HOLD_BYTES) as usize;
    assert_eq!(per_connection, 4);
    assert_eq!(served, CONNECTIONS * per_connection);
    assert_eq!(refused, CONNECTIONS * (STREAMS - per_connection));
    assert_eq!(held_bytes(), served as u64 * STORED_HOLD_BYTES);

    // Nobody reads (the windows stay shut); the deadline frees the memory all the same.
    let started = Instant::now();
    let patience = WRITE_TIMEOUT
        + Duration::from_secs_f64(len as f64 / MIN_RATE as f64)
        + Duration::from_secs(10);
    while held_bytes() > 0 {
        assert!(
            started.elapsed() < patience,
            "still held after {:?}: {}",
            started.elapsed(),
            held_bytes()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    drop(kept);
    let _ = stop.send(());
}

/// A job that keeps running (every step kept, 2562 vertices: each frame carries ~40 KB of
/// positions), once it runs.
async fn running_job(client: &reqwest::Client, base: &str) -> String {
    let obj = obj_text(&generate::bumpy_sphere(4, 0.1));
    let query = "steps=5000&until_converged=false&frame_interval=1";
    let id = submit_obj_to(client, base, query, &obj).await;
    let running = poll_until(client, base, &id, Duration::from_secs(120), |v| {
        v["state"] != "queued"
    })
    .await;
    assert_eq!(running["state"], "running", "{running}");
    id
}

/// The floor for watchers under test: the write timeout and rate above.
fn watch_options() -> ServeOptions {
    ServeOptions {
        app: AppOptions::default(),
        conn: ConnLimits {
            write_timeout: WRITE_TIMEOUT,
            write_min_rate: MIN_RATE,
            ..ConnLimits::default()
        },
    }
}

/// How long a test leaves a watcher unread: the floor's allowance for a full channel (16 frames
/// of ~40 KB at 1 MiB/s, plus the timeout) several times over.
const UNREAD: Duration = Duration::from_secs(12);

/// An SSE watcher on HTTP/2 that stops reading: its window fills, the server can send nothing,
/// its events pile up in the watcher's channel, and at the floor the watcher drops them and
/// ends the stream. When the client reads again, the stream ends cleanly without `done` (an
/// EventSource reconnects with `Last-Event-ID`) while the job still runs. Without the floor
/// the stream would go on for the job's 5000 steps.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_sse_watcher_that_stops_reading_is_cut_off_with_a_reconnectable_close() {
    let _serial = SERIAL.lock().await;
    let client = reqwest::Client::new();
    let (addr, stop, _) = start(watch_options()).await;
    let base = format!("http://{addr}");
    let id = running_job(&client, &base).await;

    let tcp = TcpStream::connect(&addr).await.expect("connect");
    let (h2, conn) = h2::client::handshake(tcp).await.expect("h2 handshake");
    tokio::spawn(conn);
    let mut h2 = h2.ready().await.expect("stream slot");
    let req = axum::http::Request::get(format!("{base}/v1/jobs/{id}/events"))
        .body(())
        .expect("request");
    let (response, _) = h2.send_request(req, true).expect("request sent");
    let response = response.await.expect("response head");
    assert_eq!(response.status(), 200);
    let mut body = response.into_body();
    tokio::time::sleep(UNREAD).await;

    let mut text = Vec::new();
    let read_all = async {
        while let Some(chunk) = body.data().await {
            let chunk = chunk.expect("a clean end, not a reset");
            let _ = body.flow_control().release_capacity(chunk.len());
            text.extend_from_slice(&chunk);
        }
    };
    tokio::time::timeout(Duration::from_secs(30), read_all)
        .await
        .expect("the stream of a watcher that stopped reading ends");
    let text = String::from_utf8_lossy(&text);
    let frames = text.matches("event: frame").count();
    assert!(frames > 0, "some frames went out before the client stopped");
    assert!(!text.contains("event: done"), "cut off, not finished");
    let status: serde_json::Value = client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .expect("GET job")
        .json()
        .await
        .expect("job json");
    assert_eq!(status["state"], "running", "the job goes on: {status}");
    let step = status["progress"]["step"].as_u64().expect("step") as usize;
    assert!(frames < step, "{frames} frames sent of {step} steps taken");
    let _ = stop.send(());
}

/// The same over gRPC StreamFrames (a 64 KiB stream window, unread): the stream ends with
/// DEADLINE_EXCEEDED after the frames that were in flight.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_grpc_watcher_that_stops_reading_ends_with_deadline_exceeded() {
    use willow_service::api::grpc::pb::willow::v1;
    let _serial = SERIAL.lock().await;
    let client = reqwest::Client::new();
    let (addr, stop, _) = start(watch_options()).await;
    let base = format!("http://{addr}");
    let id = running_job(&client, &base).await;

    let channel = tonic::transport::Endpoint::from_shared(base.clone())
        .expect("endpoint")
        .initial_stream_window_size(Some(65_535))
        .connect()
        .await
        .expect("connect over h2c");
    let mut fairing = v1::fairing_client::FairingClient::new(channel);
    let mut stream = fairing
        .stream_frames(v1::StreamFramesRequest {
            name: format!("jobs/{id}"),
            from_step: 0,
        })
        .await
        .expect("StreamFrames")
        .into_inner();
    tokio::time::sleep(UNREAD).await;

    let mut frames = 0;
    let status = loop {
        match tokio::time::timeout(Duration::from_secs(30), stream.message()).await {
            Ok(Ok(Some(_))) => frames += 1,
            Ok(Ok(None)) => panic!("the stream ended OK after {frames} messages"),
            Ok(Err(status)) => break status,
            Err(_) => panic!("still streaming after {frames} messages: not cut off"),
        }
    };
    assert_eq!(status.code(), tonic::Code::DeadlineExceeded, "{status:?}");
    assert!(frames > 0, "the messages in flight arrive first");
    let _ = stop.send(());
}
