//! Authentication end to end (issue 12): the real router with its one auth layer, in process on
//! an ephemeral loopback port, over HTTP and gRPC. Refused requests must do nothing; keys
//! reload without a restart; stream tokens open one job's events and nothing else; no token
//! reaches a log line.
//!
//! One file a theme: `http`, `streams`, `grpc`, `config`; this one holds the server and the
//! credentials they share.

#[path = "../service_http_support/mod.rs"]
mod service_http_support;

mod config;
mod grpc;
mod http;
mod streams;

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
            .post(self.url("/v1/jobs?steps=2&method=conformal"))
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
