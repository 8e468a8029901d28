//! API and worker nodes over one NATS: the harness, watching across nodes, SIGKILLed workers
//! and API nodes, a restarted NATS server, cancelling across nodes.

use super::*;

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
    let victim = running_worker(&workers).await;
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

/// What `repair` changed is stored in the NATS job record: submitted through API A, it is
/// reported by API B's poll (which reads the record, not A's answer); a job without `repair`
/// reports none.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn repairs_are_stored_in_the_nats_record() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let api_a = Node::spawn(d, "api-a", Some(&url), &NodeOpts::api());
    let api_b = Node::spawn(d, "api-b", Some(&url), &NodeOpts::api());
    let w = Node::spawn(d, "worker", Some(&url), &NodeOpts::worker());
    all_ready(&[&api_a, &api_b, &w]).await;
    let bowtie = service_http_support::bowtie_obj();
    let (status, _, answer) = api_a.submit_obj(&bowtie, "steps=2&repair=true", None).await;
    assert_eq!(status, 202, "{answer}");
    let id = answer["id"].as_str().expect("id").to_string();
    assert_eq!(answer["repairs"]["split_vertices"]["count"], 1, "{answer}");
    let polled = api_b.poll_until(&id, is_terminal).await;
    assert_eq!(polled["state"], "succeeded", "{polled}");
    assert_eq!(polled["repairs"], answer["repairs"], "{polled}");
    let plain = api_a.submit(&small_obj(), "steps=1").await;
    let polled = api_b.poll_until(&plain, is_terminal).await;
    assert!(polled.get("repairs").is_none(), "{polled}");
}
