//! A job runs once: a NATS restart mid-job, a frozen worker that loses its job.

use super::*;

/// Steps a worker took (its step-duration histogram's count; 0 when absent).
pub(crate) async fn steps_taken(node: &Node) -> f64 {
    metric(&node.metrics().await, "willow_step_seconds_count", &[]).unwrap_or(0.0)
}

/// Every (state, step) a client polling job `id` every 100 ms sees, until it is terminal and
/// 8 s more (a second run would show as running again, or as progress going back).
pub(crate) fn poll_states(api: &Node, id: &str) -> tokio::task::JoinHandle<Vec<(String, u64)>> {
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

/// Longer than any quiet time of a watched running job (a frame per step; a watcher checks
/// the store after 5 s without news, and ends its stream when the store cannot answer) and
/// than the 15 s keep-alive.
const SILENCE: Duration = Duration::from_secs(30);

/// A client watching job `id`'s events that reconnects with `Last-Event-ID` whenever its
/// stream ends without `done` (the API node ends it while NATS is away) or the node answers
/// anything but 200; every event it saw, up to and with `done`. A stream silent for
/// [`SILENCE`] fails the test: a stream must end with `done` or a close, never go quiet.
pub(crate) fn reconnecting_watcher(api: &Node, id: &str) -> tokio::task::JoinHandle<Vec<Sse>> {
    let (client, base, id) = (api.client.clone(), api.base.clone(), id.to_string());
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
            loop {
                match sse.next(SILENCE).await {
                    SseNext::Event(e) => {
                        let done = e.event == "done";
                        events.push(e);
                        if done {
                            return events;
                        }
                    }
                    SseNext::TimedOut => panic!(
                        "an SSE stream went silent for {SILENCE:?} without `done` or a close: {:?}",
                        frame_steps(&events)
                    ),
                    _ => break,
                }
            }
        }
        panic!("no `done` in time: {:?}", frame_steps(&events));
    })
}

/// The states after the first terminal one are all `succeeded` at step `n`.
pub(crate) fn assert_succeeded_once_at(seen: &[(String, u64)], n: u64) {
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
    let watcher = reconnecting_watcher(&api, &id);
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
    let victim = running_worker(&workers).await;
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
