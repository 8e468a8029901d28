//! The shared queue: full across nodes, idempotency keys across nodes, a job delivered too
//! often, a drained worker handing its job back.

use super::*;

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

/// `--max-deliveries`: a job whose workers die before they reach a new checkpoint fails with
/// a reason instead of being handed to one more worker. With `--max-deliveries 1` and no
/// checkpoint before the kill, the delivery after the crash is the one too many.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_delivered_too_often_fails_with_code_redelivered() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    // No checkpoint in this job's life: every run makes no progress that survives it.
    let opts = |o: NodeOpts| {
        o.ack_wait_secs(2)
            .max_deliveries(1)
            .checkpoint_steps(100_000)
    };
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
        done["error"].as_str().is_some_and(
            |m| m.contains("delivered 2 times in a row without reaching a new checkpoint")
        ),
        "the reason says how often and why: {done}"
    );
}

/// `--max-deliveries` counts deliveries without progress, not crashes after progress (issue
/// 25 item 4: a 1000-step job killed at steps 43, 144 and 243, each past a checkpoint, failed
/// `redelivered`). With `--max-deliveries 1`, the worker running the job is killed three
/// times, each time 8 steps past where its run resumed (so past a new checkpoint, one every 5
/// steps); a new worker takes over each time. The job succeeds, resumed three times.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_workers_die_after_progress_is_not_failed_redelivered() {
    const N: u64 = 300;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let opts = |o: NodeOpts| o.ack_wait_secs(2).max_deliveries(1).checkpoint_steps(5);
    let api = Node::spawn(d, "api", Some(&url), &opts(NodeOpts::api()));
    let mut worker = Node::spawn(d, "worker-0", Some(&url), &opts(NodeOpts::worker()));
    all_ready(&[&api, &worker]).await;
    let id = api
        .submit(
            &slow_obj(),
            &format!("steps={N}&frame_interval=50&until_converged=false"),
        )
        .await;
    let mut resumed_at = 0;
    let mut killed_at = Vec::new();
    for kill in 1..=3 {
        let v = api
            .poll_until(&id, |v| {
                is_terminal(v)
                    || (v["state"] == "running"
                        && v["progress"]["step"].as_u64().unwrap_or(0) >= resumed_at + 8)
            })
            .await;
        assert_eq!(v["state"], "running", "still running at kill {kill}: {v}");
        let step = v["progress"]["step"].as_u64().unwrap_or(0);
        worker.kill();
        killed_at.push(step);
        // Checkpoints fall on multiples of 5 (every 5 steps from 0, and from a resume
        // point): the next run resumes at or below this one, and once it shows 8 steps past
        // it, the checkpoint 5 past it is written.
        resumed_at = step / 5 * 5;
        worker = Node::spawn(
            d,
            &format!("worker-{kill}"),
            Some(&url),
            &opts(NodeOpts::worker()),
        );
        all_ready(&[&worker]).await;
        worker
            .wait_metric("willow_jobs_resumed_total", &[], 1.0, PATIENCE)
            .await;
    }
    let done = api.poll_until(&id, is_terminal).await;
    assert_eq!(
        done["state"], "succeeded",
        "killed at steps {killed_at:?}, each past a new checkpoint: {done}"
    );
    assert_eq!(done["progress"]["step"], N, "{done}");
    assert_eq!(api.frame_list(&id).await, steps(0..=N));
    eprintln!("workers killed at steps {killed_at:?}; the job succeeded");
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
