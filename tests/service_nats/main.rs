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
//!
//! One file a theme: `blobs`, `nodes`, `queue`, `consumers`, `fencing`, `outages`, `storage_full`; this one holds the helpers
//! they share.

#[path = "../nats_support/mod.rs"]
mod nats_support;
#[path = "../service_http_support/mod.rs"]
mod service_http_support;
#[path = "../webhook_support/mod.rs"]
mod webhook_support;

mod blobs;
mod consumers;
mod fencing;
mod nodes;
mod outages;
mod queue;
mod storage_full;
mod webhooks;

use futures::StreamExt;
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

/// Which of two workers runs the one running job: the one whose `willow_jobs_running` is 1
/// while the other's is 0 (fails after [`PATIENCE`] if no single worker reports it).
async fn running_worker(workers: &[Node]) -> usize {
    let start = Instant::now();
    loop {
        let mut running = Vec::new();
        for w in workers {
            running.push(metric(&w.metrics().await, "willow_jobs_running", &[]));
        }
        match running[..] {
            [Some(1.0), Some(0.0)] => return 0,
            [Some(0.0), Some(1.0)] => return 1,
            _ if start.elapsed() > PATIENCE => {
                panic!("no single worker reports willow_jobs_running 1: {running:?}")
            }
            _ => tokio::time::sleep(Duration::from_millis(20)).await,
        }
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

/// [`orphan_chunks`] seen by two scans `apart`: a write in flight while the first scan ran
/// (a job's checkpoint, a re-queued job trying again) has its chunks named or purged by the
/// second, and every try writes under a fresh chunk id, so only chunk sets that something
/// left behind are in both. (chunk subjects, their messages in the second scan)
pub(crate) async fn lasting_orphan_chunks(url: &str, apart: Duration) -> (Vec<String>, u64) {
    let first = orphan_chunk_counts(url).await;
    if first.is_empty() {
        return (Vec::new(), 0);
    }
    tokio::time::sleep(apart).await;
    let lasting: Vec<(String, u64)> = orphan_chunk_counts(url)
        .await
        .into_iter()
        .filter(|(s, _)| first.iter().any(|(f, _)| f == s))
        .collect();
    let messages = lasting.iter().map(|(_, n)| n).sum();
    (lasting.into_iter().map(|(s, _)| s).collect(), messages)
}

/// Chunk sets in the object store's stream that no object's info names: what a write cut
/// midway leaves unless it cleans up. (chunk subjects, their messages), from the stream's
/// per-subject counts and each info's `nuid` (direct gets: the stream allows them).
pub(crate) async fn orphan_chunks(url: &str) -> (Vec<String>, u64) {
    let counts = orphan_chunk_counts(url).await;
    let messages = counts.iter().map(|(_, n)| n).sum();
    (counts.into_iter().map(|(s, _)| s).collect(), messages)
}

/// [`orphan_chunks`], each chunk subject with its message count.
async fn orphan_chunk_counts(url: &str) -> Vec<(String, u64)> {
    let js = async_nats::jetstream::new(async_nats::connect(url).await.expect("client"));
    let stream = js
        .get_stream("OBJ_willow-blobs")
        .await
        .expect("the object store's stream");
    let subjects = |filter: &'static str| {
        let stream = stream.clone();
        async move {
            let mut out = Vec::new();
            let mut s = stream
                .info_with_subjects(filter)
                .await
                .expect("stream subjects");
            while let Some(item) = s.next().await {
                out.push(item.expect("subject count"));
            }
            out
        }
    };
    let mut named = std::collections::HashSet::new();
    for (meta, _) in subjects("$O.willow-blobs.M.>").await {
        let m = stream
            .direct_get_last_for_subject(meta.as_str())
            .await
            .expect("an object's info");
        let info: serde_json::Value = serde_json::from_slice(&m.payload).expect("info JSON");
        if info["deleted"] != true {
            named.insert(info["nuid"].as_str().expect("nuid").to_string());
        }
    }
    let mut orphans = Vec::new();
    for (subject, count) in subjects("$O.willow-blobs.C.>").await {
        let nuid = subject.rsplit('.').next().unwrap_or_default();
        if !named.contains(nuid) {
            orphans.push((subject, count as u64));
        }
    }
    orphans
}
