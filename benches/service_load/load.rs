//! Parts 1–3: throughput and latency per concurrency level, the service's overhead on one
//! large job, and memory per queued job.

use super::common::*;
use super::nats_server::NatsNode;

/// One client's loop: submit, read status, wait for the first SSE frame; `n` times.
pub(crate) async fn client_loop(
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
pub(crate) struct LoadRow {
    pub(crate) jobs: usize,
    pub(crate) rate: f64,
    pub(crate) pure: f64,
    pub(crate) submit: (f64, f64),
    pub(crate) status: (f64, f64),
    pub(crate) first: (f64, f64),
    pub(crate) refused: usize,
}

/// `clients` concurrent clients, `per_client` jobs each, against the server at `base`.
pub(crate) async fn load_level(
    base: &str,
    obj: &str,
    clients: usize,
    per_client: usize,
) -> LoadRow {
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

pub(crate) fn load_cells(r: &LoadRow) -> String {
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

pub(crate) async fn throughput(obj: &str) {
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

pub(crate) fn big_mesh() -> (String, Format, String) {
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

pub(crate) async fn overhead(steps: usize) {
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

pub(crate) async fn memory_per_queued_job(obj_small: &str) {
    println!();
    println!("## 3. Memory per queued job");
    let srv = start(1, 5_000).await;
    let client = reqwest::Client::new();
    // Occupy the only worker with a long job so the others stay queued.
    let long = obj_text(&willow::mesh::generate::bumpy_sphere(4, 0.1));
    let res = client
        .post(format!(
            "{}/v1/jobs?steps=10000&until_converged=false",
            srv.base
        ))
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
