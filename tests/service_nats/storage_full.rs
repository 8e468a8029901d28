//! JetStream full, end to end (issue 25 item 5 on the NATS backend): nats-server runs with a
//! small `max_file_store`, and one node (API and two workers) fills it with jobs whose inputs
//! are large. Then submissions answer 507 `storage_full` (problem+json, `Retry-After`) and
//! gRPC `RESOURCE_EXHAUSTED`, `/readyz` says "storage full", the running job is re-queued
//! instead of failed, earlier results still read; DELETE of finished jobs frees JetStream's
//! bytes (the object store's purge writes nothing, so it works on a full JetStream), the node
//! is ready again, new submissions succeed and the long job resumes past where it stopped.

use super::*;
use willow_service::api::grpc::pb::willow::v1;

/// nats-server's `max_file_store` for this test: room for a few of the large jobs.
const MAX_FILE_STORE: u64 = 8 << 20;

/// A job input of about 0.9 MB (10 242 vertices): a few fill [`MAX_FILE_STORE`].
fn large_obj() -> String {
    service_http_support::obj_text(&willow::mesh::generate::bumpy_sphere(5, 0.1))
}

/// Bytes JetStream holds now (all streams), from the server's own accounting.
async fn jetstream_bytes(nats: &Nats) -> u64 {
    nats.monitor("jsz").await["storage"]
        .as_u64()
        .expect("jsz storage bytes")
}

/// `/readyz`'s status and text.
async fn readyz_text(node: &Node) -> (u16, String) {
    let res = node
        .client
        .get(node.url("/readyz"))
        .send()
        .await
        .expect("GET /readyz");
    let status = res.status().as_u16();
    (status, res.text().await.unwrap_or_default())
}

/// Wait until `/readyz` answers `status` (with `text` if given).
async fn wait_readyz_text(node: &Node, status: u16, text: Option<&str>, timeout: Duration) {
    let start = Instant::now();
    loop {
        let got = readyz_text(node).await;
        if got.0 == status && text.is_none_or(|t| got.1 == t) {
            return;
        }
        assert!(
            start.elapsed() < timeout,
            "/readyz is {got:?}, not {status} {text:?}, after {timeout:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_jetstream_refuses_submissions_requeues_the_running_job_and_recovers_after_delete() {
    let dir = tempfile::tempdir().expect("temp dir");
    let d = dir.path();
    let nats = Nats::start_with_max_file_store(d, MAX_FILE_STORE);
    let url = nats.url();
    let opts = NodeOpts {
        workers: 2,
        ..NodeOpts::all()
    }
    .queue_capacity(64)
    .checkpoint_steps(2);
    let node = Node::spawn(d, "node", Some(&url), &opts);
    all_ready(&[&node]).await;

    // An earlier result, read again on the full JetStream.
    let earlier = node.submit(&small_obj(), "steps=2").await;
    let v = node.poll_until(&earlier, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    let earlier_result = node.result_obj(&earlier).await;

    // A long job that writes a checkpoint every 2 steps: it meets the full JetStream.
    let long = node
        .submit(
            &slow_obj(),
            "steps=10000&until_converged=false&frame_interval=10000",
        )
        .await;
    node.poll_until(&long, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 4
    })
    .await;

    // Large jobs, one at a time, until a submission is refused.
    let large = large_obj();
    let mut finished_large = Vec::new();
    // Large jobs that met the full JetStream while they ran (re-queued): they finish later.
    let mut waiting_large = Vec::new();
    let refused = loop {
        assert!(
            finished_large.len() < 12,
            "{} large jobs ({} bytes each) fit in a {MAX_FILE_STORE}-byte JetStream",
            finished_large.len(),
            large.len()
        );
        let (status, headers, body) = node.submit_obj(&large, "steps=1", None).await;
        if status == 507 {
            break (headers, body);
        }
        assert_eq!(
            status, 202,
            "a submission is accepted or refused 507: {body}"
        );
        let id = body["id"].as_str().expect("id").to_string();
        // It ends, or meets the full JetStream while it runs (and waits, re-queued).
        let start = Instant::now();
        loop {
            let (_, v) = node.get_json(&format!("/v1/jobs/{id}")).await;
            if is_terminal(&v) {
                assert_eq!(v["state"], "succeeded", "{v}");
                finished_large.push(id);
                break;
            }
            if readyz_text(&node).await.1 == "storage full" {
                waiting_large.push(id);
                break;
            }
            assert!(
                start.elapsed() < PATIENCE,
                "large job {id} neither ended nor met a full JetStream: {v}"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    };
    let (headers, problem) = refused;
    assert_eq!(problem["code"], "storage_full", "{problem}");
    assert_eq!(problem["status"], 507, "{problem}");
    assert_eq!(
        headers.get("content-type").and_then(|v| v.to_str().ok()),
        Some("application/problem+json")
    );
    let retry: u64 = headers
        .get("retry-after")
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse().ok())
        .expect("Retry-After in seconds");
    assert!(retry >= 1, "Retry-After {retry}");
    // The refused write left no chunks behind (it was cut at a chunk JetStream refused; the
    // client's own `put` left the chunks before it). Jobs still write here (the long one's
    // checkpoint, a re-queued large job trying again when a probe finds room): a chunk set
    // counts only if it outlasts a second scan.
    let (orphans, messages) = lasting_orphan_chunks(&url, Duration::from_secs(2)).await;
    assert!(
        orphans.is_empty(),
        "a write refused by the full JetStream left {} chunk sets ({messages} messages) that no object names",
        orphans.len()
    );
    let full_bytes = jetstream_bytes(&nats).await;
    eprintln!(
        "JetStream full at {full_bytes} bytes of {MAX_FILE_STORE} after {} large jobs of {} bytes",
        finished_large.len(),
        large.len()
    );
    assert!(
        finished_large.len() >= 2,
        "some large jobs finished before JetStream filled: {finished_large:?}"
    );

    // Readiness says why; gRPC refuses as RESOURCE_EXHAUSTED.
    wait_readyz_text(&node, 503, Some("storage full"), Duration::from_secs(10)).await;
    let channel = tonic::transport::Channel::from_shared(node.grpc_uri())
        .expect("uri")
        .connect()
        .await
        .expect("gRPC connect");
    let mut client = v1::fairing_client::FairingClient::new(channel);
    let status = client
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
        .expect_err("JetStream is full");
    assert_eq!(
        status.code(),
        tonic::Code::ResourceExhausted,
        "{}",
        status.message()
    );

    // The long job met it: re-queued, not failed.
    let start = Instant::now();
    while !std::fs::read_to_string(&node.log)
        .unwrap_or_default()
        .contains("storage full: the job is re-queued")
    {
        assert!(
            start.elapsed() < PATIENCE,
            "no running job was re-queued on the full JetStream"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let (status, v) = node.get_json(&format!("/v1/jobs/{long}")).await;
    assert_eq!(status, 200, "{v}");
    assert!(
        v["state"] == "running" || v["state"] == "queued",
        "the long job waits for room: {v}"
    );
    let step_when_full = v["progress"]["step"].as_u64().unwrap_or(0);

    // Reads keep working.
    assert_eq!(node.result_obj(&earlier).await, earlier_result);
    let (status, list) = node.get_json("/v1/jobs").await;
    assert_eq!(status, 200, "{list}");

    // DELETE the finished large jobs: JetStream's bytes fall by at least their inputs.
    for id in &finished_large {
        let res = node
            .client
            .delete(node.url(&format!("/v1/jobs/{id}")))
            .send()
            .await
            .expect("DELETE");
        assert_eq!(res.status(), 204, "DELETE {id} on a full JetStream");
    }
    let after_delete = jetstream_bytes(&nats).await;
    let inputs = (finished_large.len() * large.len()) as u64;
    eprintln!(
        "JetStream after {} DELETEs: {after_delete} bytes (was {full_bytes}; inputs {inputs})",
        finished_large.len()
    );
    assert!(
        after_delete + inputs <= full_bytes,
        "DELETE frees at least the inputs: {full_bytes} -> {after_delete} bytes, inputs {inputs}"
    );

    // Ready again; a submission succeeds and runs; the long job goes on past where it stopped.
    wait_readyz_text(&node, 200, None, Duration::from_secs(20)).await;
    let later = node.submit(&small_obj(), "steps=2").await;
    let v = node.poll_until(&later, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "{v}");
    let v = node
        .poll_until(&long, |v| {
            is_terminal(v)
                || (v["state"] == "running"
                    && v["progress"]["step"].as_u64().unwrap_or(0) > step_when_full + 4)
        })
        .await;
    assert_eq!(v["state"], "running", "the long job resumed: {v}");
    for id in &waiting_large {
        let v = node.poll_until(id, is_terminal).await;
        assert_eq!(v["state"], "succeeded", "a re-queued large job ends: {v}");
    }
    assert_eq!(finished(&node, "failed").await, 0.0, "no job failed");

    // With every write settled (the long job cancelled, nothing running), no chunks are left
    // that no object names. (While a job runs, a write between its chunks and its info
    // would look the same.)
    let res = node
        .client
        .post(node.url(&format!("/v1/jobs/{long}/cancel")))
        .send()
        .await
        .expect("cancel");
    assert_eq!(res.status(), 202);
    let v = node.poll_until(&long, is_terminal).await;
    assert_eq!(v["state"], "cancelled", "{v}");
    node.wait_metric("willow_jobs_running", &[], 0.0, METRIC_PATIENCE)
        .await;
    let (orphans, messages) = orphan_chunks(&url).await;
    assert!(
        orphans.is_empty(),
        "{} chunk sets ({messages} messages) that no object names: {orphans:?}",
        orphans.len()
    );
}
