//! Over HTTP: refusals without side effects, ES256 and RS256 tokens, key files that reload,
//! open routes, `--auth none`.

use super::*;

// HTTP

/// No credentials, a bad key, an expired JWT, a wrong audience or issuer, a bad signature: all
/// 401, and none of those submissions created a job.
#[tokio::test]
async fn http_refusals_have_no_side_effects() {
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;

    assert_401(server.submit(None).await, "missing_credentials", "").await;
    let bad_key = "wlw_not-a-key-that-is-listed-anywhere";
    assert_401(
        server.submit(Some(&bearer(bad_key))).await,
        "invalid_token",
        bad_key,
    )
    .await;
    let expired = hs256(&claims(|c| {
        c["exp"] = json!(now() - 3600);
        c["iat"] = json!(now() - 7200);
    }));
    server.refuses(&expired, "expired_token").await;
    let wrong_aud = hs256(&claims(|c| c["aud"] = json!("someone-else")));
    server.refuses(&wrong_aud, "invalid_token").await;
    let wrong_iss = hs256(&claims(|c| c["iss"] = json!("https://evil.example")));
    server.refuses(&wrong_iss, "invalid_token").await;
    let forged = encode(
        &Header::new(Algorithm::HS256),
        &claims(|_| {}),
        &EncodingKey::from_secret(b"another secret of more than 32 bytes!!"),
    )
    .expect("sign");
    server.refuses(&forged, "invalid_token").await;
    let no_tenant = hs256(&claims(|c| {
        c.as_object_mut().map(|o| o.remove("tenant"));
    }));
    server.refuses(&no_tenant, "invalid_token").await;
    // Another scheme.
    let res = server
        .client
        .post(server.url("/v1/jobs"))
        .basic_auth("acme", Some("pw"))
        .send()
        .await
        .expect("POST");
    assert_401(res, "invalid_request", "pw").await;
    // Other routes too, and deletes: nothing happens.
    assert_401(
        server.get("/v1/jobs", None).await,
        "missing_credentials",
        "",
    )
    .await;

    // None of the refused submissions made a job.
    let all = all_jobs(&server.jobs).await;
    assert!(
        all.is_empty(),
        "refused requests created jobs: {}",
        all.len()
    );
    assert_eq!(server.job_count(&bearer(&key)).await, 0);

    // Valid credentials work: a key, and a JWT.
    let res = server.submit(Some(&bearer(&key))).await;
    assert_eq!(res.status(), 202);
    let jwt = hs256(&claims(|_| {}));
    assert_eq!(server.job_count(&bearer(&jwt)).await, 1);
    let res = server.submit(Some(&format!("bearer   {jwt}"))).await;
    assert_eq!(res.status(), 202, "the scheme is case-insensitive");
    server.stop().await;
}

/// ES256 (JWT only): a token signed by the identity provider's key works; an HS256 token, or
/// one signed by another EC key, does not.
#[tokio::test]
async fn es256_jwt() {
    let (signing, public_pem) = es256_pair();
    let (other, _) = es256_pair();
    let config = jwt_only(JwtConfig {
        algorithm: Algorithm::ES256,
        key: public_pem,
        ..hs_jwt()
    });
    let server = Server::start(config).await;
    let es = |key: &EncodingKey, c: &Value| {
        encode(&Header::new(Algorithm::ES256), c, key).expect("sign ES256")
    };
    let good = es(&signing, &claims(|_| {}));
    assert_eq!(server.job_count(&bearer(&good)).await, 0);
    let res = server.submit(Some(&bearer(&good))).await;
    assert_eq!(res.status(), 202);
    let forged = es(&other, &claims(|_| {}));
    server.refuses(&forged, "invalid_token").await;
    let hs = hs256(&claims(|_| {}));
    server.refuses(&hs, "invalid_token").await;
    let expired = es(
        &signing,
        &claims(|c| {
            c["exp"] = json!(now() - 600);
        }),
    );
    server.refuses(&expired, "expired_token").await;
    let wrong_aud = es(&signing, &claims(|c| c["aud"] = json!("other")));
    server.refuses(&wrong_aud, "invalid_token").await;
    // An API key is nothing to a JWT-only server.
    let (key, _) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    server.refuses(&key, "invalid_token").await;
    assert_eq!(server.job_count(&bearer(&good)).await, 1);
    server.stop().await;
}

/// RS256 (JWT only), with the identity provider's public key as a PEM file: its tokens work;
/// one signed by another RSA key is refused, and so is the algorithm-confusion forgery (an
/// HS256 token whose HMAC secret is the public key the server holds).
#[tokio::test]
async fn rs256_jwt() {
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/jwt");
    let read = |name: &str| std::fs::read(data.join(name)).expect("test key");
    let public_pem = read("rs256-idp.pub.pem");
    let signing = EncodingKey::from_rsa_pem(&read("rs256-idp.key.pem")).expect("RSA key");
    let other = EncodingKey::from_rsa_pem(&read("rs256-other.key.pem")).expect("RSA key");
    let config = jwt_only(JwtConfig {
        algorithm: Algorithm::RS256,
        key: public_pem.clone(),
        ..hs_jwt()
    });
    let server = Server::start(config).await;
    let rs = |key: &EncodingKey, c: &Value| {
        encode(&Header::new(Algorithm::RS256), c, key).expect("sign RS256")
    };
    let good = rs(&signing, &claims(|_| {}));
    let res = server.submit(Some(&bearer(&good))).await;
    assert_eq!(res.status(), 202);
    let forged = rs(&other, &claims(|_| {}));
    server.refuses(&forged, "invalid_token").await;
    let confused = encode(
        &Header::new(Algorithm::HS256),
        &claims(|_| {}),
        &EncodingKey::from_secret(&public_pem),
    )
    .expect("sign HS256");
    server.refuses(&confused, "invalid_token").await;
    let expired = rs(&signing, &claims(|c| c["exp"] = json!(now() - 600)));
    server.refuses(&expired, "expired_token").await;
    assert_eq!(server.job_count(&bearer(&good)).await, 1);
    server.stop().await;
}

/// The JWT key file is re-read without a restart, as the identity provider rotates its key:
/// after the file changes, tokens of the new key work and those of the old one are refused;
/// a file that holds no valid key keeps the key in use.
#[tokio::test]
async fn jwt_key_file_reloads() {
    let (old, old_pem) = es256_pair();
    let (new, new_pem) = es256_pair();
    let dir = tempfile::tempdir().expect("dir");
    let file = dir.path().join("idp.pem");
    std::fs::write(&file, &old_pem).expect("write");
    let config = AuthConfig {
        keys_poll: Duration::from_millis(100),
        ..jwt_only(JwtConfig {
            algorithm: Algorithm::ES256,
            key: old_pem,
            key_file: Some(file.clone()),
            ..hs_jwt()
        })
    };
    let server = Server::start(config).await;
    let es = |key: &EncodingKey| {
        encode(&Header::new(Algorithm::ES256), &claims(|_| {}), key).expect("sign ES256")
    };
    let (old_token, new_token) = (es(&old), es(&new));
    let status = |token: String| {
        let server = &server;
        async move { server.get("/v1/jobs", Some(&bearer(&token))).await.status() }
    };
    assert_eq!(status(old_token.clone()).await, 200);
    assert_eq!(status(new_token.clone()).await, 401);

    std::fs::write(&file, &new_pem).expect("rotate");
    let mut rotated = false;
    for _ in 0..100 {
        if status(new_token.clone()).await == 200 {
            rotated = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert!(rotated, "the new key was never picked up");
    assert_eq!(status(old_token.clone()).await, 401, "the old key is gone");

    std::fs::write(&file, "not a key").expect("break");
    tokio::time::sleep(Duration::from_millis(800)).await;
    assert_eq!(status(new_token).await, 200, "a broken file keeps the key");
    server.stop().await;
}

/// The key file is re-read without a restart: a new key works, a removed one is refused, and a
/// broken file keeps the keys there were.
#[tokio::test]
async fn key_file_reloads() {
    let (old, old_line) = willow_service::api::auth::new_key("acme", "old").expect("key");
    let (new, new_line) = willow_service::api::auth::new_key("acme", "new").expect("key");
    let keys = key_file(&[old_line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&old))).await.status(),
        200
    );
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&new))).await.status(),
        401
    );

    std::fs::write(&keys.file, format!("# rotated\n{new_line}\n")).expect("rewrite");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        if server.get("/v1/jobs", Some(&bearer(&new))).await.status() == 200 {
            break;
        }
        assert!(std::time::Instant::now() < deadline, "new key never loaded");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&old))).await.status(),
        401
    );

    // A broken file: the current keys stay.
    std::fs::write(&keys.file, "acme broken sha256:nothex\n").expect("rewrite");
    tokio::time::sleep(Duration::from_millis(800)).await;
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&new))).await.status(),
        200
    );
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&old))).await.status(),
        401
    );
    server.stop().await;
}

/// SIGHUP re-reads the key file at once (the poll here is an hour away).
#[cfg(unix)]
#[tokio::test]
async fn sighup_reloads_keys() {
    let (old, old_line) = willow_service::api::auth::new_key("acme", "old").expect("key");
    let (new, new_line) = willow_service::api::auth::new_key("acme", "new").expect("key");
    let keys = key_file(&[old_line]);
    let config = AuthConfig {
        keys_poll: Duration::from_secs(3600),
        ..keys_and_jwt(&keys.file)
    };
    let server = Server::start(config).await;
    // A request first: the reloader task has run and installed its SIGHUP handler by then
    // (this runtime has one thread), so the signal below cannot end the process.
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&old))).await.status(),
        200
    );
    tokio::time::sleep(Duration::from_millis(200)).await;
    std::fs::write(&keys.file, format!("{new_line}\n")).expect("rewrite");
    let status = std::process::Command::new("kill")
        .args(["-HUP", &std::process::id().to_string()])
        .status()
        .expect("kill -HUP");
    assert!(status.success());
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        if server.get("/v1/jobs", Some(&bearer(&new))).await.status() == 200 {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "SIGHUP did not reload"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(
        server.get("/v1/jobs", Some(&bearer(&old))).await.status(),
        401
    );
    server.stop().await;
}

/// Probes, docs and the web page are open; /metrics is open unless protected.
#[tokio::test]
async fn open_routes_and_metrics() {
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    for path in ["/healthz", "/openapi.json", "/docs", "/", "/metrics"] {
        let res = server.get(path, None).await;
        assert_eq!(res.status(), 200, "{path} should be open");
    }
    let ready = server.get("/readyz", None).await.status();
    assert!(ready == 200 || ready == 503, "{ready}");
    // The OpenAPI doc declares the scheme and the stream-token route.
    let doc: Value = server
        .get("/openapi.json", None)
        .await
        .json()
        .await
        .expect("json");
    assert_eq!(
        doc["components"]["securitySchemes"]["bearer"]["scheme"],
        "bearer"
    );
    assert!(doc["paths"]["/v1/jobs/{id}/stream-token"]["post"].is_object());
    assert_eq!(doc["security"][0]["bearer"], json!([]));
    assert_eq!(doc["paths"]["/healthz"]["get"]["security"], json!([{}]));
    assert_eq!(
        doc["components"]["securitySchemes"]["stream_token"]["in"],
        "query"
    );
    assert_eq!(
        doc["paths"]["/v1/jobs/{id}/events"]["get"]["security"],
        json!([{"bearer": []}, {"stream_token": []}])
    );
    // An unknown path is refused, not described.
    assert_eq!(server.get("/nope", None).await.status(), 401);
    server.stop().await;

    let protected = AuthConfig {
        protect_metrics: true,
        ..keys_and_jwt(&keys.file)
    };
    let server = Server::start(protected).await;
    assert_401(
        server.get("/metrics", None).await,
        "missing_credentials",
        "",
    )
    .await;
    assert_eq!(
        server.get("/metrics", Some(&bearer(&key))).await.status(),
        200
    );
    assert_eq!(server.get("/healthz", None).await.status(), 200);
    server.stop().await;
}

/// `--auth none`: everything answers without credentials (the embedded default).
#[tokio::test]
async fn auth_none_is_open() {
    let server = Server::start_with(Auth::none()).await;
    assert_eq!(server.submit(None).await.status(), 202);
    assert_eq!(server.get("/v1/jobs", None).await.status(), 200);
    server.stop().await;
}
