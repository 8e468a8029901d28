//! The serve flags' defaults and checks, and request ids that are replaced, not echoed.

use super::*;

#[test]
fn serve_flags_have_defaults_and_are_validated() {
    use clap::Parser;
    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        serve: willow_service::api::server::ServeArgs,
    }
    let parse = |args: &[&str]| {
        let mut all = vec!["willow"];
        all.extend_from_slice(args);
        Cli::try_parse_from(all)
            .expect("flags parse")
            .serve
            .serve_options()
    };
    let o = parse(&[]).expect("the defaults are valid");
    assert!(o.app.cors_origins.is_empty());
    assert_eq!(o.conn.header_read_timeout, Duration::from_secs(10));
    assert_eq!(o.conn.body_timeout, Duration::from_secs(30));
    assert_eq!(o.conn.body_min_rate, 32 * 1024);
    assert_eq!(o.conn.idle_timeout, Duration::from_secs(60));
    assert_eq!(o.conn.max_connections, 1024);
    assert_eq!(o.conn.max_requests_per_connection, 1000);
    assert_eq!(o.conn.max_streams_per_connection, 128);
    let o = parse(&[
        "--cors-origin",
        "https://a.example",
        "--cors-origin",
        "http://localhost:5173",
        "--idle-timeout-secs",
        "1.5",
        "--max-requests-per-connection",
        "0",
    ])
    .expect("valid");
    assert_eq!(o.app.cors_origins.len(), 2);
    assert_eq!(o.conn.idle_timeout, Duration::from_millis(1500));
    for (flag, value) in [
        ("--header-read-timeout-secs", "0"),
        ("--body-timeout-secs=-1", ""),
        ("--idle-timeout-secs", "NaN"),
        ("--keepalive-interval-secs", "1e300"),
        ("--max-connections", "0"),
        ("--max-streams-per-connection", "0"),
        ("--cors-origin", "*"),
    ] {
        let args: Vec<&str> = [flag, value]
            .into_iter()
            .filter(|a| !a.is_empty())
            .collect();
        let e = parse(&args).expect_err(flag);
        let name = flag.split('=').next().unwrap_or(flag);
        assert!(e.contains(name), "{flag} {value}: {e}");
    }
}

/// A client's `X-Request-Id` is echoed when it is a plausible id, and replaced by a fresh one
/// when it is long (8 KB was seen echoed and logged) or carries other characters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn implausible_request_ids_are_replaced_not_echoed() {
    let srv = start(ServeOptions::default()).await;
    let client = reqwest::Client::new();
    let id_for = |given: Option<String>| {
        let mut req = client.get(srv.url("/healthz"));
        if let Some(g) = given {
            req = req.header("x-request-id", g);
        }
        async move {
            let res = req.send().await.expect("healthz");
            assert_eq!(res.status(), 200);
            res.headers()["x-request-id"]
                .to_str()
                .expect("ascii")
                .to_string()
        }
    };
    let fine = "00-4bf92f3577b34da6a3ce929d0e0e4736-00f067aa0ba902b7-01".to_string();
    assert_eq!(id_for(Some(fine.clone())).await, fine);
    let longest = "a".repeat(willow_service::api::server::MAX_REQUEST_ID_LEN);
    assert_eq!(id_for(Some(longest.clone())).await, longest);
    for bad in [
        "a".repeat(8192),
        "a".repeat(willow_service::api::server::MAX_REQUEST_ID_LEN + 1),
        "id with spaces".to_string(),
        "id\"quoted\"".to_string(),
    ] {
        let got = id_for(Some(bad.clone())).await;
        assert_ne!(got, bad);
        assert_eq!(got.len(), 36, "a fresh UUID: {got}");
    }
    srv.stop().await;
}
