//! Processes for the multi-process tests of the NATS JetStream backend (tests/service_nats/):
//! a nats-server of the test's own on loopback, and `willow serve` nodes (roles api, worker,
//! all) pointed at it, each a child process killed and reaped when its guard drops, so that a
//! failing test leaves nothing running. Logs go to files in the test's temp dir; a guard
//! dropped while its test panics prints the end of its log.
//!
//! The nats-server binary is `$WILLOW_NATS_SERVER` when set, else whatever
//! `scripts/nats-server.sh --print-path` prints (it installs the pinned release on first use).
#![allow(dead_code)]

use crate::service_http_support::Sse;
use futures::StreamExt;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// Upper bound on anything a test waits for: generous for a loaded 2-core machine, finite so
/// that a hang fails instead of blocking the suite.
pub const PATIENCE: Duration = Duration::from_secs(90);

/// Lines of a process's log printed when its test fails.
const LOG_TAIL_LINES: usize = 60;

// ---------------------------------------------------------------------------------------------
// nats-server

/// The nats-server binary: `$WILLOW_NATS_SERVER`, or the project's pinned one (installed by
/// scripts/nats-server.sh on first use). Resolved once per test binary.
pub fn nats_server_bin() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| {
        if let Some(p) = std::env::var_os("WILLOW_NATS_SERVER").filter(|p| !p.is_empty()) {
            return PathBuf::from(p);
        }
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/nats-server.sh");
        let out = Command::new("bash")
            .arg(&script)
            .arg("--print-path")
            .stdin(Stdio::null())
            .stderr(Stdio::inherit())
            .output()
            .unwrap_or_else(|e| panic!("run {}: {e}", script.display()));
        assert!(
            out.status.success(),
            "{} --print-path failed: {:?}",
            script.display(),
            out.status
        );
        let path = String::from_utf8(out.stdout).expect("UTF-8 path");
        PathBuf::from(path.trim())
    })
    .clone()
}

/// A port on 127.0.0.1 that was free a moment ago (bound to :0, then released).
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .expect("bind 127.0.0.1:0")
        .local_addr()
        .expect("local addr")
        .port()
}

/// The last `n` lines of a file (empty if it cannot be read).
pub fn tail(path: &Path, n: usize) -> String {
    let mut text = String::new();
    if let Ok(mut f) = File::open(path) {
        let _ = f.read_to_string(&mut text);
    }
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

fn print_tail(what: &str, path: &Path) {
    eprintln!(
        "----- {what}: last {LOG_TAIL_LINES} lines of {} -----\n{}\n----- end of {what} -----",
        path.display(),
        tail(path, LOG_TAIL_LINES)
    );
}

/// SIGTERM (through kill(1): no libc in this crate's dependencies).
pub fn sigterm(child: &Child) {
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .expect("kill -TERM");
    assert!(status.success(), "kill -TERM {}", child.id());
}

/// Wait for a child to exit, at most `timeout`; SIGKILL it after that.
pub fn wait_or_kill(child: &mut Child, timeout: Duration) -> Option<std::process::ExitStatus> {
    let deadline = Instant::now() + timeout;
    loop {
        match child.try_wait() {
            Ok(Some(status)) => return Some(status),
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
            _ => {
                let _ = child.kill();
                let _ = child.wait();
                return None;
            }
        }
    }
}

/// A nats-server with JetStream and a file store, on loopback, owned by one test. Dropping it
/// kills it.
pub struct Nats {
    child: Option<Child>,
    /// Client port (kept across restarts).
    pub port: u16,
    /// HTTP monitoring port (`/varz`, `/jsz`).
    pub monitor_port: u16,
    store: PathBuf,
    dir: PathBuf,
    starts: usize,
    log: PathBuf,
    /// Settings of the `jetstream { … }` block of a config file (`-c`), e.g.
    /// `max_file_store: 8MB`, which no command-line flag sets; `None`: flags only.
    jetstream_config: Option<String>,
}

impl Nats {
    /// Start a nats-server on free loopback ports with its store in `dir/nats-store`.
    pub fn start(dir: &Path) -> Nats {
        Nats::start_with(dir, None)
    }

    /// [`Nats::start`] with JetStream limited to `max_file_store` bytes of file storage
    /// (over the whole server: every stream's messages count, as nats-server accounts them).
    pub fn start_with_max_file_store(dir: &Path, max_file_store: u64) -> Nats {
        Nats::start_with(dir, Some(format!("max_file_store: {max_file_store}")))
    }

    fn start_with(dir: &Path, jetstream_config: Option<String>) -> Nats {
        let mut nats = Nats {
            child: None,
            port: 0,
            monitor_port: 0,
            store: dir.join("nats-store"),
            dir: dir.to_path_buf(),
            starts: 0,
            log: PathBuf::new(),
            jetstream_config,
        };
        // A port picked by binding :0 could be taken again before nats-server binds it: try
        // a few times.
        let mut last = String::new();
        for _ in 0..5 {
            nats.port = free_port();
            nats.monitor_port = free_port();
            match nats.spawn() {
                Ok(()) => return nats,
                Err(e) => last = e,
            }
        }
        panic!("nats-server did not start: {last}");
    }

    /// `nats://127.0.0.1:PORT`, the `--backend` of the willow nodes.
    pub fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    pub fn is_running(&mut self) -> bool {
        matches!(self.child.as_mut().map(|c| c.try_wait()), Some(Ok(None)))
    }

    fn spawn(&mut self) -> Result<(), String> {
        assert!(self.child.is_none(), "nats-server is already running");
        self.starts += 1;
        self.log = self.dir.join(format!("nats-{}.log", self.starts));
        let log = File::create(&self.log).expect("nats log file");
        let bin = nats_server_bin();
        let mut command = Command::new(&bin);
        if let Some(settings) = &self.jetstream_config {
            // The flags below set the address, ports and store dir (`-sd`: a `store_dir`
            // here too is refused as a duplicate); the file adds what only a config can say.
            let conf = self.dir.join("nats.conf");
            let text = format!("jetstream {{\n  {settings}\n}}\n");
            std::fs::write(&conf, text).expect("write nats.conf");
            command.arg("-c").arg(&conf);
        }
        let mut child = command
            .args(["-a", "127.0.0.1", "-p", &self.port.to_string()])
            .args(["-m", &self.monitor_port.to_string()])
            .arg("-js")
            .arg("-sd")
            .arg(&self.store)
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("clone log file"))
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("spawn {}: {e}", bin.display()));
        // Ready when it accepts TCP and greets with INFO (JetStream is up by then).
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Ok(Some(status)) = child.try_wait() {
                let why = format!(
                    "nats-server exited with {status}:\n{}",
                    tail(&self.log, LOG_TAIL_LINES)
                );
                return Err(why);
            }
            if let Some(info) = nats_info(self.port) {
                assert!(
                    info.contains("\"jetstream\":true"),
                    "nats-server without JetStream: {info}"
                );
                self.child = Some(child);
                return Ok(());
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                return Err(format!(
                    "nats-server did not accept connections in 30 s:\n{}",
                    tail(&self.log, LOG_TAIL_LINES)
                ));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// SIGKILL, and reap.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM (nats-server shuts down cleanly), and reap.
    pub fn terminate(&mut self) {
        if let Some(mut c) = self.child.take() {
            sigterm(&c);
            wait_or_kill(&mut c, Duration::from_secs(20));
        }
    }

    /// Start again on the same ports with the same store (after `kill` or `terminate`).
    pub fn restart(&mut self) {
        // The old process released the port when it died; retry briefly in case the kernel
        // has not let go of it yet.
        let mut last = String::new();
        for _ in 0..20 {
            match self.spawn() {
                Ok(()) => return,
                Err(e) => last = e,
            }
            std::thread::sleep(Duration::from_millis(250));
        }
        panic!("nats-server did not restart on port {}: {last}", self.port);
    }

    /// A monitoring endpoint's JSON (`varz`, `jsz?consumers=true`, …).
    pub async fn monitor(&self, path: &str) -> serde_json::Value {
        reqwest::get(format!("http://127.0.0.1:{}/{path}", self.monitor_port))
            .await
            .expect("nats monitoring")
            .json()
            .await
            .expect("nats monitoring JSON")
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.kill();
        if std::thread::panicking() {
            for start in 1..=self.starts {
                let log = self.dir.join(format!("nats-{start}.log"));
                print_tail(&format!("nats-server (start {start})"), &log);
            }
        }
    }
}

/// The INFO line a NATS server sends on connect, if one answers on `port`.
pub fn nats_info(port: u16) -> Option<String> {
    let stream = TcpStream::connect_timeout(
        &std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        Duration::from_millis(500),
    )
    .ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(2))).ok()?;
    let mut line = String::new();
    BufReader::new(&stream).read_line(&mut line).ok()?;
    line.starts_with("INFO ").then_some(line)
}

// ---------------------------------------------------------------------------------------------
// willow serve

/// How a node is started.
#[derive(Clone, Debug)]
pub struct NodeOpts {
    /// `api`, `worker` or `all`; `None` for an embedded node (no `--backend`, no `--role`).
    pub role: Option<&'static str>,
    pub workers: usize,
    pub queue_capacity: usize,
    pub checkpoint_steps: usize,
    /// `--nats-ack-wait-secs` (NATS nodes only).
    pub ack_wait_secs: u64,
    pub grace_secs: f64,
    /// `--max-deliveries`.
    pub max_deliveries: u32,
    /// More flags, as given.
    pub extra: Vec<String>,
}

impl NodeOpts {
    pub fn api() -> NodeOpts {
        NodeOpts {
            role: Some("api"),
            ..NodeOpts::embedded()
        }
    }

    pub fn worker() -> NodeOpts {
        NodeOpts {
            role: Some("worker"),
            ..NodeOpts::embedded()
        }
    }

    pub fn all() -> NodeOpts {
        NodeOpts {
            role: Some("all"),
            ..NodeOpts::embedded()
        }
    }

    /// The default backend (SQLite and files in the node's data dir), one worker.
    pub fn embedded() -> NodeOpts {
        NodeOpts {
            role: None,
            workers: 1,
            queue_capacity: 8,
            checkpoint_steps: 10,
            ack_wait_secs: 3,
            grace_secs: 2.0,
            max_deliveries: 3,
            extra: Vec::new(),
        }
    }

    /// One more flag (or flag value) on the command line.
    pub fn arg(mut self, a: impl Into<String>) -> NodeOpts {
        self.extra.push(a.into());
        self
    }

    pub fn queue_capacity(mut self, n: usize) -> NodeOpts {
        self.queue_capacity = n;
        self
    }

    pub fn checkpoint_steps(mut self, n: usize) -> NodeOpts {
        self.checkpoint_steps = n;
        self
    }

    pub fn ack_wait_secs(mut self, s: u64) -> NodeOpts {
        self.ack_wait_secs = s;
        self
    }

    pub fn max_deliveries(mut self, n: u32) -> NodeOpts {
        self.max_deliveries = n;
        self
    }
}

/// A `willow serve` child process. Dropping it kills it.
pub struct Node {
    child: Option<Child>,
    pub name: String,
    /// `http://127.0.0.1:PORT`
    pub base: String,
    pub log: PathBuf,
    pub client: reqwest::Client,
}

impl Node {
    /// Start `willow serve` named `name` (its data dir and log are `dir/NAME-data`,
    /// `dir/NAME.log`) against `backend` (`None`: the embedded backend); returns once it
    /// printed its address. `RUST_LOG=info`, JSON logs.
    pub fn spawn(dir: &Path, name: &str, backend: Option<&str>, opts: &NodeOpts) -> Node {
        let data = dir.join(format!("{name}-data"));
        let log = dir.join(format!("{name}.log"));
        // Logs (stdout, where the tracing subscriber writes) and stderr (clap's errors, panics)
        // both go to the node's log file.
        let log_file = File::create(&log).expect("node log file");
        let mut log_out = log_file.try_clone().expect("clone log file");
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_willow"));
        cmd.args(["serve", "--addr", "127.0.0.1:0"])
            .arg("--data-dir")
            .arg(&data)
            .args(["--queue-capacity", &opts.queue_capacity.to_string()])
            .args(["--checkpoint-steps", &opts.checkpoint_steps.to_string()])
            .args(["--grace-secs", &opts.grace_secs.to_string()])
            .args(["--max-deliveries", &opts.max_deliveries.to_string()])
            .args(["--log-format", "json"]);
        if opts.role != Some("api") {
            cmd.args(["--workers", &opts.workers.to_string()]);
        }
        if let Some(backend) = backend {
            cmd.args(["--backend", backend]);
            cmd.args(["--nats-ack-wait-secs", &opts.ack_wait_secs.to_string()]);
        }
        if let Some(role) = opts.role {
            cmd.args(["--role", role]);
        }
        cmd.args(&opts.extra);
        let mut child = cmd
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log_file)
            .spawn()
            .expect("spawn willow serve");
        let stdout = child.stdout.take().expect("piped stdout");
        let (tx, rx) = std::sync::mpsc::channel();
        // Reads stdout to its end (the pipe closes when the process dies), so the child never
        // blocks on a full pipe, and copies it into the log.
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = writeln!(log_out, "{line}");
                if let Some(url) = line.strip_prefix("listening on ") {
                    let _ = tx.send(url.trim().to_string());
                }
            }
        });
        let base = match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(base) => base,
            Err(e) => {
                let status = match child.try_wait() {
                    Ok(Some(s)) => format!("exited with {s}"),
                    _ => "still running".to_string(),
                };
                let _ = child.kill();
                let _ = child.wait();
                panic!(
                    "willow serve {name} printed no address ({e}; {status}); its log:\n{}",
                    tail(&log, LOG_TAIL_LINES)
                );
            }
        };
        Node {
            child: Some(child),
            name: name.to_string(),
            base,
            log,
            client: reqwest::Client::new(),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    /// gRPC endpoint (same port).
    pub fn grpc_uri(&self) -> String {
        self.base.clone()
    }

    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// SIGKILL, and reap.
    pub fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// SIGTERM, and wait for the exit (SIGKILL after `timeout`); the exit status if it exited
    /// by itself.
    pub fn terminate(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let mut c = self.child.take()?;
        sigterm(&c);
        wait_or_kill(&mut c, timeout)
    }

    /// HTTP status of `/readyz`, or `None` if the node does not answer.
    pub async fn readyz(&self) -> Option<u16> {
        let res = self
            .client
            .get(self.url("/readyz"))
            .timeout(Duration::from_secs(5))
            .send()
            .await
            .ok()?;
        Some(res.status().as_u16())
    }

    /// Wait until `/readyz` answers `status`; panics with the node's log after `timeout`.
    pub async fn wait_readyz(&self, status: u16, timeout: Duration) {
        let start = Instant::now();
        let mut last = None;
        while start.elapsed() < timeout {
            last = self.readyz().await;
            if last == Some(status) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        panic!(
            "{}: /readyz did not answer {status} in {timeout:?} (last: {last:?})",
            self.name
        );
    }

    /// `/metrics` text.
    pub async fn metrics(&self) -> String {
        self.client
            .get(self.url("/metrics"))
            .send()
            .await
            .unwrap_or_else(|e| panic!("{}: GET /metrics: {e}", self.name))
            .text()
            .await
            .expect("metrics text")
    }

    /// Wait until `metric(name, labels)` of this node is `want` (a job's counters and gauges
    /// may move just after its state does); panics with the metrics after `timeout`.
    pub async fn wait_metric(
        &self,
        name: &str,
        labels: &[(&str, &str)],
        want: f64,
        timeout: Duration,
    ) {
        let start = Instant::now();
        loop {
            let text = self.metrics().await;
            if metric(&text, name, labels) == Some(want) {
                return;
            }
            if start.elapsed() > timeout {
                panic!(
                    "{}: {name} {labels:?} is not {want} after {timeout:?}:\n{text}",
                    self.name
                );
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// POST an OBJ with query parameters; (status, headers, JSON body).
    pub async fn submit_obj(
        &self,
        obj: &str,
        query: &str,
        idempotency_key: Option<&str>,
    ) -> (
        reqwest::StatusCode,
        reqwest::header::HeaderMap,
        serde_json::Value,
    ) {
        let mut req = self
            .client
            .post(self.url(&format!(
                "/v1/jobs?{}",
                crate::service_http_support::conformal_unless_named(query)
            )))
            .header("content-type", "model/obj")
            .body(obj.to_string());
        if let Some(key) = idempotency_key {
            req = req.header("Idempotency-Key", key);
        }
        let res = req
            .send()
            .await
            .unwrap_or_else(|e| panic!("{}: POST /v1/jobs: {e}", self.name));
        let status = res.status();
        let headers = res.headers().clone();
        let json = res.json().await.unwrap_or(serde_json::Value::Null);
        (status, headers, json)
    }

    /// Submit, expect 202; the job id.
    pub async fn submit(&self, obj: &str, query: &str) -> String {
        let (status, _, job) = self.submit_obj(obj, query, None).await;
        assert_eq!(status, 202, "{}: submit {query}: {job}", self.name);
        job["id"].as_str().expect("job id").to_string()
    }

    /// GET a JSON resource; (status, body).
    pub async fn get_json(&self, path: &str) -> (reqwest::StatusCode, serde_json::Value) {
        let res = self
            .client
            .get(self.url(path))
            .send()
            .await
            .unwrap_or_else(|e| panic!("{}: GET {path}: {e}", self.name));
        let status = res.status();
        (status, res.json().await.unwrap_or(serde_json::Value::Null))
    }

    /// Poll a job on this node until `pred` holds (panics after `PATIENCE`).
    pub async fn poll_until(
        &self,
        id: &str,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        crate::service_http_support::poll_until(&self.client, &self.base, id, PATIENCE, pred).await
    }

    /// The steps listed by `/v1/jobs/{id}/frames`.
    pub async fn frame_list(&self, id: &str) -> Vec<u64> {
        let (status, frames) = self
            .get_json(&format!("/v1/jobs/{id}/frames?page_size=10000"))
            .await;
        assert_eq!(status, 200, "{}: frames of {id}: {frames}", self.name);
        frames["frames"]
            .as_array()
            .expect("frames array")
            .iter()
            .map(|f| f["step"].as_u64().expect("frame step"))
            .collect()
    }

    /// The OBJ result of a finished job.
    pub async fn result_obj(&self, id: &str) -> String {
        let res = self
            .client
            .get(self.url(&format!("/v1/jobs/{id}/result?format=obj")))
            .send()
            .await
            .expect("GET result");
        assert_eq!(res.status(), 200, "{}: result of {id}", self.name);
        res.text().await.expect("OBJ text")
    }

    /// Open `/v1/jobs/{id}/events` (with `Last-Event-ID` if given).
    pub async fn events(&self, id: &str, last_event_id: Option<u64>) -> SseStream {
        let mut req = self.client.get(self.url(&format!("/v1/jobs/{id}/events")));
        if let Some(last) = last_event_id {
            req = req.header("Last-Event-ID", last.to_string());
        }
        let res = req
            .send()
            .await
            .unwrap_or_else(|e| panic!("{}: GET events of {id}: {e}", self.name));
        assert_eq!(res.status(), 200, "{}: events of {id}", self.name);
        SseStream::new(res)
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        self.kill();
        if std::thread::panicking() {
            print_tail(&format!("willow {}", self.name), &self.log);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Metrics

/// Sum of the samples of metric `name` (exact name, e.g. `willow_jobs_resumed_total`) whose
/// labels include every pair of `labels`; `None` if no sample matches.
pub fn metric(text: &str, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    let mut sum = None;
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let Some((series, value)) = line.rsplit_once(' ') else {
            continue;
        };
        let (metric_name, label_text) = match series.split_once('{') {
            Some((n, rest)) => (n, rest.trim_end_matches('}')),
            None => (series, ""),
        };
        if metric_name != name {
            continue;
        }
        let have: BTreeMap<&str, &str> = label_text
            .split(',')
            .filter_map(|kv| kv.split_once('='))
            .map(|(k, v)| (k.trim(), v.trim().trim_matches('"')))
            .collect();
        if labels.iter().all(|(k, v)| have.get(k) == Some(v)) {
            if let Ok(v) = value.trim().parse::<f64>() {
                *sum.get_or_insert(0.0) += v;
            }
        }
    }
    sum
}

// ---------------------------------------------------------------------------------------------
// Server-Sent Events, read as they come

type ByteStream = Pin<Box<dyn futures::Stream<Item = reqwest::Result<bytes::Bytes>> + Send>>;

/// An open SSE response, read one event at a time.
pub struct SseStream {
    stream: ByteStream,
    buf: String,
}

/// What reading the next event gave.
#[derive(Debug)]
pub enum SseNext {
    Event(Sse),
    /// The server closed the stream.
    End,
    /// The connection broke (e.g. the node died).
    Broken(String),
    TimedOut,
}

impl SseStream {
    pub fn new(res: reqwest::Response) -> SseStream {
        SseStream {
            stream: Box::pin(res.bytes_stream()),
            buf: String::new(),
        }
    }

    /// The next event (keep-alive comments skipped), waiting at most `timeout`.
    pub async fn next(&mut self, timeout: Duration) -> SseNext {
        let deadline = Instant::now() + timeout;
        loop {
            while let Some(end) = self.buf.find("\n\n") {
                let block: String = self.buf.drain(..end + 2).collect();
                if let Some(event) = crate::service_http_support::parse_sse_block(&block) {
                    return SseNext::Event(event);
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, self.stream.next()).await {
                Ok(Some(Ok(chunk))) => self
                    .buf
                    .push_str(&String::from_utf8_lossy(&chunk).replace("\r\n", "\n")),
                Ok(Some(Err(e))) => return SseNext::Broken(e.to_string()),
                Ok(None) => return SseNext::End,
                Err(_) => return SseNext::TimedOut,
            }
        }
    }

    /// Every event until `done` (included); panics if the stream ends, breaks or times out
    /// first.
    pub async fn until_done(&mut self, timeout: Duration) -> Vec<Sse> {
        let deadline = Instant::now() + timeout;
        let mut out = Vec::new();
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.next(left).await {
                SseNext::Event(e) => {
                    let done = e.event == "done";
                    out.push(e);
                    if done {
                        return out;
                    }
                }
                other => panic!(
                    "SSE ended before `done` ({other:?}); frame steps so far: {:?}",
                    crate::service_http_support::frame_steps(&out)
                ),
            }
        }
    }
}
