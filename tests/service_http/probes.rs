//! Probes, metrics, OpenAPI, docs, CORS and request ids.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn probes_metrics_openapi_docs_cors_and_request_id() {
    let options = willow_service::api::server::ServeOptions {
        app: willow_service::api::server::AppOptions {
            cors_origins: vec![
                willow_service::api::server::parse_origin("http://example.test")
                    .expect("an origin"),
            ],
            ..Default::default()
        },
        ..Default::default()
    };
    let srv = start_with(tempfile::tempdir().expect("temp dir"), |_| {}, options).await;
    let res = srv.get("/healthz").await;
    assert_eq!(res.status(), 200);
    let rid = res
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .map(str::to_string);
    assert!(
        rid.is_some_and(|r| r.len() >= 32),
        "a request id is generated"
    );
    let res = srv
        .client
        .get(srv.url("/healthz"))
        .header("x-request-id", "abc-123")
        .send()
        .await
        .expect("healthz");
    assert_eq!(
        res.headers()["x-request-id"],
        "abc-123",
        "a given request id is echoed"
    );
    let res = srv.get("/readyz").await;
    assert_eq!(res.status(), 200);

    let (st, _, j) = srv.submit_obj(&small_obj(), "steps=2").await;
    assert_eq!(st, 202);
    srv.poll_until(j["id"].as_str().expect("id"), JOB_TIMEOUT, is_terminal)
        .await;
    let text = srv.get("/metrics").await.text().await.expect("text");
    for name in [
        "willow_queue_depth",
        "willow_jobs_running",
        "willow_jobs_finished_total{outcome=\"succeeded\"",
        "willow_step_seconds_bucket",
        "willow_job_seconds_count",
    ] {
        assert!(text.contains(name), "/metrics lacks {name}:\n{text}");
    }

    let (st, doc) = srv.get_json("/openapi.json").await;
    assert_eq!(st, 200);
    assert!(doc["openapi"].as_str().is_some_and(|v| v.starts_with("3.")));
    for path in [
        "/v1/jobs",
        "/v1/jobs/{id}",
        "/v1/jobs/{id}/events",
        "/v1/jobs/{id}/result",
    ] {
        assert!(doc["paths"].get(path).is_some(), "OpenAPI lacks {path}");
    }
    let res = srv.get("/docs").await;
    assert_eq!(res.status(), 200);
    let html = res.text().await.expect("html");
    assert!(
        html.contains("/openapi.json") && !html.contains("https://"),
        "self-contained docs page"
    );

    // CORS, for the listed origin only: a browser can read Location and Retry-After.
    let res = srv
        .client
        .post(srv.url("/v1/jobs?steps=1"))
        .header("origin", "http://example.test")
        .header("content-type", "model/obj")
        .body(small_obj())
        .send()
        .await
        .expect("cors post");
    assert_eq!(res.status(), 202);
    assert_eq!(
        res.headers()["access-control-allow-origin"],
        "http://example.test"
    );
    let vary = res.headers()["vary"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(vary.contains("origin"), "{vary}");
    let exposed = res.headers()["access-control-expose-headers"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(
        exposed.contains("location") && exposed.contains("retry-after"),
        "{exposed}"
    );
    let res = srv
        .client
        .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
        .header("origin", "http://example.test")
        .header("access-control-request-method", "POST")
        .header(
            "access-control-request-headers",
            "idempotency-key,content-type",
        )
        .send()
        .await
        .expect("preflight");
    assert!(res.status().is_success());
    let allowed = res.headers()["access-control-allow-headers"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(allowed.contains("idempotency-key"), "{allowed}");
    assert_eq!(
        res.headers()["access-control-allow-origin"],
        "http://example.test"
    );
    // Another origin gets no grant, on the preflight or the request itself.
    let res = srv
        .client
        .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
        .header("origin", "http://other.test")
        .header("access-control-request-method", "POST")
        .send()
        .await
        .expect("preflight");
    assert!(res.headers().get("access-control-allow-origin").is_none());
    let res = srv
        .client
        .get(srv.url("/healthz"))
        .header("origin", "http://other.test")
        .send()
        .await
        .expect("get");
    assert_eq!(res.status(), 200);
    assert!(res.headers().get("access-control-allow-origin").is_none());

    // Draining: readiness turns false and submissions get 503 with Retry-After.
    srv.jobs.begin_drain();
    let res = srv.get("/readyz").await;
    assert_eq!(res.status(), 503);
    let (st, h, p) = srv.submit_obj(&small_obj(), "steps=1").await;
    assert_eq!(st, 503, "{p}");
    assert!(h.get("retry-after").is_some());
    assert_eq!(p["code"], "shutting_down");
    srv.stop().await;
}
