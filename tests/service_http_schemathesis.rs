//! Issue 12, part 5: what schemathesis (scripts/schemathesis.sh) found against the served
//! OpenAPI document, one regression each. Every response must have a status the document
//! lists for its operation, with the documented content type.

mod service_http_support;

use service_http_support::*;

/// Sends `GET path_and_query` (with `headers`) and checks the answer against the operation
/// `template` of the served document.
async fn assert_documented(
    srv: &TestServer,
    doc: &serde_json::Value,
    template: &str,
    path_and_query: &str,
    headers: &[(&str, &str)],
) {
    let mut req = srv.client.get(srv.url(path_and_query));
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let res = req.send().await.expect("GET");
    let status = res.status().as_u16().to_string();
    let content_type = res
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    let response = &doc["paths"][template]["get"]["responses"][&status];
    assert!(
        response.is_object(),
        "GET {path_and_query}: status {status} is not documented for {template}"
    );
    let documented: Vec<&String> = response["content"]
        .as_object()
        .map(|c| c.keys().collect())
        .unwrap_or_default();
    assert!(
        documented
            .iter()
            .any(|t| content_type.starts_with(t.as_str())),
        "GET {path_and_query}: {status} is {content_type}, documented {documented:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameter_errors_are_documented_400s() {
    let srv = start(|_| {}).await;
    let (st, doc) = srv.get_json("/openapi.json").await;
    assert_eq!(st, 200);
    // The four requests schemathesis reported as "undocumented status code" (400).
    assert_documented(
        &srv,
        &doc,
        "/v1/jobs/{id}/events",
        "/v1/jobs/0/events?from_step=-1",
        &[("last-event-id", "")],
    )
    .await;
    assert_documented(
        &srv,
        &doc,
        "/v1/jobs/{id}/frames",
        "/v1/jobs/0/frames?page_size=0&x-unknown=42",
        &[],
    )
    .await;
    assert_documented(
        &srv,
        &doc,
        "/v1/jobs/{id}/frames/{step}",
        "/v1/jobs/0/frames/-1?format=",
        &[],
    )
    .await;
    assert_documented(
        &srv,
        &doc,
        "/v1/jobs/{id}/result",
        "/v1/jobs/0/result?format=",
        &[],
    )
    .await;
}
