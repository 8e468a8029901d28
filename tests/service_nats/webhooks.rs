//! Webhooks on the NATS backend: the pending mark lives in the job's KV record, so a job that
//! ended on a worker is delivered (and retried after a 500) with a valid signature, and one
//! whose every try failed while the nodes ran is delivered by a node started afterwards.

use super::*;
use crate::webhook_support::{next, query_escape, receiver, SECRET};

/// Flags of a node that signs with the test's secret and may call back to loopback.
fn hooks(dir: &Path, o: NodeOpts) -> NodeOpts {
    let secret = dir.join("webhook-secret");
    std::fs::write(&secret, SECRET).expect("write the secret file");
    o.arg("--allow-insecure-callbacks")
        .arg("--webhook-secret-file")
        .arg(secret.to_string_lossy().into_owned())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_ended_on_a_worker_is_retried_then_delivered_after_the_nodes_restart() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start(d);
    let url = nats.url();
    // 500 once (the retry), then refusals until the nodes are gone.
    let (hook, mut rx, script) = receiver(&[500, 503, 503, 503, 503, 503, 503, 503]).await;
    let mut api = Node::spawn(d, "api", Some(&url), &hooks(d, NodeOpts::api()));
    let mut worker = Node::spawn(d, "worker", Some(&url), &hooks(d, NodeOpts::worker()));
    all_ready(&[&api, &worker]).await;

    let id = api
        .submit(
            &small_obj(),
            &format!(
                "steps=2&until_converged=false&callback_url={}",
                query_escape(&hook)
            ),
        )
        .await;
    let first = next(&mut rx).await;
    let second = next(&mut rx).await;
    for d in [&first, &second] {
        assert!(d.signature_ok, "{d:?}");
        assert_eq!(d.id, format!("msg_{id}"));
        assert_eq!(d.body["type"], "job.succeeded");
        assert_eq!(d.body["data"]["percent_complete"], 100.0);
    }
    assert_eq!((first.answered, second.answered), (500, 503));
    api.kill();
    worker.kill();
    while rx.try_recv().is_ok() {}

    // The receiver heals; a new API node finds the job still pending in KV and delivers it.
    script.lock().expect("script").clear();
    let api = Node::spawn(d, "api-2", Some(&url), &hooks(d, NodeOpts::api()));
    all_ready(&[&api]).await;
    let delivered = next(&mut rx).await;
    assert_eq!(delivered.answered, 200);
    assert!(delivered.signature_ok, "{delivered:?}");
    assert_eq!(delivered.id, format!("msg_{id}"));
    let (_, v) = api.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(v["progress"]["percent_complete"], 100.0, "{v}");
}
