//! Watchers and blob reads leave no consumers behind.

use super::*;

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
    // Two 9,000-step jobs keeping every frame hold ~1.7 GB of the tenant's stored bytes
    // (`jobs::stored`): room for them, this test is about consumers.
    let api = Node::spawn(
        d,
        "api",
        Some(&url),
        &NodeOpts {
            extra: vec!["--tenant-max-stored-mib".into(), "4096".into()],
            ..NodeOpts::api()
        },
    );
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
    // Deleted by purging (nothing written, so it works on a full JetStream): no info left.
    let gone = blobs
        .info(&input)
        .await
        .expect_err("the job's input is deleted with it");
    assert_eq!(
        gone.kind(),
        async_nats::jetstream::object_store::InfoErrorKind::NotFound,
        "{gone}"
    );
    assert_eq!(blob_consumers(&js).await, 0, "consumers after a delete");
}

/// A deployment upgraded in place: the jobs stream and the workers' consumers were made by
/// the release before, whose consumers stopped delivering a job after `max_deliver` =
/// `--max-deliveries` + 1 deliveries. The new release counts deliveries itself and wants the
/// server's count unlimited (`max_deliver` -1): starting it against the old consumers updates
/// them in place (nats-server accepts the change), and a job runs through them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn consumers_made_with_the_old_finite_max_deliver_are_updated_to_unlimited() {
    use async_nats::jetstream::{consumer, stream};
    use sha2::Digest;
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    let js = async_nats::jetstream::new(async_nats::connect(url.as_str()).await.expect("client"));

    // What the old release made (its `connect` and tenant consumers, `--max-deliveries 3`).
    let jobs = js
        .create_stream(stream::Config {
            name: "WILLOW_JOBS".into(),
            subjects: vec!["willow.jobs".into(), "willow.jobs.>".into()],
            retention: stream::RetentionPolicy::WorkQueue,
            max_messages: 8,
            discard: stream::DiscardPolicy::New,
            storage: stream::StorageType::File,
            duplicate_window: Duration::from_secs(120),
            ..Default::default()
        })
        .await
        .expect("the old jobs stream");
    let old = consumer::pull::Config {
        ack_policy: consumer::AckPolicy::Explicit,
        ack_wait: Duration::from_secs(3),
        max_deliver: 4,
        ..Default::default()
    };
    // The default tenant's consumer is named after a digest of the tenant id.
    let digest = sha2::Sha256::digest(b"default");
    let hex: String = digest.iter().take(10).map(|b| format!("{b:02x}")).collect();
    let tenant_consumer = format!("willow-workers-{hex}");
    for (name, filter) in [
        ("willow-workers".to_string(), "willow.jobs"),
        (tenant_consumer.clone(), "willow.jobs.default"),
    ] {
        jobs.create_consumer(consumer::pull::Config {
            durable_name: Some(name.clone()),
            filter_subject: filter.into(),
            inactive_threshold: Duration::from_secs(3600),
            ..old.clone()
        })
        .await
        .unwrap_or_else(|e| panic!("the old consumer {name}: {e}"));
    }
    let max_deliver = |name: String| {
        let jobs = jobs.clone();
        async move {
            let mut c: consumer::PullConsumer = jobs
                .get_consumer(&name)
                .await
                .unwrap_or_else(|e| panic!("consumer {name}: {e}"));
            c.info().await.expect("consumer info").config.max_deliver
        }
    };
    assert_eq!(max_deliver(tenant_consumer.clone()).await, 4);

    let node = Node::spawn(d, "node", Some(&url), &NodeOpts::all());
    all_ready(&[&node]).await;
    assert_eq!(
        max_deliver("willow-workers".into()).await,
        -1,
        "the legacy consumer is updated at start"
    );
    let id = node.submit(&small_obj(), "steps=2").await;
    let v = node.poll_until(&id, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    assert_eq!(
        max_deliver(tenant_consumer).await,
        -1,
        "the tenant's consumer is updated when first used"
    );
}
