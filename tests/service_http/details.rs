//! Issue 42, item 5: the error details (each refusal says what was wrong, in a problem body)
//! and `Range` on mesh downloads.

use super::errors::problem;
use super::*;

fn detail(p: &serde_json::Value) -> &str {
    p["detail"].as_str().unwrap_or_default()
}

/// 414 and 431 have problem bodies (hyper's own answers are empty), on HTTP/1.1 and h2c.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn request_heads_over_the_limits_get_problem_bodies() {
    let srv = start(|_| {}).await;
    let long_query = format!("/v1/jobs?page_token={}", "a".repeat(33 << 10));
    let h2 = reqwest::Client::builder()
        .http2_prior_knowledge()
        .build()
        .expect("h2c client");
    for (version, client) in [("HTTP/1.1", &srv.client), ("h2c", &h2)] {
        let (status, p) =
            problem(client.get(srv.url(&long_query)).send().await.expect("send")).await;
        assert_eq!(status, 414, "{version}: {p}");
        assert_eq!(p["code"], "uri_too_long", "{version}: {p}");
        assert_eq!(p["title"], "URI Too Long", "{version}: {p}");
        assert_eq!(p["limit"], 32768, "{version}: {p}");
        assert!(detail(&p).contains("the limit is 32768"), "{version}: {p}");

        let big = "b".repeat(20 << 10);
        let (status, p) = problem(
            client
                .get(srv.url("/v1/jobs"))
                .header("x-big", big.as_str())
                .send()
                .await
                .expect("send"),
        )
        .await;
        assert_eq!(status, 431, "{version}: {p}");
        assert_eq!(p["code"], "headers_too_large", "{version}: {p}");
        assert_eq!(p["status"], 431, "{version}: {p}");
        assert_eq!(p["limit"], 16384, "{version}: {p}");

        let mut many = client.get(srv.url("/v1/jobs"));
        for i in 0..150 {
            many = many.header(format!("x-h{i}"), "1");
        }
        let (status, p) = problem(many.send().await.expect("send")).await;
        assert_eq!(status, 431, "{version}: {p}");
        assert!(
            detail(&p).contains("header fields; the limit is 100"),
            "{version}: {p}"
        );
    }
    // Under the limits nothing changes.
    let res = srv.get("/v1/jobs?page_size=5").await;
    assert_eq!(res.status(), 200);
    srv.stop().await;
}

/// A binary STL whose header's triangle count does not match its length says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_binary_stl_with_a_wrong_count_names_the_count_and_the_size() {
    let srv = start(|_| {}).await;
    let mut stl = vec![0u8; 80];
    stl.extend_from_slice(&4u32.to_le_bytes());
    for t in 0..3u32 {
        stl.extend_from_slice(&[0u8; 12]);
        for k in 0..9u32 {
            stl.extend_from_slice(&((t * 9 + k) as f32 + 0.25).to_le_bytes());
        }
        stl.extend_from_slice(&[0, 0]);
    }
    let res = srv
        .client
        .post(srv.url("/v1/jobs"))
        .header("content-type", "model/stl")
        .body(stl)
        .send()
        .await
        .expect("send");
    let (status, p) = problem(res).await;
    assert_eq!(status, 422, "{p}");
    assert_eq!(p["code"], "parse_error", "{p}");
    assert!(
        detail(&p).contains(
            "binary STL header says 4 triangles (84 + 50·4 = 284 bytes) but the file has 234 bytes"
        ),
        "{p}"
    );
    srv.stop().await;
}

/// A truncated `params` part names the field `params` and where the JSON broke off.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_params_part_names_params_and_the_position() {
    let srv = start(|_| {}).await;
    for text in [
        r#"{"steps": 3, "tau": "#,
        r#"{"filter": {"sigma": 0.1"#,
        "{\n  \"steps\": 3,\n",
    ] {
        let form = reqwest::multipart::Form::new()
            .part(
                "mesh",
                reqwest::multipart::Part::text(small_obj()).file_name("m.obj"),
            )
            .text("params", text);
        let res = srv
            .client
            .post(srv.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .expect("send");
        let (status, p) = problem(res).await;
        assert_eq!(status, 400, "{text}: {p}");
        assert_eq!(p["field"], "params", "{text}: {p}");
        assert!(
            detail(&p).starts_with("invalid parameter `params`: the `params` part is not valid JSON: EOF while parsing"),
            "{text}: {p}"
        );
        assert!(p["line"].is_u64() && p["column"].is_u64(), "{text}: {p}");
    }
    srv.stop().await;
}

/// A bad integer in a query string names the parameter, what it must be and the value.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_query_integers_say_what_is_expected() {
    let srv = start(|_| {}).await;
    for (path, field, value) in [
        ("/v1/jobs/x/frames?from_step=-1", "from_step", "-1"),
        ("/v1/jobs/x/frames?page_size=ten", "page_size", "ten"),
        ("/v1/jobs/x/events?from_step=1.5", "from_step", "1.5"),
        (
            "/v1/jobs?page_size=99999999999999999999999",
            "page_size",
            "99999999999999999999999",
        ),
    ] {
        let (status, p) = problem(srv.get(path).await).await;
        assert_eq!(status, 400, "{path}: {p}");
        assert_eq!(p["field"], field, "{path}: {p}");
        assert_eq!(
            detail(&p),
            format!("invalid parameter `{field}`: must be a non-negative integer, got `{value}`"),
            "{path}"
        );
    }
    srv.stop().await;
}

/// A request body with a content coding is refused (415, naming it, `Accept-Encoding:
/// identity`); `identity` is no coding and passes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn content_codings_on_request_bodies_are_refused_with_415() {
    let srv = start(|_| {}).await;
    for coding in ["br", "deflate", "gzip", "zstd", "gzip, identity"] {
        let res = srv
            .client
            .post(srv.url("/v1/jobs?method=conformal&steps=1"))
            .header("content-type", "model/obj")
            .header("content-encoding", coding)
            .body(small_obj())
            .send()
            .await
            .expect("send");
        assert_eq!(
            res.headers()
                .get("accept-encoding")
                .and_then(|v| v.to_str().ok()),
            Some("identity"),
            "{coding}"
        );
        let (status, p) = problem(res).await;
        assert_eq!(status, 415, "{coding}: {p}");
        assert_eq!(p["code"], "unsupported_content_encoding", "{coding}: {p}");
        let named = coding.trim_end_matches(", identity");
        assert_eq!(p["encoding"], named, "{coding}: {p}");
        assert!(
            detail(&p).contains(&format!("`Content-Encoding: {named}` is not supported")),
            "{coding}: {p}"
        );
    }
    let res = srv
        .client
        .post(srv.url("/v1/curves:fair"))
        .header("content-type", "application/json")
        .header("content-encoding", "br")
        .body("{}")
        .send()
        .await
        .expect("send");
    assert_eq!(res.status(), 415);
    let res = srv
        .client
        .post(srv.url("/v1/jobs?method=conformal&steps=1"))
        .header("content-type", "model/obj")
        .header("content-encoding", "identity")
        .body(small_obj())
        .send()
        .await
        .expect("send");
    assert_eq!(res.status(), 202);
    srv.stop().await;
}

/// One rule for names the API defines: any case, on every parameter (`method`, `format`,
/// `boundary`, `state`, booleans); an unknown name is still refused naming its field.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn names_are_read_in_any_case_everywhere() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv
        .submit_obj(
            &small_obj(),
            "method=Conformal&steps=1&safeguard=True&boundary=FREE&include_positions=FALSE",
        )
        .await;
    assert_eq!(status, 202, "{job}");
    assert_eq!(job["params"]["method"], "conformal", "{job}");
    assert_eq!(job["params"]["safeguard"], true, "{job}");
    assert_eq!(job["params"]["include_positions"], false, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    let (status, list) = srv.get_json("/v1/jobs?state=Queued").await;
    assert_eq!(status, 200, "{list}");
    srv.poll_until(&id, JOB_TIMEOUT, |j| j["state"] == "succeeded")
        .await;
    let res = srv.get(&format!("/v1/jobs/{id}/result?format=GLB")).await;
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["content-type"], "model/gltf-binary");
    for (query, field) in [
        ("method=Conformale", "method"),
        ("safeguard=yes", "safeguard"),
    ] {
        let (status, _, p) = srv.submit_obj(&small_obj(), query).await;
        assert_eq!(status, 400, "{query}: {p}");
        assert_eq!(p["field"], field, "{query}: {p}");
    }
    let (status, p) = srv.get_json("/v1/jobs?state=Done").await;
    assert_eq!(
        (status.as_u16(), &p["field"]),
        (400, &serde_json::json!("state"))
    );
    srv.stop().await;
}

/// `Range` on the result and on a frame: 206 with `Content-Range`, the bytes of the whole
/// file at that place; 416 past the end; several ranges and `If-Range` get the whole file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn downloads_answer_single_byte_ranges() {
    let srv = start(|_| {}).await;
    let (status, _, job) = srv
        .submit_obj(&small_obj(), "steps=2&until_converged=false")
        .await;
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    srv.poll_until(&id, JOB_TIMEOUT, |j| j["state"] == "succeeded")
        .await;
    for path in [
        format!("/v1/jobs/{id}/result"),
        format!("/v1/jobs/{id}/result?format=glb"),
        format!("/v1/jobs/{id}/frames/0?format=obj"),
    ] {
        let whole = srv.get(&path).await;
        assert_eq!(whole.status(), 200, "{path}");
        assert_eq!(whole.headers()["accept-ranges"], "bytes", "{path}");
        let whole = whole.bytes().await.expect("body").to_vec();
        let len = whole.len();
        assert!(len > 100, "{path}: {len}");
        let ranged = |range: String| srv.client.get(srv.url(&path)).header("range", range).send();
        for (range, first, last) in [
            ("bytes=0-9".to_string(), 0, 9),
            (format!("bytes={}-", len - 7), len - 7, len - 1),
            ("bytes=-5".to_string(), len - 5, len - 1),
            (format!("bytes=50-{}", len * 2), 50, len - 1),
        ] {
            let res = ranged(range.clone()).await.expect("send");
            assert_eq!(res.status(), 206, "{path} {range}");
            assert_eq!(
                res.headers()["content-range"],
                format!("bytes {first}-{last}/{len}").as_str(),
                "{path} {range}"
            );
            assert_eq!(res.headers()["accept-ranges"], "bytes");
            assert_eq!(
                res.headers()["content-length"],
                (last - first + 1).to_string().as_str()
            );
            let part = res.bytes().await.expect("body");
            assert_eq!(&part[..], &whole[first..=last], "{path} {range}");
        }
        let res = ranged(format!("bytes={len}-")).await.expect("send");
        assert_eq!(
            res.headers()["content-range"],
            format!("bytes */{len}").as_str()
        );
        let (status, p) = problem(res).await;
        assert_eq!(status, 416, "{path}: {p}");
        assert_eq!(p["code"], "range_not_satisfiable", "{p}");
        assert_eq!(p["length"], len, "{p}");
        for range in ["bytes=0-1,5-6", "bytes=9-2", "lines=1-2"] {
            let res = ranged(range.to_string()).await.expect("send");
            assert_eq!(res.status(), 200, "{path} {range}");
            assert_eq!(res.bytes().await.expect("body").len(), len);
        }
        let res = srv
            .client
            .get(srv.url(&path))
            .header("range", "bytes=0-9")
            .header("if-range", "\"anything\"")
            .send()
            .await
            .expect("send");
        assert_eq!(
            res.status(),
            200,
            "{path}: If-Range never matches (no validator)"
        );
    }
    srv.stop().await;
}
