//! The CORS allow-list (issue 12, item 2): preflights and responses, origins validated.

use super::*;

#[tokio::test]
async fn cors_is_an_allow_list() {
    let allowed = "https://app.example";
    let mut options = limits(|_| {});
    options.app.cors_origins = vec![parse_origin(allowed).expect("origin")];
    let srv = start(options).await;
    let client = fresh_client();

    // An allowed origin: its own origin echoed, Vary: Origin, the exposed headers.
    let res = client
        .post(srv.url("/v1/jobs?steps=1"))
        .header("origin", allowed)
        .header("content-type", "model/obj")
        .body(small_obj())
        .send()
        .await
        .expect("post");
    assert_eq!(res.status(), 202);
    assert_eq!(res.headers()["access-control-allow-origin"], allowed);
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
    let preflight = |origin: &'static str| {
        client
            .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
            .header("origin", origin)
            .header("access-control-request-method", "POST")
            .header(
                "access-control-request-headers",
                "idempotency-key,content-type",
            )
            .send()
    };
    let res = preflight(allowed).await.expect("preflight");
    assert!(res.status().is_success());
    assert_eq!(res.headers()["access-control-allow-origin"], allowed);
    let headers = res.headers()["access-control-allow-headers"]
        .to_str()
        .expect("ascii")
        .to_ascii_lowercase();
    assert!(headers.contains("idempotency-key"), "{headers}");

    // Any other origin: no grant, on the request or the preflight.
    for origin in [
        "https://evil.example",
        "https://app.example.evil",
        "http://app.example",
    ] {
        let res = client
            .get(srv.url("/healthz"))
            .header("origin", origin)
            .send()
            .await
            .expect("get");
        assert_eq!(res.status(), 200);
        assert!(
            res.headers().get("access-control-allow-origin").is_none(),
            "{origin}"
        );
        assert!(res
            .headers()
            .get("access-control-allow-credentials")
            .is_none());
        let res = preflight(origin).await.expect("preflight");
        assert!(
            res.headers().get("access-control-allow-origin").is_none(),
            "{origin}"
        );
    }
    srv.stop().await;

    // The default: no origin allowed, no CORS headers at all; the built-in page is served
    // from the same origin and needs none.
    let srv = start(limits(|_| {})).await;
    let res = client
        .get(srv.url("/healthz"))
        .header("origin", allowed)
        .send()
        .await
        .expect("get");
    assert_eq!(res.status(), 200);
    assert!(
        !res.headers()
            .keys()
            .any(|k| k.as_str().starts_with("access-control-")),
        "{:?}",
        res.headers()
    );
    let res = preflight_to(&client, &srv, allowed).await;
    assert!(
        !res.headers()
            .keys()
            .any(|k| k.as_str().starts_with("access-control-")),
        "{:?}",
        res.headers()
    );
    let page = client.get(srv.url("/")).send().await.expect("page");
    assert_eq!(page.status(), 200);
    srv.stop().await;
}

async fn preflight_to(
    client: &reqwest::Client,
    srv: &TestServer,
    origin: &str,
) -> reqwest::Response {
    client
        .request(reqwest::Method::OPTIONS, srv.url("/v1/jobs"))
        .header("origin", origin)
        .header("access-control-request-method", "POST")
        .send()
        .await
        .expect("preflight")
}

#[test]
fn cors_origins_are_validated_and_normalised() {
    let ok = |s: &str| {
        parse_origin(s)
            .expect(s)
            .to_str()
            .expect("ascii")
            .to_string()
    };
    assert_eq!(ok("https://app.example"), "https://app.example");
    assert_eq!(ok("HTTPS://App.Example:443"), "https://app.example");
    assert_eq!(ok("http://localhost:5173"), "http://localhost:5173");
    assert_eq!(ok("http://127.0.0.1:80"), "http://127.0.0.1");
    for bad in [
        "*",
        "null",
        "app.example",
        "https://app.example/",
        "https://app.example/path",
        "ftp://app.example",
        "https://user@app.example",
        "https://",
        "https://app.example:port",
    ] {
        let e = parse_origin(bad).expect_err(bad);
        assert!(e.contains("--cors-origin"), "{e}");
    }
}
