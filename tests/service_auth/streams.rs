//! Stream tokens: one job's events and nothing else, for a while.

use super::*;

/// A token minted for job A opens A's events and frames as `?access_token=`, and nothing else:
/// not job B, not other routes, not as a bearer; SSE with the header works too.
#[tokio::test]
async fn stream_tokens() {
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    let auth = bearer(&key);
    let a = create_job(&server, &auth).await;
    let b = create_job(&server, &auth).await;

    assert_401(mint(&server, &a, None).await, "missing_credentials", "").await;
    let res = mint(&server, "no-such-job", Some(&auth)).await;
    assert_eq!(res.status(), 404);
    let res = mint(&server, &a, Some(&auth)).await;
    assert_eq!(res.status(), 200);
    assert_eq!(
        res.headers()
            .get("cache-control")
            .and_then(|v| v.to_str().ok()),
        Some("no-store")
    );
    let body: Value = res.json().await.expect("json");
    let token = body["token"].as_str().expect("token").to_string();
    let expires_in = body["expires_in"].as_u64().expect("expires_in");
    assert!((290..=300).contains(&expires_in), "{expires_in}");
    assert!(body["expires_at"]
        .as_str()
        .expect("expires_at")
        .ends_with('Z'));

    // A's events with the token: the whole stream, to `done`.
    let res = server
        .get(&format!("/v1/jobs/{a}/events?access_token={token}"), None)
        .await;
    assert_eq!(res.status(), 200);
    let events = read_sse(res, PATIENCE).await;
    assert_eq!(events.last().map(|e| e.event.as_str()), Some("done"));
    // Other query parameters still reach the handler (the token is taken out first).
    let res = server
        .get(
            &format!("/v1/jobs/{a}/events?from_step=1&access_token={token}"),
            None,
        )
        .await;
    assert_eq!(res.status(), 200);
    let events = read_sse(res, PATIENCE).await;
    assert!(events
        .iter()
        .filter(|e| e.event == "frame")
        .all(|e| e.data["step"].as_u64() >= Some(1)));
    // A frame download of A.
    let res = server
        .get(&format!("/v1/jobs/{a}/frames/0?access_token={token}"), None)
        .await;
    assert_eq!(res.status(), 200);

    // Not B, not other routes of A, not as a bearer.
    let bearer_token = bearer(&token);
    for (path, header, reason) in [
        (
            format!("/v1/jobs/{b}/events?access_token={token}"),
            None,
            "invalid_token",
        ),
        (
            format!("/v1/jobs/{a}?access_token={token}"),
            None,
            "invalid_request",
        ),
        (
            format!("/v1/jobs?access_token={token}"),
            None,
            "invalid_request",
        ),
        (
            format!("/v1/jobs/{a}/events"),
            Some(bearer_token.as_str()),
            "invalid_token",
        ),
    ] {
        assert_401(server.get(&path, header).await, reason, &token).await;
    }
    let res = server
        .client
        .delete(server.url(&format!("/v1/jobs/{a}?access_token={token}")))
        .send()
        .await
        .expect("DELETE");
    assert_eq!(res.status(), 401);
    assert!(
        server.jobs.get(&acme(), &a).await.is_ok(),
        "a refused delete deleted"
    );
    let forged = token.replacen("wst_", "wst_x", 1);
    assert_401(
        server
            .get(&format!("/v1/jobs/{a}/events?access_token={forged}"), None)
            .await,
        "invalid_token",
        &forged,
    )
    .await;

    // SSE with the Authorization header (fetch-based clients).
    let res = server
        .get(&format!("/v1/jobs/{b}/events"), Some(&auth))
        .await;
    assert_eq!(res.status(), 200);
    let events = read_sse(res, PATIENCE).await;
    assert_eq!(events.last().map(|e| e.event.as_str()), Some("done"));
    server.stop().await;
}

/// An expired stream token is refused (TTL of one second for the test).
#[tokio::test]
async fn stream_token_expires() {
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let config = AuthConfig {
        stream_ttl: Duration::from_secs(1),
        ..keys_and_jwt(&keys.file)
    };
    let server = Server::start(config).await;
    let a = create_job(&server, &bearer(&key)).await;
    let body: Value = mint(&server, &a, Some(&bearer(&key)))
        .await
        .json()
        .await
        .expect("json");
    let token = body["token"].as_str().expect("token").to_string();
    tokio::time::sleep(Duration::from_millis(2100)).await;
    assert_401(
        server
            .get(&format!("/v1/jobs/{a}/events?access_token={token}"), None)
            .await,
        "expired_token",
        &token,
    )
    .await;
    server.stop().await;
}
