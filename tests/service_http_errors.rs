//! Issue 12, part 4: one error contract. Every HTTP error is `application/problem+json` with
//! `code` and `detail`, and `field` when one parameter (or header, or multipart part) is at
//! fault. Each test here is one error the service used to get wrong: no field, an empty or
//! plain-text body, or silent acceptance.

mod service_http_support;

use service_http_support::*;
use std::time::Duration;

const JOB_TIMEOUT: Duration = Duration::from_secs(60);

/// The status and body of a problem response; fails unless it is problem+json with `code`
/// and `detail`.
async fn problem(res: reqwest::Response) -> (u16, serde_json::Value) {
    let status = res.status().as_u16();
    assert_eq!(
        res.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("application/problem+json"),
        "status {status}"
    );
    let p: serde_json::Value = res.json().await.expect("problem json");
    assert!(p["code"].as_str().is_some_and(|c| !c.is_empty()), "{p}");
    assert!(p["detail"].as_str().is_some_and(|d| !d.is_empty()), "{p}");
    (status, p)
}

async fn post_obj(srv: &TestServer, query: &str, body: String) -> reqwest::Response {
    srv.client
        .post(srv.url(&format!(
            "/v1/jobs?{}",
            service_http_support::conformal_unless_named(query)
        )))
        .header("content-type", "model/obj")
        .body(body)
        .send()
        .await
        .expect("POST /v1/jobs")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn query_type_errors_name_their_parameter() {
    let srv = start(|_| {}).await;
    for (q, field) in [
        ("tau=abc", "tau"),
        ("steps=1.5", "steps"),
        ("steps=-3", "steps"),
        ("include_positions=maybe", "include_positions"),
        ("filter.sigma=x&filter.k=1", "filter.sigma"),
        ("stepz=3", "stepz"),
    ] {
        let (st, p) = problem(post_obj(&srv, q, small_obj()).await).await;
        assert_eq!(st, 400, "{q}: {p}");
        assert_eq!(p["code"], "invalid_parameter", "{q}: {p}");
        assert_eq!(p["field"], field, "{q}: {p}");
    }
    // The other routes' queries too.
    for (path, field) in [
        ("/v1/jobs?page_size=ten", "page_size"),
        ("/v1/jobs/x/frames?from_step=-1", "from_step"),
        ("/v1/jobs/x/events?from_step=a", "from_step"),
    ] {
        let res = srv.client.get(srv.url(path)).send().await.expect("GET");
        let (st, p) = problem(res).await;
        assert_eq!((st, p["field"].as_str()), (400, Some(field)), "{path}: {p}");
    }
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn method_not_allowed_is_a_problem_and_keeps_allow() {
    let srv = start(|_| {}).await;
    let res = srv
        .client
        .put(srv.url("/v1/jobs"))
        .send()
        .await
        .expect("PUT");
    let allow = res
        .headers()
        .get("allow")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    let (st, p) = problem(res).await;
    assert_eq!(
        (st, p["code"].as_str()),
        (405, Some("method_not_allowed")),
        "{p}"
    );
    assert!(
        allow.contains("GET") && allow.contains("POST"),
        "Allow: {allow}"
    );
    // The problem names the same methods as the header.
    let detail = p["detail"].as_str().unwrap_or("");
    assert!(
        detail.contains("allowed: ") && detail.contains("GET") && detail.contains("POST"),
        "{p}"
    );
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn far_oversized_bodies_get_a_problem_naming_the_limit() {
    let limit = 64 * 1024;
    let srv = start(|c| c.limits.max_upload_bytes = limit).await;
    // Above limit + multipart slack: refused by the body-limit layer from Content-Length alone,
    // so the request goes out by hand with its headers only. (Sent whole by a client, the
    // body races the refusal: a client still writing when the server answers and closes can
    // see a broken pipe instead of the 413.)
    use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
    let length = 3 * (limit as usize + (1 << 20));
    let addr = srv.base.trim_start_matches("http://").to_string();
    let mut stream = tokio::net::TcpStream::connect(&addr)
        .await
        .expect("connect");
    stream
        .write_all(
            format!(
                "POST /v1/jobs HTTP/1.1\r\nHost: {addr}\r\nContent-Type: model/obj\r\n\
                 Content-Length: {length}\r\n\r\n"
            )
            .as_bytes(),
        )
        .await
        .expect("headers");
    let mut response = Vec::new();
    let mut chunk = [0u8; 4096];
    let complete = |r: &[u8]| -> Option<usize> {
        let text = std::str::from_utf8(r).ok()?;
        let (head, body) = text.split_once("\r\n\r\n")?;
        let len: usize = head.lines().find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.eq_ignore_ascii_case("content-length")
                .then(|| v.trim().parse().ok())
                .flatten()
        })?;
        (body.len() >= len).then_some(head.len() + 4 + len)
    };
    let end = loop {
        if let Some(end) = complete(&response) {
            break end;
        }
        let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut chunk))
            .await
            .expect("the refusal comes before any body byte")
            .expect("read");
        assert!(n > 0, "closed before a whole response: {response:?}");
        response.extend_from_slice(&chunk[..n]);
    };
    let text = String::from_utf8_lossy(&response[..end]).to_string();
    let (head, body) = text.split_once("\r\n\r\n").expect("head");
    assert!(head.starts_with("HTTP/1.1 413"), "{head}");
    assert!(
        head.to_ascii_lowercase()
            .contains("content-type: application/problem+json"),
        "{head}"
    );
    let p: serde_json::Value = serde_json::from_str(body).expect("problem json");
    assert_eq!(p["code"].as_str(), Some("too_large"), "{p}");
    assert!(p["limit"].as_u64().is_some(), "{p}");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn garbage_last_event_id_and_forged_page_token_are_refused() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv.submit_obj(&small_obj(), "steps=2").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    for bad in ["abc", "-1", "1.5"] {
        let res = srv
            .client
            .get(srv.url(&format!("/v1/jobs/{id}/events")))
            .header("Last-Event-ID", bad)
            .send()
            .await
            .expect("events");
        let (st, p) = problem(res).await;
        assert_eq!(st, 400, "{bad}: {p}");
        assert_eq!(p["code"], "invalid_parameter", "{p}");
        assert_eq!(p["field"], "Last-Event-ID", "{p}");
    }
    srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;

    // Two more jobs, so that a page of one has a next page.
    for _ in 0..2 {
        let (status, _, job) = srv.submit_obj(&small_obj(), "steps=1").await;
        assert_eq!(status, 202, "{job}");
    }
    let (st, page) = srv.get_json("/v1/jobs?page_size=1").await;
    assert_eq!(st, 200, "{page}");
    let token = page["next_page_token"]
        .as_str()
        .expect("a next page")
        .to_string();
    let (st, next) = srv
        .get_json(&format!("/v1/jobs?page_size=1&page_token={token}"))
        .await;
    assert_eq!(st, 200, "{next}");
    assert_eq!(next["jobs"].as_array().map(Vec::len), Some(1), "{next}");

    // Well-formed for the backend but never handed out: `at:0:…` would list nothing.
    use base64::Engine as _;
    let forged = base64::engine::general_purpose::URL_SAFE_NO_PAD.encode("at:0:x");
    let edited = format!("{}x", &token[..token.len() - 1]);
    for t in [forged.as_str(), edited.as_str(), "!!!", "a.b"] {
        let res = srv
            .client
            .get(srv.url(&format!("/v1/jobs?page_token={t}")))
            .send()
            .await
            .expect("list");
        let (st, p) = problem(res).await;
        assert_eq!(st, 400, "{t}: {p}");
        assert_eq!(p["code"], "invalid_parameter", "{p}");
        assert_eq!(p["field"], "page_token", "{p}");
    }
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_user_text_is_clipped_in_details() {
    let srv = start(|_| {}).await;
    // 20 000 characters: well inside what hyper and the `http` crate accept in a URI (64 KiB).
    let long = "x".repeat(20_000);
    for q in [format!("method={long}"), format!("boundary={long}")] {
        let res = srv
            .client
            .post(srv.url(&format!("/v1/jobs?{q}")))
            .header("content-type", "model/obj")
            .body(small_obj())
            .send()
            .await
            .expect("POST");
        let (st, p) = problem(res).await;
        assert_eq!(st, 400, "{p}");
        let detail = p["detail"].as_str().unwrap_or("");
        assert!(
            detail.contains('…') && detail.chars().count() <= 1025,
            "{} chars",
            detail.len()
        );
    }
    // A long header value echoed back (Last-Event-ID) is clipped too.
    let (status, _, job) = srv.submit_obj(&small_obj(), "steps=1").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id");
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/events")))
        .header("Last-Event-ID", "y".repeat(4000))
        .send()
        .await
        .expect("events");
    let (st, p) = problem(res).await;
    assert_eq!(st, 400);
    let detail = p["detail"].as_str().unwrap_or("");
    assert!(detail.contains('…') && detail.len() < 1000, "{detail}");
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn result_defaults_to_the_input_format() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv.submit_obj(&small_obj(), "steps=1").await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    srv.poll_until(&id, JOB_TIMEOUT, is_terminal).await;
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/result")))
        .send()
        .await
        .expect("result");
    assert_eq!(res.status(), 200);
    assert_eq!(
        res.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("model/obj")
    );
    // A named format still wins.
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/result?format=glb")))
        .send()
        .await
        .expect("result");
    assert_eq!(
        res.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("model/gltf-binary")
    );
    srv.stop().await;
}

fn mesh_part() -> reqwest::multipart::Part {
    reqwest::multipart::Part::text(small_obj()).file_name("m.obj")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ambiguous_multipart_uploads_are_refused() {
    let srv = start(|_| {}).await;
    let send = |form: reqwest::multipart::Form, q: &'static str| {
        srv.client
            .post(srv.url(&format!("/v1/jobs{q}")))
            .multipart(form)
            .send()
    };
    let two_meshes = reqwest::multipart::Form::new()
        .part("mesh", mesh_part())
        .part("mesh", mesh_part());
    let (st, p) = problem(send(two_meshes, "").await.expect("send")).await;
    assert_eq!((st, p["field"].as_str()), (400, Some("mesh")), "{p}");
    assert_eq!(p["code"], "invalid_multipart");

    let two_params = reqwest::multipart::Form::new()
        .part("mesh", mesh_part())
        .text("params", "{}")
        .text("params", r#"{"steps": 2}"#);
    let (st, p) = problem(send(two_params, "").await.expect("send")).await;
    assert_eq!((st, p["field"].as_str()), (400, Some("params")), "{p}");
    assert_eq!(p["code"], "invalid_multipart");

    let both = reqwest::multipart::Form::new()
        .part("mesh", mesh_part())
        .text("params", r#"{"steps": 2}"#);
    let (st, p) = problem(send(both, "?steps=3").await.expect("send")).await;
    assert_eq!((st, p["field"].as_str()), (400, Some("params")), "{p}");
    assert_eq!(p["code"], "invalid_parameter");
    assert!(
        p["detail"]
            .as_str()
            .is_some_and(|d| d.contains("query string")),
        "{p}"
    );

    // Query parameters alone with multipart still work.
    let only_query = reqwest::multipart::Form::new().part("mesh", mesh_part());
    let res = send(only_query, "?steps=2").await.expect("send");
    assert_eq!(res.status(), 202);
    srv.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mesh_read_refusals_reach_the_client_as_problems() {
    let srv = start(|_| {}).await;
    let short_face = format!("{}f 1 2\n", small_obj());
    let (st, p) = problem(post_obj(&srv, "", short_face).await).await;
    assert_eq!(st, 422, "{p}");
    assert_eq!(p["code"], "parse_error", "{p}");
    assert!(
        p["detail"].as_str().is_some_and(|d| d.contains("line")),
        "{p}"
    );
    let huge = obj_with_huge_coordinate();
    let (st, p) = problem(post_obj(&srv, "", huge).await).await;
    assert_eq!(st, 422, "{p}");
    assert_eq!(p["code"], "coordinate_out_of_range", "{p}");
    srv.stop().await;
}

/// `small_obj` with its first `v` line's x replaced by 1e300: finite, but its square is not.
fn obj_with_huge_coordinate() -> String {
    let obj = small_obj();
    let mut out = String::new();
    let mut done = false;
    for line in obj.lines() {
        if !done && line.starts_with("v ") {
            let words: Vec<&str> = line.split_whitespace().collect();
            out.push_str(&format!("v 1e300 {} {}\n", words[2], words[3]));
            done = true;
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openapi_responses_all_have_descriptions_and_steps_minimum_is_one() {
    let srv = start(|_| {}).await;
    let (st, doc) = srv.get_json("/openapi.json").await;
    assert_eq!(st, 200);
    let mut missing = Vec::new();
    let paths = doc["paths"].as_object().expect("paths");
    for (path, ops) in paths {
        for (method, op) in ops.as_object().expect("operations") {
            let Some(responses) = op.get("responses").and_then(|r| r.as_object()) else {
                continue;
            };
            for (status, response) in responses {
                let ok = response
                    .get("description")
                    .and_then(|d| d.as_str())
                    .is_some_and(|d| !d.is_empty());
                if !ok {
                    missing.push(format!("{method} {path} {status}"));
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "responses without description: {missing:?}"
    );

    // `steps`: the spec schema (which is also the `params` part's), and the query parameters.
    for schema in ["JobSpec", "CurveParamsView"] {
        let steps = &doc["components"]["schemas"][schema]["properties"]["steps"];
        assert_eq!(steps["minimum"], 1, "{schema}.steps: {steps}");
    }
    for (path, method) in [("/v1/jobs", "post"), ("/v1/curves:fair", "post")] {
        let params = doc["paths"][path][method]["parameters"]
            .as_array()
            .expect("parameters");
        let steps = params
            .iter()
            .find(|p| p["name"] == "steps")
            .expect("a steps parameter");
        assert_eq!(steps["schema"]["minimum"], 1, "{path} steps: {steps}");
    }
    srv.stop().await;
}
