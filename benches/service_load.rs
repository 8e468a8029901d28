//! Load benchmark of the service, loopback only and bounded in requests and time.
//!
//! `cargo bench --bench service_load` (release numbers) or, on a machine where a release build
//! of every dependency is too slow, `cargo bench --bench service_load --profile dev`.
//!
//! Measures, against an in-process server on 127.0.0.1:0 with the real router:
//! 1. submissions per second and p50/p99 latency of submit, status and first SSE frame at 1, 8
//!    and 64 concurrent clients, on a small mesh (42 vertices, 1 step);
//! 2. service overhead on one ~13k-triangle job against the library alone (same steps; the
//!    service also persists every step's metrics and positions and fans frames out);
//! 3. memory per queued job (RSS growth while 1000 jobs wait behind a busy worker).
//!
//! Environment: `WILLOW_BENCH_STEPS` (default 10) steps for part 2;
//! `WILLOW_BENCH_MESH` a mesh file for part 2 (default: `../shared/meshes/cheburashka.obj` if
//! present, else a generated 13 056-triangle torus).

#[path = "../tests/service_http_support/mod.rs"]
mod service_http_support;

use futures::StreamExt;
use service_http_support::{obj_text, start as start_server, TestServer};
use std::time::{Duration, Instant};
use willow::mesh::io::{Asset, Format};

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

async fn throughput(obj: &str) {
    println!("## 1. Small jobs (42 vertices, 1 step): submit / status / first frame latency");
    println!("| clients | jobs | submits/s | submit p50 / p99 ms | status p50 / p99 ms | first frame p50 / p99 ms | 429s |");
    println!("|---|---|---|---|---|---|---|");
    for (clients, per_client) in [(1usize, 200usize), (8, 40), (64, 6)] {
        let srv = start(2, 10_000).await;
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
                    srv.base.clone(),
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
        println!(
            "| {clients} | {} | {:.0} (pure submit ≈ {:.0}) | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} / {:.1} | {refused} |",
            sub.len(),
            sub.len() as f64 / wall,
            clients as f64 * 1e3 / pct(&sub, 0.5).max(1e-3),
            pct(&sub, 0.5),
            pct(&sub, 0.99),
            pct(&st, 0.5),
            pct(&st, 0.99),
            pct(&ff, 0.5),
            pct(&ff, 0.99),
        );
        srv.stop().await;
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
    let params = willow::jobs::JobSpec::default().flow_params();
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
            .header("content-type", willow::jobs::format_media_type(format))
            .body(text.clone())
            .send()
            .await
            .expect("submit");
        assert_eq!(res.status(), 202, "bench job accepted");
        let v: serde_json::Value = res.json().await.expect("json");
        let id = v["id"].as_str().expect("id").to_string();
        let done = srv
            .jobs
            .wait(&id, Duration::from_secs(3600))
            .await
            .expect("wait");
        e2e_runs.push(t.elapsed().as_secs_f64());
        assert_eq!(done.state, willow::jobs::JobState::Succeeded, "{done:?}");
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
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    if std::env::var_os("RUST_LOG").is_none() {
        std::env::set_var("RUST_LOG", "warn");
    }
    willow::api::server::init_logging("text");
    rt.block_on(async {
        let small = obj_text(&willow::mesh::generate::icosphere(1));
        println!(
            "# willow service benchmark (loopback, {} cores)",
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        );
        throughput(&small).await;
        overhead(steps).await;
        memory_per_queued_job(&small).await;
    });
}

/// The real router on loopback with `workers` workers and a queue of `queue_capacity` (the
/// tests' server, sized for load).
async fn start(workers: usize, queue_capacity: usize) -> TestServer {
    start_server(|c| {
        c.workers = workers;
        c.queue_capacity = queue_capacity;
    })
    .await
}
