//! Authentication end to end (issue 12): the real router with its one auth layer, in process on
//! an ephemeral loopback port, over HTTP and gRPC. Refused requests must do nothing; keys
//! reload without a restart; stream tokens open one job's events and nothing else; no token
//! reaches a log line.

mod service_http_support;

use jsonwebtoken::{encode, Algorithm, EncodingKey, Header};
use serde_json::{json, Value};
use service_http_support::{read_sse, small_obj, Capture, TestServer};
use std::path::PathBuf;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tonic::transport::Channel;
use tonic::Code;
use willow_service::api::auth::{Auth, AuthArgs, AuthConfig, AuthMode, JwtConfig};
use willow_service::api::grpc::pb::willow::v1;
use willow_service::jobs::{Caller, Jobs};

use v1::fairing_client::FairingClient;

const HS_SECRET: &[u8] = b"an HS256 test secret of more than 32 bytes";
const ISSUER: &str = "https://idp.example";
const AUDIENCE: &str = "willow";
const PATIENCE: Duration = Duration::from_secs(120);

// ---------------------------------------------------------------------------------------------
// Server

/// The tests' server (tests/service_http_support) with an authentication layer.
struct Server(TestServer);

impl std::ops::Deref for Server {
    type Target = TestServer;
    fn deref(&self) -> &TestServer {
        &self.0
    }
}

impl Server {
    async fn start(config: AuthConfig) -> Server {
        let auth = Auth::new(&config).expect("auth config loads");
        auth.spawn_reloader();
        Server::start_with(auth).await
    }

    async fn start_with(auth: Auth) -> Server {
        let options = willow_service::api::server::ServeOptions {
            app: willow_service::api::server::AppOptions {
                auth,
                ..Default::default()
            },
            ..Default::default()
        };
        let dir = tempfile::tempdir().expect("temp dir");
        Server(service_http_support::start_with(dir, |_| {}, options).await)
    }

    async fn stop(self) {
        self.0.stop().await;
    }

    /// POST a small OBJ (2 steps) with `auth` as the Authorization header (if any).
    /// A submission with bearer `token` is refused with 401 `reason`, not echoing it.
    async fn refuses(&self, token: &str, reason: &str) {
        assert_401(self.submit(Some(&bearer(token))).await, reason, token).await;
    }

    async fn submit(&self, auth: Option<&str>) -> reqwest::Response {
        let mut req = self
            .client
            .post(self.url("/v1/jobs?steps=2"))
            .header("content-type", "model/obj")
            .body(small_obj());
        if let Some(a) = auth {
            req = req.header("authorization", a);
        }
        req.send().await.expect("POST /v1/jobs")
    }

    async fn get(&self, path: &str, auth: Option<&str>) -> reqwest::Response {
        let mut req = self.client.get(self.url(path));
        if let Some(a) = auth {
            req = req.header("authorization", a);
        }
        req.send().await.expect("GET")
    }

    /// Jobs listed with `auth`.
    async fn job_count(&self, auth: &str) -> usize {
        let res = self.get("/v1/jobs", Some(auth)).await;
        assert_eq!(res.status(), 200);
        let v: Value = res.json().await.expect("json");
        v["jobs"].as_array().expect("jobs").len()
    }

    async fn channel(&self) -> Channel {
        Channel::from_shared(self.base.clone())
            .expect("uri")
            .connect()
            .await
            .expect("connect h2c")
    }
}

/// The tenant of the keys and tokens below.
fn acme() -> Caller {
    Caller::new("acme", "test").expect("tenant")
}

/// Every job of the tenants a refused request could have reached (the keys' and tokens'
/// tenant, and the anonymous one).
async fn all_jobs(jobs: &Jobs) -> Vec<willow_service::jobs::JobStatus> {
    let mut all = Vec::new();
    for who in [acme(), Caller::anonymous()] {
        all.extend(jobs.list(&who, None, 100, None).await.expect("list").0);
    }
    all
}

fn bearer(t: &str) -> String {
    format!("Bearer {t}")
}

// ---------------------------------------------------------------------------------------------
// Credentials

struct Keys {
    file: PathBuf,
    _dir: tempfile::TempDir,
}

/// A key file holding `lines`.
fn key_file(lines: &[String]) -> Keys {
    let dir = tempfile::tempdir().expect("temp dir");
    let file = dir.path().join("keys");
    std::fs::write(&file, lines.join("\n") + "\n").expect("write keys");
    Keys { file, _dir: dir }
}

fn now() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .expect("clock")
        .as_secs()
}

/// Standard claims; `tweak` changes them.
fn claims(tweak: impl FnOnce(&mut Value)) -> Value {
    let mut c = json!({
        "iss": ISSUER,
        "aud": AUDIENCE,
        "sub": "alice",
        "tenant": "acme",
        "iat": now(),
        "exp": now() + 600,
    });
    tweak(&mut c);
    c
}

fn hs256(claims: &Value) -> String {
    encode(
        &Header::new(Algorithm::HS256),
        claims,
        &EncodingKey::from_secret(HS_SECRET),
    )
    .expect("sign HS256")
}

fn hs_jwt() -> JwtConfig {
    JwtConfig {
        algorithm: Algorithm::HS256,
        key: HS_SECRET.to_vec(),
        issuer: ISSUER.into(),
        audience: AUDIENCE.into(),
        tenant_claim: "tenant".into(),
        leeway_secs: 5,
        key_file: None,
    }
}

/// keys + JWT (HS256), keys from `file`.
fn keys_and_jwt(file: &std::path::Path) -> AuthConfig {
    AuthConfig {
        mode: AuthMode {
            keys: true,
            jwt: true,
        },
        keys_file: Some(file.to_path_buf()),
        keys_poll: Duration::from_millis(200),
        jwt: Some(hs_jwt()),
        stream_ttl: Duration::from_secs(300),
        ..AuthConfig::default()
    }
}

/// JWT only, with `jwt`'s settings (stream tokens of 5 minutes).
fn jwt_only(jwt: JwtConfig) -> AuthConfig {
    AuthConfig {
        mode: AuthMode {
            keys: false,
            jwt: true,
        },
        jwt: Some(jwt),
        stream_ttl: Duration::from_secs(300),
        ..AuthConfig::default()
    }
}

/// An ES256 key pair: (signing key, the public key as SPKI PEM).
fn es256_pair() -> (EncodingKey, Vec<u8>) {
    use base64::Engine as _;
    use ring::signature::{EcdsaKeyPair, KeyPair, ECDSA_P256_SHA256_FIXED_SIGNING};
    let rng = ring::rand::SystemRandom::new();
    let pkcs8 =
        EcdsaKeyPair::generate_pkcs8(&ECDSA_P256_SHA256_FIXED_SIGNING, &rng).expect("keygen");
    let pair = EcdsaKeyPair::from_pkcs8(&ECDSA_P256_SHA256_FIXED_SIGNING, pkcs8.as_ref(), &rng)
        .expect("pkcs8");
    // SubjectPublicKeyInfo: id-ecPublicKey, prime256v1, then the uncompressed point.
    let mut spki = vec![
        0x30, 0x59, 0x30, 0x13, 0x06, 0x07, 0x2a, 0x86, 0x48, 0xce, 0x3d, 0x02, 0x01, 0x06, 0x08,
        0x2a, 0x86, 0x48, 0xce, 0x3d, 0x03, 0x01, 0x07, 0x03, 0x42, 0x00,
    ];
    spki.extend_from_slice(pair.public_key().as_ref());
    let b64 = base64::engine::general_purpose::STANDARD.encode(&spki);
    let pem = format!("-----BEGIN PUBLIC KEY-----\n{b64}\n-----END PUBLIC KEY-----\n");
    (EncodingKey::from_ec_der(pkcs8.as_ref()), pem.into_bytes())
}

/// Assert a 401 problem with `reason`, whose detail does not echo `secret`.
async fn assert_401(res: reqwest::Response, reason: &str, secret: &str) {
    assert_eq!(res.status(), 401);
    let www = res
        .headers()
        .get("www-authenticate")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(www.starts_with("Bearer"), "{www}");
    if reason == "invalid_token" || reason == "expired_token" {
        assert!(www.contains("error=\"invalid_token\""), "{www}");
    }
    assert_eq!(
        res.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some("application/problem+json")
    );
    let body: Value = res.json().await.expect("problem json");
    assert_eq!(body["code"], "unauthenticated", "{body}");
    assert_eq!(body["reason"], reason, "{body}");
    assert!(
        secret.is_empty() || !body.to_string().contains(secret),
        "detail echoes the token"
    );
}

// ---------------------------------------------------------------------------------------------
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

// ---------------------------------------------------------------------------------------------
// Stream tokens and SSE

async fn create_job(server: &Server, auth: &str) -> String {
    let res = server.submit(Some(auth)).await;
    assert_eq!(res.status(), 202);
    let v: Value = res.json().await.expect("json");
    v["id"].as_str().expect("id").to_string()
}

async fn mint(server: &Server, id: &str, auth: Option<&str>) -> reqwest::Response {
    let mut req = server
        .client
        .post(server.url(&format!("/v1/jobs/{id}/stream-token")));
    if let Some(a) = auth {
        req = req.header("authorization", a);
    }
    req.send().await.expect("POST stream-token")
}

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
    assert_401(
        server
            .get(&format!("/v1/jobs/{b}/events?access_token={token}"), None)
            .await,
        "invalid_token",
        &token,
    )
    .await;
    assert_401(
        server
            .get(&format!("/v1/jobs/{a}?access_token={token}"), None)
            .await,
        "invalid_request",
        &token,
    )
    .await;
    assert_401(
        server
            .get(&format!("/v1/jobs?access_token={token}"), None)
            .await,
        "invalid_request",
        &token,
    )
    .await;
    assert_401(
        server
            .get(&format!("/v1/jobs/{a}/events"), Some(&bearer(&token)))
            .await,
        "invalid_token",
        &token,
    )
    .await;
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

// ---------------------------------------------------------------------------------------------
// gRPC

fn inline_request() -> v1::CreateJobRequest {
    v1::CreateJobRequest {
        mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
            format: v1::MeshFormat::Obj as i32,
            data: small_obj().into_bytes().into(),
        })),
        params: Some(v1::JobParams {
            steps: Some(2),
            ..Default::default()
        }),
        request_id: String::new(),
    }
}

fn with_auth<T>(msg: T, auth: Option<&str>) -> tonic::Request<T> {
    let mut req = tonic::Request::new(msg);
    if let Some(a) = auth {
        req.metadata_mut()
            .insert("authorization", a.parse().expect("ascii metadata"));
    }
    req
}

/// gRPC: the same refusals as UNAUTHENTICATED (with an ErrorInfo reason), nothing created;
/// valid credentials work; health stays open.
#[tokio::test]
async fn grpc_refusals_have_no_side_effects() {
    use tonic_types::StatusExt as _;
    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(&[line]);
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    let mut client = FairingClient::new(server.channel().await);

    let expired = hs256(&claims(|c| c["exp"] = json!(now() - 3600)));
    let wrong_aud = hs256(&claims(|c| c["aud"] = json!("someone-else")));
    let wrong_iss = hs256(&claims(|c| c["iss"] = json!("https://evil.example")));
    let bad_key = "wlw_unknown".to_string();
    let cases: Vec<(Option<String>, &str)> = vec![
        (None, "MISSING_CREDENTIALS"),
        (Some(bearer(&bad_key)), "INVALID_TOKEN"),
        (Some(bearer(&expired)), "EXPIRED_TOKEN"),
        (Some(bearer(&wrong_aud)), "INVALID_TOKEN"),
        (Some(bearer(&wrong_iss)), "INVALID_TOKEN"),
    ];
    for (auth, reason) in &cases {
        let status = client
            .create_job(with_auth(inline_request(), auth.as_deref()))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated, "{auth:?}: {status:?}");
        let info = status.get_details_error_info().expect("ErrorInfo");
        assert_eq!(info.reason, *reason);
        assert_eq!(info.domain, "willow.v1");
        if let Some(a) = auth {
            assert!(!status.message().contains(a.trim_start_matches("Bearer ")));
        }
        let status = client
            .list_jobs(with_auth(v1::ListJobsRequest::default(), auth.as_deref()))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::Unauthenticated);
    }
    let all = all_jobs(&server.jobs).await;
    assert!(all.is_empty(), "refused CreateJob calls created jobs");

    // Valid: a key, a JWT.
    let auth = bearer(&key);
    client
        .create_job(with_auth(inline_request(), Some(&auth)))
        .await
        .expect("CreateJob with a key");
    let jwt = bearer(&hs256(&claims(|_| {})));
    let list = client
        .list_jobs(with_auth(v1::ListJobsRequest::default(), Some(&jwt)))
        .await
        .expect("ListJobs with a JWT")
        .into_inner();
    assert_eq!(list.jobs.len(), 1);

    // Health is open.
    let mut health = tonic_health::pb::health_client::HealthClient::new(server.channel().await);
    health
        .check(tonic_health::pb::HealthCheckRequest {
            service: String::new(),
        })
        .await
        .expect("health without credentials");
    server.stop().await;
}

// ---------------------------------------------------------------------------------------------
// Configuration, CLI, logs

/// The loopback rule as `willow serve` applies it: no auth on a non-loopback address is refused
/// unless explicitly allowed.
#[test]
fn non_loopback_without_auth_is_refused() {
    let args = AuthArgs::default();
    let e =
        AuthConfig::from_args(&args, "0.0.0.0:8080".parse().expect("addr")).expect_err("refused");
    assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
    assert!(AuthConfig::from_args(&args, "127.0.0.1:8080".parse().expect("addr")).is_ok());
    let allowed = AuthArgs {
        insecure_allow_unauthenticated: true,
        ..AuthArgs::default()
    };
    assert!(AuthConfig::from_args(&allowed, "0.0.0.0:8080".parse().expect("addr")).is_ok());

    let out = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["serve", "--addr", "0.0.0.0:0", "--data-dir"])
        .arg(std::env::temp_dir().join("willow-auth-never-created"))
        .output()
        .expect("run willow");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("--insecure-allow-unauthenticated"),
        "{stderr}"
    );
}

/// `--insecure-allow-unauthenticated` alone or as `=true` (deployment files use that form:
/// their linters read `--flag=value`); it never takes the next argument as its value.
#[test]
fn insecure_flag_forms() {
    use clap::Parser;
    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        auth: AuthArgs,
        #[arg(long)]
        data_dir: Option<String>,
    }
    let t = T::try_parse_from(["t", "--insecure-allow-unauthenticated", "--data-dir", "/d"])
        .expect("bare flag");
    assert!(t.auth.insecure_allow_unauthenticated);
    assert_eq!(t.data_dir.as_deref(), Some("/d"));
    let t = T::try_parse_from(["t", "--insecure-allow-unauthenticated=true"]).expect("=true");
    assert!(t.auth.insecure_allow_unauthenticated);
    let t = T::try_parse_from(["t"]).expect("default");
    assert!(!t.auth.insecure_allow_unauthenticated);
    assert_eq!(t.auth.auth, "none");
    assert!(T::try_parse_from(["t", "--insecure-allow-unauthenticated=maybe"]).is_err());
}

/// `willow keys new` prints a key and a line whose hash is the key's.
#[test]
fn keys_new_cli() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["keys", "new", "--tenant", "acme", "--name", "ci"])
        .output()
        .expect("run willow");
    assert!(out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 2, "{stdout}");
    assert!(lines[0].starts_with("wlw_"));
    assert!(lines[1].starts_with("acme ci sha256:"));
    assert!(!lines[1].contains(lines[0]));
    let bad = std::process::Command::new(env!("CARGO_BIN_EXE_willow"))
        .args(["keys", "new", "--tenant", "no spaces", "--name", "ci"])
        .output()
        .expect("run willow");
    assert!(!bad.status.success());
}

/// Keys, JWTs and stream tokens, good and bad, in headers and queries: none reaches the log
/// (every level, span fields included), while the refusals and requests are logged.
#[tokio::test]
async fn tokens_never_reach_the_log() {
    let capture = Capture::default();
    let subscriber = tracing_subscriber::fmt()
        .with_writer(capture.clone())
        .with_max_level(tracing::Level::TRACE)
        .json()
        .with_current_span(true)
        .with_span_list(true)
        .finish();
    // A current-thread runtime: the server's tasks run on this thread, under this subscriber.
    let _guard = tracing::subscriber::set_default(subscriber);

    let (key, line) = willow_service::api::auth::new_key("acme", "ci").expect("key");
    let keys = key_file(std::slice::from_ref(&line));
    let server = Server::start(keys_and_jwt(&keys.file)).await;
    let auth = bearer(&key);
    let bad_key = "wlw_secret-bad-key-0123456789";
    let jwt = hs256(&claims(|_| {}));
    let expired = hs256(&claims(|c| c["exp"] = json!(now() - 3600)));
    let a = create_job(&server, &auth).await;
    let body: Value = mint(&server, &a, Some(&auth))
        .await
        .json()
        .await
        .expect("json");
    let token = body["token"].as_str().expect("token").to_string();
    server.submit(Some(&bearer(bad_key))).await;
    server.submit(Some(&bearer(&expired))).await;
    server.get("/v1/jobs", Some(&bearer(&jwt))).await;
    let res = server
        .get(&format!("/v1/jobs/{a}/events?access_token={token}"), None)
        .await;
    read_sse(res, PATIENCE).await;
    server
        .get(&format!("/v1/jobs?access_token={token}"), None)
        .await;
    server
        .get(&format!("/v1/nope?access_token={token}"), Some(&auth))
        .await;
    server.stop().await;

    let log = String::from_utf8_lossy(&capture.0.lock().expect("log").clone()).to_string();
    assert!(log.contains("request refused"), "nothing captured: {log}");
    let hash = line.rsplit(':').next().expect("hash");
    for secret in [
        key.as_str(),
        bad_key,
        jwt.as_str(),
        expired.as_str(),
        token.as_str(),
        hash,
    ] {
        assert!(!log.contains(secret), "a secret reached the log");
    }
    assert!(!log.contains("access_token"), "the query reached the log");
    assert!(!log.to_ascii_lowercase().contains("authorization"));
}
