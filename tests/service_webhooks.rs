//! Webhooks end to end: a receiver (an axum server on loopback) checks each delivery's
//! Standard Webhooks signature with its own HMAC-SHA256, answers as scripted (a 500 first to
//! see the retry), and sees a job's end delivered after the server was stopped before it could
//! deliver and started again on the same data dir.

mod service_http_support;
mod webhook_support;

use service_http_support::*;
use webhook_support::*;
use willow_service::jobs::Config;

fn allow_loopback_hooks(c: &mut Config) {
    c.allow_insecure_callbacks = true;
    c.webhook_secret = Some(SECRET.to_vec());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_succeeded_job_is_signed_retried_after_a_500_and_reports_percent_complete() {
    let (url, mut rx, _) = receiver(&[500]).await;
    let server = start(allow_loopback_hooks).await;
    let (status, _, job) = server
        .submit_obj(
            &small_obj(),
            &format!(
                "steps=3&until_converged=false&callback_url={}",
                query_escape(&url)
            ),
        )
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    assert_eq!(job["params"]["callback_url"], url.as_str());

    let first = next(&mut rx).await;
    let second = next(&mut rx).await;
    for d in [&first, &second] {
        assert!(d.signature_ok, "signature of {d:?}");
        assert_eq!(d.id, format!("msg_{id}"), "one webhook-id for every try");
        assert_eq!(d.body["type"], "job.succeeded");
        assert_eq!(d.body["data"]["id"], id.as_str());
        assert_eq!(d.body["data"]["state"], "succeeded");
        assert_eq!(d.body["data"]["percent_complete"], 100.0);
    }
    assert_eq!((first.answered, second.answered), (500, 200));
    // The retry waited its backoff (1 s): whole seconds apart at least.
    assert!(second.timestamp > first.timestamp, "{first:?} {second:?}");

    let (_, v) = server.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(v["progress"]["percent_complete"], 100.0, "{v}");
    let dir = server.stop().await;
    drop(dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancelled_job_sends_job_cancelled_with_its_progress() {
    let (url, mut rx, _) = receiver(&[]).await;
    let server = start(allow_loopback_hooks).await;
    let (status, _, job) = server
        .submit_obj(
            &slow_obj(),
            &format!(
                "steps=5000&until_converged=false&callback_url={}",
                query_escape(&url)
            ),
        )
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    server
        .poll_until(&id, TIMEOUT, |v| v["progress"]["step"].as_u64() >= Some(1))
        .await;
    let res = server
        .client
        .post(server.url(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .await
        .expect("cancel");
    assert!(res.status().is_success(), "{}", res.status());
    let d = next(&mut rx).await;
    assert!(d.signature_ok, "{d:?}");
    assert_eq!(d.body["type"], "job.cancelled");
    let (step, total) = (
        d.body["data"]["step"].as_f64().expect("step"),
        d.body["data"]["total_steps"].as_f64().expect("total"),
    );
    assert_eq!(total, 5000.0);
    let percent = d.body["data"]["percent_complete"]
        .as_f64()
        .expect("percent");
    assert!(
        (percent - step / total * 100.0).abs() < 1e-9,
        "{percent} vs {step}/{total}"
    );
    assert!(percent < 100.0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_that_ended_before_a_stop_is_delivered_after_the_restart() {
    // Every try of the first server is refused (503), so nothing is delivered before it stops.
    let (url, mut rx, script) = receiver(&[503; 64]).await;
    let server = start(allow_loopback_hooks).await;
    let (status, _, job) = server
        .submit_obj(
            &small_obj(),
            &format!(
                "steps=2&until_converged=false&callback_url={}",
                query_escape(&url)
            ),
        )
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let refused = next(&mut rx).await;
    assert_eq!(refused.answered, 503);
    let dir = server.stop().await;
    // Anything the stopped server still had in flight is drained before the receiver heals.
    while let Ok(d) = rx.try_recv() {
        assert_eq!(d.answered, 503);
    }
    script.lock().expect("script").clear();

    let server = start_in(dir, allow_loopback_hooks).await;
    let d = next(&mut rx).await;
    assert_eq!(d.answered, 200);
    assert!(d.signature_ok, "{d:?}");
    assert_eq!(d.id, format!("msg_{id}"));
    assert_eq!(d.body["type"], "job.succeeded");
    assert_eq!(d.body["data"]["id"], id.as_str());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn insecure_and_private_callbacks_are_refused_naming_the_field() {
    let server = start(|c| c.webhook_secret = Some(SECRET.to_vec())).await;
    for url in [
        "http://example.com/hook",
        "https://127.0.0.1:8443/hook",
        "https://[::1]/hook",
        "https://10.0.0.1/hook",
        "ftp://example.com/",
    ] {
        let (status, _, body) = server
            .submit_obj(
                &small_obj(),
                &format!("steps=1&callback_url={}", query_escape(url)),
            )
            .await;
        assert_eq!(status, 400, "{url}: {body}");
        assert!(body.to_string().contains("callback_url"), "{url}: {body}");
    }
    server.stop().await;
}

/// Issue 42 item 4: IPv6 forms that embed a loopback IPv4 address, and the benchmarking range,
/// are refused with a problem naming `callback_url` and the IPv4 address judged.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn embedded_ipv4_and_benchmarking_callbacks_are_refused_by_the_address_inside() {
    let server = start(|c| c.webhook_secret = Some(SECRET.to_vec())).await;
    for (url, says) in [
        (
            "https://[::127.0.0.1]/hook",
            "embeds 127.0.0.1, which is in 127.0.0.0/8 (loopback)",
        ),
        ("https://[::ffff:0:7f00:1]/hook", "embeds 127.0.0.1"),
        ("https://[64:ff9b::7f00:1]/hook", "(NAT64) embeds 127.0.0.1"),
        ("https://[2002:7f00:1::]/hook", "(6to4) embeds 127.0.0.1"),
        (
            "https://198.18.0.1/hook",
            "198.18.0.1 is in 198.18.0.0/15 (benchmarking)",
        ),
        (
            "https://[2001:db8::1]/hook",
            "2001:db8::/32 (documentation)",
        ),
    ] {
        let (status, _, body) = server
            .submit_obj(
                &small_obj(),
                &format!("steps=1&callback_url={}", query_escape(url)),
            )
            .await;
        assert_eq!(status, 400, "{url}: {body}");
        assert_eq!(body["field"], "callback_url", "{url}: {body}");
        assert_eq!(body["code"], "invalid_parameter", "{url}: {body}");
        let detail = body["detail"].as_str().unwrap_or_default();
        assert!(detail.contains(says), "{url}: {detail}");
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_job_sends_job_failed_with_its_error_code() {
    let (url, mut rx, _) = receiver(&[]).await;
    let server = start(allow_loopback_hooks).await;
    // A deadline far shorter than one step of the larger mesh: the job fails
    // `deadline_exceeded`.
    let (status, _, job) = server
        .submit_obj(
            &slow_obj(),
            &format!(
                "steps=5000&until_converged=false&deadline_secs=0.001&callback_url={}",
                query_escape(&url)
            ),
        )
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let d = next(&mut rx).await;
    assert!(d.signature_ok, "{d:?}");
    assert_eq!(d.body["type"], "job.failed");
    assert_eq!(d.body["data"]["id"], id.as_str());
    assert_eq!(
        d.body["data"]["error_code"], "deadline_exceeded",
        "{:?}",
        d.body
    );
    assert!(
        d.body["data"]["percent_complete"]
            .as_f64()
            .expect("percent")
            < 100.0
    );
    server.stop().await;
}
