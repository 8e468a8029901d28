//! The NATS JetStream backend with real processes: each test starts a nats-server of its own
//! (loopback, free ports, JetStream with a file store in the test's temp dir) and several
//! `willow serve --backend nats://…` nodes in roles `api` and `worker`, then checks what a
//! client of the cluster sees when it submits to one node and watches, polls, cancels or
//! downloads through another, and when a worker, an API node or nats-server itself dies
//! mid-job.
//!
//! nats-server is `$WILLOW_NATS_SERVER`, or the pinned release that scripts/nats-server.sh
//! installs under target/ on first use. Every child process is killed when its guard drops, and
//! a failing test prints the end of each process's log (nodes run with `RUST_LOG=info`).

mod nats_support;
mod service_http_support;

use nats_support::*;
use service_http_support::{frame_steps, is_terminal, slow_obj, small_obj, Sse};
use std::path::Path;
use std::time::{Duration, Instant};

/// How long a job's metrics may lag behind its state.
const METRIC_PATIENCE: Duration = Duration::from_secs(10);

/// The `frame` events' steps, checking that each event's SSE id is its step.
fn checked_frame_steps(events: &[Sse]) -> Vec<u64> {
    for e in events.iter().filter(|e| e.event == "frame") {
        assert_eq!(
            e.id.as_deref().and_then(|id| id.parse::<u64>().ok()),
            e.data["step"].as_u64(),
            "a frame's SSE id is its step: {e:?}"
        );
    }
    frame_steps(events)
}

fn steps(range: std::ops::RangeInclusive<u64>) -> Vec<u64> {
    range.collect()
}

/// The outcome of the last event, which must be `done`.
fn done_state(events: &[Sse]) -> String {
    let last = events.last().expect("some events");
    assert_eq!(last.event, "done", "the stream ends with `done`");
    last.data["state"].as_str().unwrap_or_default().to_string()
}

/// Start a cluster's nodes and wait until each is ready (connected to NATS).
async fn all_ready(nodes: &[&Node]) {
    for n in nodes {
        n.wait_readyz(200, PATIENCE).await;
    }
}

/// `willow_jobs_finished_total{outcome=…}` of a node (0 when absent).
async fn finished(node: &Node, outcome: &str) -> f64 {
    metric(
        &node.metrics().await,
        "willow_jobs_finished_total",
        &[("outcome", outcome)],
    )
    .unwrap_or(0.0)
}

// ---------------------------------------------------------------------------------------------

/// The harness itself: nats-server starts with JetStream on its own ports and store, a
/// SIGKILLed one restarts on the same port, and dropping the guard kills the process.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_server_harness_starts_restarts_and_cleans_up() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut nats = Nats::start(dir.path());
    let port = nats.port;
    let varz = nats.monitor("varz").await;
    assert_eq!(varz["port"], port, "{varz}");
    let store = varz["jetstream"]["config"]["store_dir"]
        .as_str()
        .expect("JetStream store dir")
        .to_string();
    assert!(
        store.starts_with(&dir.path().display().to_string()),
        "the store is in the test's dir: {store}"
    );

    nats.kill();
    assert!(nats_info(port).is_none(), "nothing answers after SIGKILL");
    nats.restart();
    assert_eq!(nats.port, port);
    let info = nats_info(port).expect("answers again on the same port");
    assert!(info.contains("\"jetstream\":true"), "{info}");

    nats.terminate();
    assert!(nats_info(port).is_none(), "nothing answers after SIGTERM");
    nats.restart();
    assert!(nats.is_running());
    let pid = nats.pid().expect("pid");
    drop(nats);
    assert!(
        !Path::new(&format!("/proc/{pid}")).exists(),
        "dropping the guard killed and reaped nats-server {pid}"
    );
    assert!(nats_info(port).is_none());
}

/// Submit through API A, watch through API B (every step once, in order, then `done`), poll
/// through both, and download through B exactly what an embedded server computes from the same
/// input and parameters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_api_nodes_two_workers_submit_on_one_watch_and_fetch_on_the_other() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let embedded = Node::spawn(d, "embedded", None, &NodeOpts::embedded());
    let api_a = Node::spawn(d, "api-a", Some(&url), &NodeOpts::api());
    let api_b = Node::spawn(d, "api-b", Some(&url), &NodeOpts::api());
    let w1 = Node::spawn(d, "worker-1", Some(&url), &NodeOpts::worker());
    let w2 = Node::spawn(d, "worker-2", Some(&url), &NodeOpts::worker());
    all_ready(&[&api_a, &api_b, &w1, &w2, &embedded]).await;

    let obj = small_obj();
    let query = "steps=10";
    let id = api_a.submit(&obj, query).await;
    // Watched on B from the start (live or replayed, whichever it is by then).
    let events = api_b.events(&id, None).await.until_done(PATIENCE).await;
    assert_eq!(checked_frame_steps(&events), steps(0..=10));
    assert_eq!(done_state(&events), "succeeded", "{:?}", events.last());

    let va = api_a.poll_until(&id, is_terminal).await;
    let vb = api_b.poll_until(&id, is_terminal).await;
    assert_eq!(va["state"], "succeeded", "{va}");
    for key in [
        "id",
        "state",
        "progress",
        "params",
        "created_time",
        "started_time",
        "finished_time",
    ] {
        assert_eq!(
            va[key], vb[key],
            "{key} differs between A and B:\n{va}\n{vb}"
        );
    }
    assert_eq!(va["progress"]["step"], 10, "{va}");
    assert_eq!(api_a.frame_list(&id).await, steps(0..=10));
    assert_eq!(api_b.frame_list(&id).await, steps(0..=10));

    // The same job on an embedded server gives the same bytes.
    let reference = embedded.submit(&obj, query).await;
    let v = embedded.poll_until(&reference, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    let expected = embedded.result_obj(&reference).await;
    let got = api_b.result_obj(&id).await;
    assert!(
        got == expected,
        "the OBJ from B differs from the embedded server's"
    );
    assert!(api_a.result_obj(&id).await == expected);

    // It ran once, on one of the workers.
    let start = Instant::now();
    loop {
        let runs = finished(&w1, "succeeded").await + finished(&w2, "succeeded").await;
        if runs == 1.0 {
            break;
        }
        assert!(
            runs < 1.0 && start.elapsed() < METRIC_PATIENCE,
            "{runs} runs over both workers, want 1"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A worker is SIGKILLed mid-job; after the ack wait the other worker gets the job, resumes it
/// from its last checkpoint and finishes it. A watcher connected across the crash sees each
/// step once and in order; the job's frames are exactly 0..=N.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_worker_mid_job_the_other_resumes_from_its_checkpoint() {
    // About 25 ms a step unloaded: a few seconds of work, positions every 20th frame.
    const N: u64 = 120;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.checkpoint_steps(2).ack_wait_secs(3);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let mut workers = vec![
        Node::spawn(d, "worker-1", Some(&url), &opts(NodeOpts::worker())),
        Node::spawn(d, "worker-2", Some(&url), &opts(NodeOpts::worker())),
    ];
    all_ready(&[&api, &workers[0], &workers[1]]).await;

    let id = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    let mut sse = api.events(&id, None).await;
    let watcher = tokio::spawn(async move { sse.until_done(PATIENCE * 2).await });

    let before = api
        .poll_until(&id, |v| {
            v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 5
        })
        .await;
    // The worker running it reports one running job, the other none.
    let start = Instant::now();
    let victim = loop {
        let mut running = Vec::new();
        for w in &workers {
            running.push(metric(&w.metrics().await, "willow_jobs_running", &[]));
        }
        match running[..] {
            [Some(1.0), Some(0.0)] => break 0,
            [Some(0.0), Some(1.0)] => break 1,
            _ if start.elapsed() > PATIENCE => {
                panic!("no single worker reports willow_jobs_running 1: {running:?}")
            }
            _ => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    };
    let at_kill = api.get_json(&format!("/v1/jobs/{id}")).await.1;
    assert_eq!(
        at_kill["state"], "running",
        "still running when its worker dies (make the job longer?): {at_kill}"
    );
    workers[victim].kill();
    let survivor = &workers[1 - victim];

    // Never back to step 0 while it finishes elsewhere.
    let seen = std::sync::Mutex::new(Vec::new());
    let done = api
        .poll_until(&id, |v| {
            if let Some(s) = v["progress"]["step"].as_u64() {
                seen.lock().unwrap().push(s);
            }
            is_terminal(v)
        })
        .await;
    let seen = seen.into_inner().unwrap();
    assert!(
        seen.iter().all(|&s| s > 0),
        "after the crash the job goes on from a checkpoint, not from step 0: {seen:?}"
    );
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"]["step"], N, "{done}");
    assert_eq!(api.frame_list(&id).await, steps(0..=N));

    let events = watcher.await.expect("watcher task");
    assert_eq!(
        checked_frame_steps(&events),
        steps(0..=N),
        "the watcher across the crash sees each step once, in order"
    );
    assert_eq!(done_state(&events), "succeeded");

    survivor
        .wait_metric("willow_jobs_resumed_total", &[], 1.0, METRIC_PATIENCE)
        .await;
    survivor
        .wait_metric(
            "willow_jobs_finished_total",
            &[("outcome", "succeeded")],
            1.0,
            METRIC_PATIENCE,
        )
        .await;
    // As with the embedded backend's crash recovery.
    assert_eq!(
        done["started_time"], before["started_time"],
        "it has been running since its first start"
    );
}

/// The API node serving a watcher's stream is SIGKILLed mid-job; the watcher reconnects to the
/// other API node with `Last-Event-ID` and gets the rest: every later step once, then `done`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_api_node_mid_stream_then_last_event_id_on_the_other() {
    const N: u64 = 100;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let mut api_a = Node::spawn(d, "api-a", Some(&url), &NodeOpts::api());
    let api_b = Node::spawn(d, "api-b", Some(&url), &NodeOpts::api());
    let worker = Node::spawn(d, "worker", Some(&url), &NodeOpts::worker());
    all_ready(&[&api_a, &api_b, &worker]).await;

    let id = api_a
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    let mut sse = api_a.events(&id, None).await;
    let mut seen: Vec<Sse> = Vec::new();
    while checked_frame_steps(&seen).last().is_none_or(|&s| s < 3) {
        match sse.next(PATIENCE).await {
            SseNext::Event(e) => {
                assert_ne!(
                    e.event, "done",
                    "the job ended before the kill: make it longer"
                );
                seen.push(e);
            }
            other => panic!("stream from A ended early: {other:?}"),
        }
    }
    api_a.kill();
    // What was already on the wire is still read; then the stream breaks or ends.
    loop {
        match sse.next(Duration::from_secs(10)).await {
            SseNext::Event(e) => seen.push(e),
            SseNext::End | SseNext::Broken(_) => break,
            SseNext::TimedOut => panic!("the stream from a killed node stays open"),
        }
    }
    assert!(
        seen.iter().all(|e| e.event != "done"),
        "the job ended before the kill: make it longer"
    );
    let before = checked_frame_steps(&seen);
    let last = *before.last().expect("a frame");
    assert_eq!(before, steps(0..=last), "from A: each step once, in order");
    let (_, v) = api_b.get_json(&format!("/v1/jobs/{id}")).await;
    assert!(
        matches!(v["state"].as_str(), Some("running" | "queued")),
        "the job is unaffected by the API node's death: {v}"
    );

    let rest = api_b
        .events(&id, Some(last))
        .await
        .until_done(PATIENCE)
        .await;
    assert_eq!(
        checked_frame_steps(&rest),
        steps(last + 1..=N),
        "from B after Last-Event-ID {last}"
    );
    assert_eq!(done_state(&rest), "succeeded");
}

/// nats-server (file store) is SIGKILLed with one job running and three waiting behind it on
/// the only worker, then started again on the same port and store: readiness goes 503 while
/// NATS is away and back to 200, and every accepted job succeeds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_server_restart_every_accepted_job_completes() {
    const N: u64 = 100;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let mut nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.checkpoint_steps(2).ack_wait_secs(3);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let worker = Node::spawn(d, "worker", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api, &worker]).await;

    let slow = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    let mut queued = Vec::new();
    for s in 2..5 {
        queued.push(api.submit(&small_obj(), &format!("steps={s}")).await);
    }
    api.poll_until(&slow, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 2
    })
    .await;

    nats.kill();
    api.wait_readyz(503, Duration::from_secs(30)).await;
    worker.wait_readyz(503, Duration::from_secs(30)).await;
    nats.restart();
    api.wait_readyz(200, PATIENCE).await;
    worker.wait_readyz(200, PATIENCE).await;

    for (id, steps_wanted) in std::iter::once((&slow, N)).chain(queued.iter().zip(2..5)) {
        let v = api.poll_until(id, is_terminal).await;
        assert_eq!(v["state"], "succeeded", "{v}");
        assert_eq!(v["progress"]["step"], steps_wanted, "{v}");
    }
    assert_eq!(
        api.frame_list(&slow).await,
        steps(0..=N),
        "the job running across the outage kept every frame"
    );
}

/// A job submitted through API A runs on the worker; cancelling it through API B stops it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_through_api_b_a_job_running_from_api_a() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let api_a = Node::spawn(d, "api-a", Some(&url), &NodeOpts::api());
    let api_b = Node::spawn(d, "api-b", Some(&url), &NodeOpts::api());
    let worker = Node::spawn(d, "worker", Some(&url), &NodeOpts::worker());
    all_ready(&[&api_a, &api_b, &worker]).await;

    let id = api_a
        .submit(&slow_obj(), "steps=5000&until_converged=false")
        .await;
    api_a
        .poll_until(&id, |v| {
            v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 1
        })
        .await;
    let res = api_b
        .client
        .post(api_b.url(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .await
        .expect("cancel through B");
    assert_eq!(res.status(), 202);

    let v = api_a.poll_until(&id, is_terminal).await;
    assert_eq!(v["state"], "cancelled", "{v}");
    assert_eq!(v["error_code"], "cancelled", "{v}");
    let step = v["progress"]["step"].as_u64().expect("step");
    assert!(step < 5000, "stopped early, at step {step}");
    let vb = api_b.poll_until(&id, is_terminal).await;
    assert_eq!(vb["state"], "cancelled", "{vb}");

    // The worker let go of it and takes the next job.
    let next = api_b.submit(&small_obj(), "steps=2").await;
    let v = api_b.poll_until(&next, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    worker
        .wait_metric("willow_jobs_running", &[], 0.0, METRIC_PATIENCE)
        .await;
    worker
        .wait_metric(
            "willow_jobs_finished_total",
            &[("outcome", "cancelled")],
            1.0,
            METRIC_PATIENCE,
        )
        .await;
}

/// Capacity 2 (waiting or running), counted over the cluster: one job running and one waiting,
/// both submitted through A, and a submission through B is refused with 429 `queue_full` and
/// Retry-After, over gRPC with RESOURCE_EXHAUSTED; once they are done B accepts again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_full_across_nodes_429_and_resource_exhausted() {
    use willow_service::api::grpc::pb::willow::v1;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.queue_capacity(2);
    let api_a = Node::spawn(d, "api-a", Some(&url), &opts(NodeOpts::api()));
    let api_b = Node::spawn(d, "api-b", Some(&url), &opts(NodeOpts::api()));
    let worker = Node::spawn(d, "worker", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api_a, &api_b, &worker]).await;

    let running = api_a
        .submit(&slow_obj(), "steps=5000&until_converged=false")
        .await;
    api_a
        .poll_until(&running, |v| v["state"] == "running")
        .await;
    let (status, _, waiting) = api_a.submit_obj(&small_obj(), "steps=2", None).await;
    assert_eq!(status, 202, "{waiting}");
    assert_eq!(waiting["state"], "queued", "{waiting}");
    let waiting = waiting["id"].as_str().expect("id").to_string();

    let (status, headers, p) = api_b.submit_obj(&small_obj(), "steps=2", None).await;
    assert_eq!(status, 429, "{p}");
    assert_eq!(
        headers.get("content-type").and_then(|v| v.to_str().ok()),
        Some("application/problem+json")
    );
    assert_eq!(p["code"], "queue_full", "{p}");
    let retry: u64 = headers
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("Retry-After in seconds");
    assert!(retry >= 1, "Retry-After {retry}");

    let channel = tonic::transport::Channel::from_shared(api_b.grpc_uri())
        .expect("uri")
        .connect()
        .await
        .expect("gRPC connect to B");
    let mut client = v1::fairing_client::FairingClient::new(channel);
    let full = client
        .create_job(v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
                format: v1::MeshFormat::Obj as i32,
                data: small_obj().into_bytes().into(),
            })),
            params: Some(v1::JobParams {
                method: v1::Method::Conformal as i32,
                steps: Some(2),
                ..Default::default()
            }),
            request_id: String::new(),
        })
        .await
        .expect_err("the queue is full");
    assert_eq!(
        full.code(),
        tonic::Code::ResourceExhausted,
        "{}",
        full.message()
    );

    // Room again once the running job is cancelled and the waiting one has run.
    let res = api_b
        .client
        .post(api_b.url(&format!("/v1/jobs/{running}/cancel")))
        .send()
        .await
        .expect("cancel");
    assert_eq!(res.status(), 202);
    let v = api_b.poll_until(&waiting, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    let start = Instant::now();
    let accepted = loop {
        let (status, _, job) = api_b.submit_obj(&small_obj(), "steps=2", None).await;
        if status == 202 {
            break job["id"].as_str().expect("id").to_string();
        }
        assert_eq!(status, 429, "{job}");
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "B still refuses with the queue empty: {job}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let v = api_b.poll_until(&accepted, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
}

/// One `Idempotency-Key`, two API nodes: the same request gives the same job wherever it is
/// sent (also when both arrive at once), a different one is refused with 422.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotency_key_across_api_nodes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let api_a = Node::spawn(d, "api-a", Some(&url), &NodeOpts::api());
    let api_b = Node::spawn(d, "api-b", Some(&url), &NodeOpts::api());
    let worker = Node::spawn(d, "worker", Some(&url), &NodeOpts::worker());
    all_ready(&[&api_a, &api_b, &worker]).await;
    let obj = small_obj();

    let (s1, _, j1) = api_a.submit_obj(&obj, "steps=2", Some("key-1")).await;
    assert_eq!(s1, 202, "{j1}");
    let (s2, _, j2) = api_b.submit_obj(&obj, "steps=2", Some("key-1")).await;
    assert_eq!(s2, 202, "{j2}");
    assert_eq!(j1["id"], j2["id"], "a retry through B returns A's job");

    for node in [&api_b, &api_a] {
        let (s, _, p) = node.submit_obj(&obj, "steps=3", Some("key-1")).await;
        assert_eq!(s, 422, "{}: {p}", node.name);
        assert_eq!(p["code"], "idempotency_mismatch", "{p}");
        assert!(
            p["detail"].as_str().is_some_and(|d| d.contains("key-1")),
            "{p}"
        );
    }

    // The same key at both nodes at once: one job.
    let (ra, rb) = tokio::join!(
        api_a.submit_obj(&obj, "steps=2", Some("key-2")),
        api_b.submit_obj(&obj, "steps=2", Some("key-2")),
    );
    assert_eq!(ra.0, 202, "{}", ra.2);
    assert_eq!(rb.0, 202, "{}", rb.2);
    assert_eq!(ra.2["id"], rb.2["id"], "racing submissions share the job");
    assert_ne!(ra.2["id"], j1["id"]);

    for node in [&api_a, &api_b] {
        let (_, list) = node.get_json("/v1/jobs").await;
        assert_eq!(
            list["jobs"].as_array().map(Vec::len),
            Some(2),
            "{}: one job per key: {list}",
            node.name
        );
    }
    for id in [&j1["id"], &ra.2["id"]] {
        let v = api_b
            .poll_until(id.as_str().expect("id"), is_terminal)
            .await;
        assert_eq!(v["state"], "succeeded", "{v}");
    }
    // Two runs for two keys.
    worker
        .wait_metric(
            "willow_jobs_finished_total",
            &[("outcome", "succeeded")],
            2.0,
            METRIC_PATIENCE,
        )
        .await;
}

/// `max_deliver`: a job whose worker dies once too often fails with a reason instead of being
/// handed to one more worker. With `--max-deliveries 1`, the delivery after a crash is the
/// one too many.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_delivered_too_often_fails_with_code_redelivered() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.ack_wait_secs(2).max_deliveries(1);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let mut first = Node::spawn(d, "worker-1", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api, &first]).await;
    let id = api
        .submit(
            &slow_obj(),
            "steps=120&frame_interval=20&until_converged=false",
        )
        .await;
    api.poll_until(&id, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 2
    })
    .await;
    first.kill();
    let second = Node::spawn(d, "worker-2", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&second]).await;
    let done = api.poll_until(&id, is_terminal).await;
    assert_eq!(done["state"], "failed", "{done}");
    assert_eq!(done["error_code"], "redelivered", "{done}");
    assert!(
        done["error"]
            .as_str()
            .is_some_and(|m| m.contains("delivered 1 times")),
        "the reason says how often: {done}"
    );
}

/// A worker that shuts down cleanly hands its job back without using up a delivery: with
/// `--max-deliveries 1` the job still succeeds on the next worker, resumed from the checkpoint
/// its first worker wrote on the way out.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_drained_mid_job_hands_it_back_without_spending_a_delivery() {
    const N: u64 = 120;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| NodeOpts {
        grace_secs: 0.0,
        ..o.ack_wait_secs(30).max_deliveries(1)
    };
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let mut first = Node::spawn(d, "worker-1", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api, &first]).await;
    let id = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    let before = api
        .poll_until(&id, |v| {
            v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 5
        })
        .await;
    let exit = first.terminate(Duration::from_secs(30));
    assert!(exit.is_some_and(|s| s.success()), "a clean exit: {exit:?}");
    let stopped_at = api.get_json(&format!("/v1/jobs/{id}")).await.1;
    assert_ne!(
        stopped_at["state"], "succeeded",
        "stopped mid-job: {stopped_at}"
    );
    let second = Node::spawn(d, "worker-2", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&second]).await;
    let done = api.poll_until(&id, is_terminal).await;
    assert_eq!(
        done["state"], "succeeded",
        "not failed as redelivered: {done}"
    );
    assert_eq!(api.frame_list(&id).await, steps(0..=N));
    assert!(
        done["progress"]["step"].as_u64() == Some(N)
            && before["progress"]["step"].as_u64().unwrap_or(0) >= 5,
        "{before} → {done}"
    );
    second
        .wait_metric("willow_jobs_resumed_total", &[], 1.0, METRIC_PATIENCE)
        .await;
}

/// Consumers on the object store's stream (`OBJ_willow-blobs`), as the server counts them.
async fn blob_consumers(js: &async_nats::jetstream::Context) -> usize {
    let mut stream = js
        .get_stream("OBJ_willow-blobs")
        .await
        .expect("the object store's stream");
    stream
        .info()
        .await
        .expect("stream info")
        .state
        .consumer_count
}

/// Blob reads leave no JetStream consumer behind: six SSE watchers on two long jobs read a
/// frame's positions from the object store for every step, for 30 s, while the object
/// store's consumer count is sampled every half second. It stays at 0 (each read used to
/// leave an ordered consumer for ~30 s, and at the server's 1000 per stream every blob read
/// failed: frames without positions, jobs failed `internal`). Every frame keeps its
/// positions and both jobs are still running at the end.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sse_watchers_blob_reads_leave_no_consumers_behind() {
    const WATCHERS_PER_JOB: usize = 3;
    const WATCH: Duration = Duration::from_secs(30);
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let api = Node::spawn(d, "api", Some(&url), &NodeOpts::api());
    let worker = Node::spawn(
        d,
        "worker",
        Some(&url),
        &NodeOpts {
            workers: 2,
            ..NodeOpts::worker()
        },
    );
    all_ready(&[&api, &worker]).await;
    let js = async_nats::jetstream::new(async_nats::connect(url.as_str()).await.expect("client"));

    let mut ids = Vec::new();
    for _ in 0..2 {
        ids.push(
            api.submit(&slow_obj(), "steps=9000&until_converged=false")
                .await,
        );
    }
    for id in &ids {
        api.poll_until(id, |v| v["state"] == "running").await;
    }
    let started = Instant::now();
    let mut watchers = Vec::new();
    for id in &ids {
        for _ in 0..WATCHERS_PER_JOB {
            let mut sse = api.events(id, None).await;
            watchers.push(tokio::spawn(async move {
                // (frames, frames without positions, whether `done` came)
                let (mut frames, mut bare, mut done) = (0usize, 0usize, false);
                while started.elapsed() < WATCH {
                    let left = WATCH.saturating_sub(started.elapsed());
                    match sse.next(left).await {
                        SseNext::Event(e) if e.event == "frame" => {
                            frames += 1;
                            if e.data["positions_b64"].as_str().is_none() {
                                bare += 1;
                            }
                        }
                        SseNext::Event(e) if e.event == "done" => {
                            done = true;
                            break;
                        }
                        SseNext::Event(_) => {}
                        SseNext::TimedOut => break,
                        other => panic!("the stream ended early: {other:?}"),
                    }
                }
                (frames, bare, done)
            }));
        }
    }
    let mut samples = Vec::new();
    while started.elapsed() < WATCH {
        samples.push(blob_consumers(&js).await);
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    let (mut frames, mut bare) = (0, 0);
    for w in watchers {
        let (f, b, done) = w.await.expect("watcher task");
        assert!(!done, "a job ended while watched");
        frames += f;
        bare += b;
    }
    let max = samples.iter().copied().max().unwrap_or(0);
    eprintln!(
        "{frames} frames to {} watchers; object store consumers sampled: {samples:?}",
        ids.len() * WATCHERS_PER_JOB
    );
    assert!(
        frames >= 200,
        "too few frames ({frames}) to say anything: is the machine that slow?"
    );
    assert_eq!(bare, 0, "{bare} of {frames} frames came without positions");
    assert!(
        max <= 2,
        "blob reads left consumers behind on the object store: {samples:?}"
    );
    for id in &ids {
        let (_, v) = api.get_json(&format!("/v1/jobs/{id}")).await;
        assert_eq!(v["state"], "running", "{v}");
        let res = api
            .client
            .post(api.url(&format!("/v1/jobs/{id}/cancel")))
            .send()
            .await
            .expect("cancel");
        assert_eq!(res.status(), 202);
    }
    for id in &ids {
        let v = api.poll_until(id, is_terminal).await;
        assert_eq!(v["state"], "cancelled", "{v}");
    }
    // Deleting a job finds its blobs without a consumer either, and deletes them.
    let blobs = js
        .get_object_store("willow-blobs")
        .await
        .expect("object store");
    let input = format!("jobs/{}/input.obj", ids[0]);
    assert!(!blobs.info(&input).await.expect("input info").deleted);
    let res = api
        .client
        .delete(api.url(&format!("/v1/jobs/{}", ids[0])))
        .send()
        .await
        .expect("delete");
    assert!(res.status().is_success(), "delete: {}", res.status());
    assert!(
        blobs.info(&input).await.expect("input info").deleted,
        "the job's input is deleted with it"
    );
    assert_eq!(blob_consumers(&js).await, 0, "consumers after a delete");
}

/// Steps a worker took (its step-duration histogram's count; 0 when absent).
async fn steps_taken(node: &Node) -> f64 {
    metric(&node.metrics().await, "willow_step_seconds_count", &[]).unwrap_or(0.0)
}

/// Every (state, step) a client polling job `id` every 100 ms sees, until it is terminal and
/// 8 s more (a second run would show as running again, or as progress going back).
fn poll_states(api: &Node, id: &str) -> tokio::task::JoinHandle<Vec<(String, u64)>> {
    let (client, base, id) = (api.client.clone(), api.base.clone(), id.to_string());
    tokio::spawn(async move {
        let mut seen: Vec<(String, u64)> = Vec::new();
        let mut terminal_since = None;
        let start = Instant::now();
        while start.elapsed() < PATIENCE * 2 {
            let got = client
                .get(format!("{base}/v1/jobs/{id}"))
                .timeout(Duration::from_secs(5))
                .send()
                .await;
            if let Ok(res) = got {
                if let Ok(v) = res.json::<serde_json::Value>().await {
                    if let Some(state) = v["state"].as_str() {
                        let step = v["progress"]["step"].as_u64().unwrap_or(0);
                        seen.push((state.to_string(), step));
                        if is_terminal(&v) {
                            terminal_since.get_or_insert_with(Instant::now);
                        }
                    }
                }
            }
            if terminal_since.is_some_and(|t| t.elapsed() > Duration::from_secs(8)) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        seen
    })
}

/// The states after the first terminal one are all `succeeded` at step `n`.
fn assert_succeeded_once_at(seen: &[(String, u64)], n: u64) {
    let first_terminal = seen
        .iter()
        .position(|(s, _)| s != "queued" && s != "running")
        .expect("the poller saw the end");
    assert!(
        seen[first_terminal..]
            .iter()
            .all(|(s, step)| s == "succeeded" && *step == n),
        "`succeeded` only at step {n}, and it stays: {:?}",
        &seen[first_terminal.saturating_sub(3)..]
    );
}

/// A running job is run by one worker at a time across a NATS restart: nats-server is stopped
/// for ~3 s (longer than `ack_wait`) while a job runs on one worker and a second worker idles.
/// The job's message is delivered again when NATS is back, but the first worker's fence still
/// holds the job, so the duplicate is not run: one worker finishes it, `succeeded` appears
/// once, at the last step, every step is taken once (no resume, no second run), and the
/// watcher across the outage sees each frame once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_restart_mid_job_the_job_runs_once_on_one_worker() {
    const N: u64 = 400;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let mut nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.checkpoint_steps(2).ack_wait_secs(3);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let w1 = Node::spawn(d, "worker-1", Some(&url), &opts(NodeOpts::worker()));
    let w2 = Node::spawn(d, "worker-2", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api, &w1, &w2]).await;

    let id = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    // A watcher that reconnects with `Last-Event-ID` when its stream ends (the API node ends
    // it while NATS is away), as a client does.
    let watcher = {
        let (client, base, id) = (api.client.clone(), api.base.clone(), id.clone());
        tokio::spawn(async move {
            let mut events: Vec<Sse> = Vec::new();
            let start = Instant::now();
            while start.elapsed() < PATIENCE * 2 {
                let mut req = client.get(format!("{base}/v1/jobs/{id}/events"));
                if let Some(&last) = frame_steps(&events).last() {
                    req = req.header("Last-Event-ID", last.to_string());
                }
                let res = match req.send().await {
                    Ok(r) if r.status() == 200 => r,
                    _ => {
                        tokio::time::sleep(Duration::from_millis(200)).await;
                        continue;
                    }
                };
                let mut sse = SseStream::new(res);
                while let SseNext::Event(e) = sse.next(PATIENCE).await {
                    let done = e.event == "done";
                    events.push(e);
                    if done {
                        return events;
                    }
                }
            }
            panic!("no `done` in time: {:?}", frame_steps(&events));
        })
    };
    let poller = poll_states(&api, &id);
    api.poll_until(&id, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 10
    })
    .await;
    let t = Instant::now();
    nats.terminate();
    let stopped = t.elapsed();
    tokio::time::sleep(Duration::from_secs(3)).await;
    nats.restart();
    let restarted = t.elapsed();
    all_ready(&[&api, &w1, &w2]).await;
    eprintln!(
        "nats-server stopped in {stopped:?}, up again after {restarted:?}, nodes ready after {:?}",
        t.elapsed()
    );

    let done = api.poll_until(&id, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"]["step"], N, "{done}");
    assert_succeeded_once_at(&poller.await.expect("poller task"), N);
    let events = watcher.await.expect("watcher task");
    assert_eq!(
        checked_frame_steps(&events),
        steps(0..=N),
        "the watcher across the outage sees each step once, in order"
    );
    assert_eq!(done_state(&events), "succeeded");
    assert_eq!(
        events.iter().filter(|e| e.event == "done").count(),
        1,
        "one `done`"
    );

    // One finisher, no resume, every step taken once over both workers, also after two
    // more ack waits (a duplicate run would start over or resume meanwhile).
    tokio::time::sleep(Duration::from_secs(6)).await;
    let finishers = finished(&w1, "succeeded").await + finished(&w2, "succeeded").await;
    assert_eq!(finishers, 1.0, "exactly one worker finished the job");
    let (mut waited, mut gave_up) = (0, 0);
    for w in [&w1, &w2] {
        let log = std::fs::read_to_string(&w.log).unwrap_or_default();
        waited += log
            .matches("delivered while another worker holds it")
            .count();
        gave_up += log.matches("the job will be delivered again").count();
    }
    let resumed = metric(&w1.metrics().await, "willow_jobs_resumed_total", &[]).unwrap_or(0.0)
        + metric(&w2.metrics().await, "willow_jobs_resumed_total", &[]).unwrap_or(0.0);
    let taken = steps_taken(&w1).await + steps_taken(&w2).await;
    eprintln!(
        "duplicate deliveries waited out: {waited}; runs given up while NATS was away: \
         {gave_up}; resumes: {resumed}; steps taken: {taken}"
    );
    if gave_up == 0 {
        // The worker rode the outage out: nobody else ran or resumed the job.
        assert_eq!(resumed, 0.0, "no worker resumed the job from a checkpoint");
        assert_eq!(taken, N as f64, "every step taken once over both workers");
    } else {
        // NATS was away longer than the worker's retries (a slow restart on a loaded
        // machine): its run was handed back and resumed once, from its checkpoint.
        assert_eq!(resumed, 1.0, "the handed-back run resumed once");
    }
}

/// Send `signal` (`STOP`, `CONT`) to a node's process.
fn signal(node: &Node, signal: &str) {
    let pid = node.pid().expect("a running node");
    let status = std::process::Command::new("kill")
        .args([format!("-{signal}"), pid.to_string()])
        .status()
        .expect("kill");
    assert!(status.success(), "kill -{signal} {pid}");
}

/// A stale worker's writes are refused: the worker running a job is frozen (SIGSTOP) until its
/// hold lapses and the other worker takes the job over and resumes it; thawed, the first
/// worker finds at its next write that it lost the job and stops, writing nothing more. One
/// worker finishes, `succeeded` appears once at the last step, and the frames are each step
/// once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frozen_worker_loses_its_job_and_stops_when_thawed() {
    const N: u64 = 300;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.checkpoint_steps(2).ack_wait_secs(2);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let workers = [
        Node::spawn(d, "worker-1", Some(&url), &opts(NodeOpts::worker())),
        Node::spawn(d, "worker-2", Some(&url), &opts(NodeOpts::worker())),
    ];
    all_ready(&[&api, &workers[0], &workers[1]]).await;

    let id = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=20&until_converged=false"),
        )
        .await;
    let poller = poll_states(&api, &id);
    api.poll_until(&id, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 5
    })
    .await;
    let start = Instant::now();
    let victim = loop {
        let mut running = Vec::new();
        for w in &workers {
            running.push(metric(&w.metrics().await, "willow_jobs_running", &[]));
        }
        match running[..] {
            [Some(1.0), Some(0.0)] => break 0,
            [Some(0.0), Some(1.0)] => break 1,
            _ if start.elapsed() > PATIENCE => {
                panic!("no single worker reports willow_jobs_running 1: {running:?}")
            }
            _ => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    };
    let (frozen, other) = (&workers[victim], &workers[1 - victim]);
    signal(frozen, "STOP");
    // The other worker gets the message after ack_wait, waits out the hold, and resumes.
    other
        .wait_metric("willow_jobs_resumed_total", &[], 1.0, PATIENCE)
        .await;
    let (_, v) = api.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(v["state"], "running", "still running when thawed: {v}");
    signal(frozen, "CONT");

    let done = api.poll_until(&id, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"]["step"], N, "{done}");
    assert_succeeded_once_at(&poller.await.expect("poller task"), N);
    assert_eq!(api.frame_list(&id).await, steps(0..=N));
    assert_eq!(
        finished(frozen, "succeeded").await,
        0.0,
        "the thawed worker finished nothing"
    );
    assert_eq!(
        finished(other, "succeeded").await,
        1.0,
        "the other worker finished it"
    );
    frozen
        .wait_metric("willow_jobs_running", &[], 0.0, METRIC_PATIENCE)
        .await;
    let log = std::fs::read_to_string(&frozen.log).unwrap_or_default();
    assert!(
        log.contains("another worker holds the job now") || log.contains("the job's hold is gone"),
        "the thawed worker saw that it lost the job"
    );
}
