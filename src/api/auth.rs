//! Authentication (issue 12): one axum middleware in front of the whole merged router, so the
//! REST API, SSE and gRPC share it. It turns a request's credentials into a
//! [`Caller`] (tenant + subject) in the request extensions, or refuses the request before any
//! handler runs: HTTP gets a 401 problem, gRPC a trailers-only `UNAUTHENTICATED`.
//!
//! Credentials, all as `Authorization: Bearer <token>`:
//! - **API keys** (`--auth keys`): random tokens (`wlw_` + 32 random bytes, base64url) listed
//!   by their SHA-256 in a key file (`--api-keys-file`) and/or `WILLOW_API_KEYS`, one
//!   `<tenant> <name> sha256:<hex>` per line. Only the hashes are stored. The file is re-read
//!   when its content changes (polled) and on SIGHUP; a bad file keeps the old keys.
//! - **JWT** (`--auth jwt`): HS256, RS256 or ES256; signature, `exp`/`nbf` (with a small
//!   leeway), `iss` and `aud` are checked; `sub` becomes the subject and the tenant claim
//!   (`--jwt-tenant-claim`, default `tenant`) the tenant. With both enabled, a bearer of three
//!   dot-separated parts goes to JWT, anything else to the keys.
//! - **Stream tokens**: browsers cannot set headers on an `EventSource`, so an authenticated
//!   `POST /v1/jobs/{id}/stream-token` mints a short-lived HMAC token bound to (tenant, job),
//!   accepted only as `?access_token=` on that job's events and frame downloads.
//!
//! With `--auth none` (the default, loopback only unless explicitly allowed) every request is
//! [`Caller::anonymous`]. Probes, docs, the web page, gRPC health and reflection are open;
//! `/metrics` too unless `--protect-metrics`.
//!
//! Secrets never reach a log line: `access_token` is removed from the URI before anything
//! below this layer sees it, the request span records only the path, and refusals log the
//! reason, never the token.

// `Problem` is large; errors are the cold path (see http.rs).
#![allow(clippy::result_large_err)]

use super::problem::Problem;
use crate::jobs::{rfc3339, Caller, Jobs};
use axum::body::Body;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::post;
use axum::{Extension, Json, Router};
use base64::Engine as _;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::{BTreeSet, HashMap};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, RwLock, Weak};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The environment variable holding API key lines (same format as the key file).
pub const API_KEYS_ENV: &str = "WILLOW_API_KEYS";

/// Prefix of the keys `willow keys new` makes (any bearer is accepted if its hash is listed).
pub const KEY_PREFIX: &str = "wlw_";

/// Prefix of stream tokens, so one is recognised (and never mistaken for an API key).
const STREAM_TOKEN_PREFIX: &str = "wst_";

/// The query parameter carrying a stream token.
pub const ACCESS_TOKEN_PARAM: &str = "access_token";

const B64: base64::engine::GeneralPurpose = base64::engine::general_purpose::URL_SAFE_NO_PAD;

// ---------------------------------------------------------------------------------------------
// Flags and configuration

/// The authentication flags of `willow serve` (flattened into its `ServeArgs`).
#[derive(Debug, Clone, clap::Args)]
pub struct AuthArgs {
    /// Who may call: `none` (everyone is the anonymous caller; loopback only unless
    /// --insecure-allow-unauthenticated), `keys` (API keys), `jwt` (JSON Web Tokens) or
    /// `keys,jwt`.
    #[arg(long, default_value = "none")]
    pub auth: String,
    /// Serve a non-loopback --addr with `--auth none`: anyone who can reach the port can
    /// submit, read and delete jobs. Only behind something that authenticates for us.
    /// (`--insecure-allow-unauthenticated=true` works too, for argument lists that expect
    /// `--flag=value`.)
    #[arg(long, num_args = 0..=1, require_equals = true, default_missing_value = "true",
          action = clap::ArgAction::Set, default_value_t = false)]
    pub insecure_allow_unauthenticated: bool,
    /// API key file: lines `<tenant> <name> sha256:<hex>` (`#` starts a comment), as
    /// `willow keys new` prints them. Re-read when it changes and on SIGHUP. The variable
    /// WILLOW_API_KEYS may hold more lines.
    #[arg(long)]
    pub api_keys_file: Option<PathBuf>,
    /// Seconds between checks of --api-keys-file for changes.
    #[arg(long, default_value_t = 5.0)]
    pub api_keys_poll_secs: f64,
    /// JWT signature algorithm: HS256, RS256 or ES256.
    #[arg(long)]
    pub jwt_algorithm: Option<String>,
    /// JWT verification key: the shared secret (HS256; the file's bytes, a final newline
    /// dropped) or the PEM public key (RS256, ES256).
    #[arg(long)]
    pub jwt_key_file: Option<PathBuf>,
    /// Required `iss` of JWTs.
    #[arg(long)]
    pub jwt_issuer: Option<String>,
    /// Required `aud` of JWTs.
    #[arg(long)]
    pub jwt_audience: Option<String>,
    /// The JWT claim naming the caller's tenant.
    #[arg(long, default_value = "tenant")]
    pub jwt_tenant_claim: String,
    /// Clock skew allowed on JWT `exp` and `nbf`, in seconds.
    #[arg(long, default_value_t = 30)]
    pub jwt_leeway_secs: u64,
    /// Secret (at least 32 bytes) signing stream tokens. Give every node of a multi-node
    /// deployment the same file, or a token minted on one node is refused by the others;
    /// without it each process draws a random secret (tokens die with the process).
    #[arg(long)]
    pub stream_token_secret_file: Option<PathBuf>,
    /// Lifetime of a stream token in seconds.
    #[arg(long, default_value_t = 300)]
    pub stream_token_ttl_secs: u64,
    /// Require credentials on /metrics too.
    #[arg(long)]
    pub protect_metrics: bool,
}

impl Default for AuthArgs {
    fn default() -> Self {
        AuthArgs {
            auth: "none".into(),
            insecure_allow_unauthenticated: false,
            api_keys_file: None,
            api_keys_poll_secs: 5.0,
            jwt_algorithm: None,
            jwt_key_file: None,
            jwt_issuer: None,
            jwt_audience: None,
            jwt_tenant_claim: "tenant".into(),
            jwt_leeway_secs: 30,
            stream_token_secret_file: None,
            stream_token_ttl_secs: 300,
            protect_metrics: false,
        }
    }
}

/// Which credentials `--auth` accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AuthMode {
    pub keys: bool,
    pub jwt: bool,
}

impl AuthMode {
    /// `none`, `keys`, `jwt`, `keys,jwt` (or `jwt,keys`).
    pub fn parse(s: &str) -> Result<AuthMode, String> {
        let mut mode = AuthMode::default();
        if s.trim() == "none" {
            return Ok(mode);
        }
        for part in s.split(',') {
            match part.trim() {
                "keys" => mode.keys = true,
                "jwt" => mode.jwt = true,
                _ => {
                    return Err(format!(
                        "--auth must be `none`, `keys`, `jwt` or `keys,jwt`, got `{}`",
                        super::problem::clip(s)
                    ))
                }
            }
        }
        Ok(mode)
    }

    pub fn enabled(self) -> bool {
        self.keys || self.jwt
    }
}

/// JWT verification settings.
#[derive(Debug, Clone)]
pub struct JwtConfig {
    pub algorithm: jsonwebtoken::Algorithm,
    /// HS256: the secret; RS256/ES256: the PEM public key.
    pub key: Vec<u8>,
    pub issuer: String,
    pub audience: String,
    pub tenant_claim: String,
    pub leeway_secs: u64,
}

/// Everything [`Auth::new`] needs, validated; built from the flags by [`AuthConfig::from_args`]
/// or directly (tests).
#[derive(Debug, Clone, Default)]
pub struct AuthConfig {
    pub mode: AuthMode,
    pub keys_file: Option<PathBuf>,
    /// Key lines from [`API_KEYS_ENV`].
    pub keys_env: Option<String>,
    pub keys_poll: Duration,
    pub jwt: Option<JwtConfig>,
    /// `None`: a random secret for this process.
    pub stream_secret: Option<Vec<u8>>,
    pub stream_ttl: Duration,
    pub protect_metrics: bool,
}

impl AuthConfig {
    /// The configuration the flags describe for a server on `addr`; refuses a non-loopback
    /// address without authentication unless `--insecure-allow-unauthenticated`.
    pub fn from_args(args: &AuthArgs, addr: SocketAddr) -> Result<AuthConfig, String> {
        let mode = AuthMode::parse(&args.auth)?;
        check_bind(addr, mode, args.insecure_allow_unauthenticated)?;
        let keys_env = std::env::var(API_KEYS_ENV).ok();
        if !mode.keys && (args.api_keys_file.is_some() || keys_env.is_some()) {
            return Err(format!(
                "--api-keys-file or {API_KEYS_ENV} is set but --auth does not include `keys`"
            ));
        }
        if mode.keys && args.api_keys_file.is_none() && keys_env.is_none() {
            return Err(format!(
                "--auth keys needs --api-keys-file or the {API_KEYS_ENV} variable"
            ));
        }
        if !(args.api_keys_poll_secs.is_finite() && args.api_keys_poll_secs >= 0.1) {
            return Err("--api-keys-poll-secs must be at least 0.1".into());
        }
        let jwt_flags = args.jwt_algorithm.is_some()
            || args.jwt_key_file.is_some()
            || args.jwt_issuer.is_some()
            || args.jwt_audience.is_some();
        if !mode.jwt && jwt_flags {
            return Err("--jwt-* flags are set but --auth does not include `jwt`".into());
        }
        let jwt = if mode.jwt {
            let need = |v: &Option<String>, flag: &str| {
                v.clone()
                    .filter(|s| !s.is_empty())
                    .ok_or_else(|| format!("--auth jwt needs {flag}"))
            };
            let algorithm = parse_algorithm(&need(&args.jwt_algorithm, "--jwt-algorithm")?)?;
            let path = args
                .jwt_key_file
                .as_ref()
                .ok_or("--auth jwt needs --jwt-key-file")?;
            let mut key = std::fs::read(path)
                .map_err(|e| format!("cannot read --jwt-key-file {}: {e}", path.display()))?;
            if algorithm == jsonwebtoken::Algorithm::HS256 {
                strip_final_newline(&mut key);
            }
            Some(JwtConfig {
                algorithm,
                key,
                issuer: need(&args.jwt_issuer, "--jwt-issuer")?,
                audience: need(&args.jwt_audience, "--jwt-audience")?,
                tenant_claim: args.jwt_tenant_claim.clone(),
                leeway_secs: args.jwt_leeway_secs,
            })
        } else {
            None
        };
        if args.protect_metrics && !mode.enabled() {
            return Err("--protect-metrics needs --auth keys or jwt".into());
        }
        let stream_secret = match &args.stream_token_secret_file {
            None => None,
            Some(path) => {
                let mut s = std::fs::read(path).map_err(|e| {
                    format!(
                        "cannot read --stream-token-secret-file {}: {e}",
                        path.display()
                    )
                })?;
                strip_final_newline(&mut s);
                Some(s)
            }
        };
        if args.stream_token_ttl_secs == 0 {
            return Err("--stream-token-ttl-secs must be at least 1".into());
        }
        Ok(AuthConfig {
            mode,
            keys_file: args.api_keys_file.clone(),
            keys_env,
            keys_poll: Duration::from_secs_f64(args.api_keys_poll_secs),
            jwt,
            stream_secret,
            stream_ttl: Duration::from_secs(args.stream_token_ttl_secs),
            protect_metrics: args.protect_metrics,
        })
    }
}

/// The loopback rule: without authentication, only a loopback address, unless explicitly
/// allowed.
pub fn check_bind(addr: SocketAddr, mode: AuthMode, allow_insecure: bool) -> Result<(), String> {
    if mode.enabled() || allow_insecure || addr.ip().is_loopback() {
        return Ok(());
    }
    Err(format!(
        "refusing to serve {addr} without authentication: anyone who can reach it could submit, \
         read and delete jobs. Use --auth keys or --auth jwt, bind a loopback address, or pass \
         --insecure-allow-unauthenticated if something in front of willow authenticates"
    ))
}

fn parse_algorithm(s: &str) -> Result<jsonwebtoken::Algorithm, String> {
    match s.to_ascii_uppercase().as_str() {
        "HS256" => Ok(jsonwebtoken::Algorithm::HS256),
        "RS256" => Ok(jsonwebtoken::Algorithm::RS256),
        "ES256" => Ok(jsonwebtoken::Algorithm::ES256),
        _ => Err(format!(
            "--jwt-algorithm must be HS256, RS256 or ES256, got `{}`",
            super::problem::clip(s)
        )),
    }
}

fn strip_final_newline(b: &mut Vec<u8>) {
    if b.last() == Some(&b'\n') {
        b.pop();
        if b.last() == Some(&b'\r') {
            b.pop();
        }
    }
}

// ---------------------------------------------------------------------------------------------
// API keys

/// A listed key: who it authenticates.
#[derive(Debug, Clone, PartialEq, Eq)]
struct KeyEntry {
    caller: Caller,
}

type KeyMap = HashMap<[u8; 32], KeyEntry>;

/// SHA-256 of a presented key.
fn key_digest(key: &str) -> [u8; 32] {
    Sha256::digest(key.as_bytes()).into()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex32(s: &str) -> Option<[u8; 32]> {
    if s.len() != 64 || !s.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, o) in out.iter_mut().enumerate() {
        *o = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(out)
}

/// Parse key lines (`<tenant> <name> sha256:<hex>`, `#` comments, blank lines). `source`
/// names the file or variable in errors, which quote line numbers and never a hash.
fn parse_keys(text: &str, source: &str, into: &mut KeyMap) -> Result<(), String> {
    for (n, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        let at = || format!("{source} line {}", n + 1);
        let [tenant, name, hash] = fields[..] else {
            return Err(format!(
                "{}: expected `<tenant> <name> sha256:<64 hex digits>`, got {} fields",
                at(),
                fields.len()
            ));
        };
        if name.chars().count() > 64 {
            return Err(format!("{}: key name longer than 64 characters", at()));
        }
        let caller = Caller::new(tenant, name).map_err(|e| format!("{}: {e}", at()))?;
        let digest = hash
            .strip_prefix("sha256:")
            .and_then(|h| unhex32(&h.to_ascii_lowercase()))
            .ok_or_else(|| format!("{}: the hash must be `sha256:` and 64 hex digits", at()))?;
        if into.insert(digest, KeyEntry { caller }).is_some() {
            return Err(format!("{}: the same key is listed twice", at()));
        }
    }
    Ok(())
}

/// A new API key and its key-file line: `(key, "<tenant> <name> sha256:<hex>")`.
pub fn new_key(tenant: &str, name: &str) -> Result<(String, String), String> {
    Caller::new(tenant, name)?;
    if name.is_empty() || name.chars().count() > 64 || name.contains(char::is_whitespace) {
        return Err("the key name must be 1-64 characters without spaces".into());
    }
    if name.contains('#') {
        return Err("the key name cannot contain `#` (it starts a comment)".into());
    }
    let mut bytes = [0u8; 32];
    random_bytes(&mut bytes)?;
    let key = format!("{KEY_PREFIX}{}", B64.encode(bytes));
    let line = format!("{tenant} {name} sha256:{}", hex(&key_digest(&key)));
    Ok((key, line))
}

fn random_bytes(out: &mut [u8]) -> Result<(), String> {
    use ring::rand::SecureRandom as _;
    ring::rand::SystemRandom::new()
        .fill(out)
        .map_err(|_| "the system random number generator failed".to_string())
}

/// The listed keys and where they come from.
struct KeyStore {
    file: Option<PathBuf>,
    env: Option<String>,
    poll: Duration,
    keys: RwLock<Arc<KeyMap>>,
    /// SHA-256 of the file content last looked at (loaded or refused), so a bad file is
    /// reported once, not at every poll.
    seen: RwLock<Option<[u8; 32]>>,
}

impl KeyStore {
    fn load(file: Option<PathBuf>, env: Option<String>, poll: Duration) -> Result<Self, String> {
        let store = KeyStore {
            file,
            env,
            poll,
            keys: RwLock::new(Arc::new(KeyMap::new())),
            seen: RwLock::new(None),
        };
        let (map, digest) = store.read()?;
        *write(&store.keys) = Arc::new(map);
        *write(&store.seen) = digest;
        Ok(store)
    }

    /// Read and parse the sources; also the file content's digest.
    fn read(&self) -> Result<(KeyMap, Option<[u8; 32]>), String> {
        let mut map = KeyMap::new();
        if let Some(env) = &self.env {
            parse_keys(env, API_KEYS_ENV, &mut map)?;
        }
        let mut digest = None;
        if let Some(path) = &self.file {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
            digest = Some(Sha256::digest(text.as_bytes()).into());
            parse_keys(&text, &path.display().to_string(), &mut map)?;
        }
        Ok((map, digest))
    }

    fn lookup(&self, key: &str) -> Option<Caller> {
        let keys = read(&self.keys).clone();
        keys.get(&key_digest(key)).map(|e| e.caller.clone())
    }

    /// Re-read the file if its content changed (or always, when `force`). A file that cannot
    /// be read or parsed keeps the current keys and logs why.
    fn reload(&self, force: bool) {
        let Some(path) = &self.file else { return };
        let current = std::fs::read(path)
            .ok()
            .map(|b| <[u8; 32]>::from(Sha256::digest(&b)));
        if !force && current.is_some() && current == *read(&self.seen) {
            return;
        }
        match self.read() {
            Ok((map, digest)) => {
                let old = read(&self.keys).clone();
                let names = |m: &KeyMap| -> BTreeSet<String> {
                    m.values()
                        .map(|e| format!("{}/{}", e.caller.tenant, e.caller.subject))
                        .collect()
                };
                let (before, after) = (names(&old), names(&map));
                let added: Vec<&String> = after.difference(&before).collect();
                let removed: Vec<&String> = before.difference(&after).collect();
                tracing::info!(
                    file = %path.display(),
                    keys = map.len(),
                    added = ?added,
                    removed = ?removed,
                    "API keys reloaded"
                );
                *write(&self.keys) = Arc::new(map);
                *write(&self.seen) = digest;
            }
            Err(e) => {
                let mut seen = write(&self.seen);
                if force || current.is_none() || current != *seen {
                    tracing::error!(error = %e, "API key file not reloaded; keeping the previous keys");
                }
                if current.is_some() {
                    *seen = current;
                }
            }
        }
    }
}

fn read<T>(l: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|e| e.into_inner())
}

fn write<T>(l: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|e| e.into_inner())
}

// ---------------------------------------------------------------------------------------------
// JWT

struct JwtVerifier {
    key: jsonwebtoken::DecodingKey,
    validation: jsonwebtoken::Validation,
    tenant_claim: String,
}

impl JwtVerifier {
    fn new(c: &JwtConfig) -> Result<JwtVerifier, String> {
        use jsonwebtoken::{Algorithm, DecodingKey, Validation};
        let key = match c.algorithm {
            Algorithm::RS256 => DecodingKey::from_rsa_pem(&c.key)
                .map_err(|e| format!("--jwt-key-file is not an RSA public key in PEM: {e}"))?,
            Algorithm::ES256 => DecodingKey::from_ec_pem(&c.key)
                .map_err(|e| format!("--jwt-key-file is not an EC public key in PEM: {e}"))?,
            _ => {
                if c.key.len() < 32 {
                    return Err(
                        "the HS256 secret in --jwt-key-file must be at least 32 bytes".into(),
                    );
                }
                DecodingKey::from_secret(&c.key)
            }
        };
        let mut validation = Validation::new(c.algorithm);
        validation.leeway = c.leeway_secs;
        validation.validate_exp = true;
        validation.validate_nbf = true;
        validation.set_issuer(&[c.issuer.as_str()]);
        validation.set_audience(&[c.audience.as_str()]);
        validation.set_required_spec_claims(&["exp", "iss", "aud", "sub"]);
        Ok(JwtVerifier {
            key,
            validation,
            tenant_claim: c.tenant_claim.clone(),
        })
    }

    fn verify(&self, token: &str) -> Result<Caller, Refusal> {
        use jsonwebtoken::errors::ErrorKind;
        let data = jsonwebtoken::decode::<serde_json::Map<String, serde_json::Value>>(
            token,
            &self.key,
            &self.validation,
        )
        .map_err(|e| {
            let (reason, detail) = match e.kind() {
                ErrorKind::ExpiredSignature => ("expired_token", "the token has expired".into()),
                ErrorKind::ImmatureSignature => {
                    ("invalid_token", "the token is not valid yet (nbf)".into())
                }
                ErrorKind::InvalidAudience => (
                    "invalid_token",
                    "the token's audience (aud) is not this service".into(),
                ),
                ErrorKind::InvalidIssuer => (
                    "invalid_token",
                    "the token's issuer (iss) is not accepted".into(),
                ),
                ErrorKind::InvalidSignature => (
                    "invalid_token",
                    "the token's signature does not verify".into(),
                ),
                ErrorKind::InvalidAlgorithm => (
                    "invalid_token",
                    "the token is signed with another algorithm than the server accepts".into(),
                ),
                ErrorKind::MissingRequiredClaim(c) => (
                    "invalid_token",
                    format!("the token has no `{}` claim", super::problem::clip(c)),
                ),
                _ => ("invalid_token", "the token is not a valid JWT".into()),
            };
            Refusal::invalid(reason, detail)
        })?;
        let claims = data.claims;
        let tenant = claims
            .get(&self.tenant_claim)
            .and_then(|v| v.as_str())
            .ok_or_else(|| {
                Refusal::invalid(
                    "invalid_token",
                    format!(
                        "the token has no string `{}` claim naming the tenant",
                        self.tenant_claim
                    ),
                )
            })?;
        let subject = claims.get("sub").and_then(|v| v.as_str()).unwrap_or("");
        Caller::new(tenant, subject)
            .map_err(|e| Refusal::invalid("invalid_token", format!("the token's tenant: {e}")))
    }
}

// ---------------------------------------------------------------------------------------------
// Stream tokens

struct StreamTokens {
    key: ring::hmac::Key,
    ttl: Duration,
}

/// What a stream token says (signed, not secret).
#[derive(Serialize, Deserialize)]
struct StreamClaims {
    /// Tenant.
    t: String,
    /// Subject.
    s: String,
    /// Job id.
    j: String,
    /// Expiry, Unix seconds.
    e: u64,
}

fn now_secs() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0)
}

impl StreamTokens {
    fn new(secret: Option<&[u8]>, ttl: Duration) -> Result<StreamTokens, String> {
        let key = match secret {
            Some(s) if s.len() < 32 => {
                return Err("--stream-token-secret-file must hold at least 32 bytes".into())
            }
            Some(s) => ring::hmac::Key::new(ring::hmac::HMAC_SHA256, s),
            None => {
                let mut s = [0u8; 32];
                random_bytes(&mut s)?;
                ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &s)
            }
        };
        Ok(StreamTokens { key, ttl })
    }

    /// `wst_<base64url claims>.<base64url HMAC-SHA256(claims)>` and its expiry (Unix secs).
    fn mint(&self, caller: &Caller, job_id: &str) -> (String, u64) {
        let exp = now_secs().saturating_add(self.ttl.as_secs().max(1));
        let claims = StreamClaims {
            t: caller.tenant.clone(),
            s: caller.subject.clone(),
            j: job_id.to_string(),
            e: exp,
        };
        let payload = serde_json::to_vec(&claims).unwrap_or_default();
        let tag = ring::hmac::sign(&self.key, &payload);
        let token = format!(
            "{STREAM_TOKEN_PREFIX}{}.{}",
            B64.encode(&payload),
            B64.encode(tag.as_ref())
        );
        (token, exp)
    }

    /// The caller a token for `job_id` stands for. The MAC is checked first (in constant
    /// time, by ring), so nothing of an unsigned payload is trusted.
    fn verify(&self, token: &str, job_id: &str) -> Result<Caller, Refusal> {
        let bad = || Refusal::invalid("invalid_token", "the stream token is not valid");
        let rest = token.strip_prefix(STREAM_TOKEN_PREFIX).ok_or_else(bad)?;
        let (payload, tag) = rest.split_once('.').ok_or_else(bad)?;
        let payload = B64.decode(payload).map_err(|_| bad())?;
        let tag = B64.decode(tag).map_err(|_| bad())?;
        ring::hmac::verify(&self.key, &payload, &tag).map_err(|_| bad())?;
        let claims: StreamClaims = serde_json::from_slice(&payload).map_err(|_| bad())?;
        if claims.e <= now_secs() {
            return Err(Refusal::invalid(
                "expired_token",
                "the stream token has expired; mint another with POST /v1/jobs/{id}/stream-token",
            ));
        }
        if claims.j != job_id {
            return Err(Refusal::invalid(
                "invalid_token",
                "the stream token was minted for another job",
            ));
        }
        Caller::new(&claims.t, &claims.s).map_err(|_| bad())
    }
}

// ---------------------------------------------------------------------------------------------
// The authenticator

/// The authentication state shared by every request: cheap to clone.
#[derive(Clone)]
pub struct Auth {
    inner: Arc<Inner>,
}

struct Inner {
    keys: Option<KeyStore>,
    jwt: Option<JwtVerifier>,
    stream: StreamTokens,
    protect_metrics: bool,
}

impl std::fmt::Debug for Auth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Auth")
            .field("keys", &self.inner.keys.is_some())
            .field("jwt", &self.inner.jwt.is_some())
            .field("protect_metrics", &self.inner.protect_metrics)
            .finish()
    }
}

impl Auth {
    /// `--auth none`: every request is [`Caller::anonymous`].
    pub fn none() -> Auth {
        Auth::new(&AuthConfig {
            stream_ttl: Duration::from_secs(300),
            ..AuthConfig::default()
        })
        // The only fallible parts are reading keys (none here) and the system RNG.
        .unwrap_or_else(|_| Auth {
            inner: Arc::new(Inner {
                keys: None,
                jwt: None,
                stream: StreamTokens {
                    key: ring::hmac::Key::new(ring::hmac::HMAC_SHA256, &[0u8; 0]),
                    ttl: Duration::ZERO,
                },
                protect_metrics: false,
            }),
        })
    }

    /// Load the keys (a bad key file is an error here, at start-up), the JWT key and the
    /// stream-token secret. Call [`Auth::spawn_reloader`] to follow key file changes.
    pub fn new(config: &AuthConfig) -> Result<Auth, String> {
        let keys = if config.mode.keys {
            let store = KeyStore::load(
                config.keys_file.clone(),
                config.keys_env.clone(),
                config.keys_poll,
            )?;
            let n = read(&store.keys).len();
            tracing::info!(keys = n, "API keys loaded");
            Some(store)
        } else {
            None
        };
        let jwt = match (&config.jwt, config.mode.jwt) {
            (Some(c), true) => Some(JwtVerifier::new(c)?),
            (None, true) => return Err("--auth jwt needs the --jwt-* settings".into()),
            _ => None,
        };
        Ok(Auth {
            inner: Arc::new(Inner {
                keys,
                jwt,
                stream: StreamTokens::new(config.stream_secret.as_deref(), config.stream_ttl)?,
                protect_metrics: config.protect_metrics,
            }),
        })
    }

    /// Whether requests are authenticated at all (`--auth` other than `none`).
    pub fn enabled(&self) -> bool {
        self.inner.keys.is_some() || self.inner.jwt.is_some()
    }

    /// Follow the key file: re-read it when its content changes (checked every
    /// `--api-keys-poll-secs`) and on SIGHUP. The task ends when the last `Auth` clone is
    /// dropped. Needs a tokio runtime; a no-op without a key file.
    pub fn spawn_reloader(&self) {
        let Some(store) = &self.inner.keys else {
            return;
        };
        if store.file.is_none() {
            return;
        }
        let poll = store.poll;
        let weak: Weak<Inner> = Arc::downgrade(&self.inner);
        tokio::spawn(async move {
            #[cfg(unix)]
            let mut hup =
                tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).ok();
            let mut tick = tokio::time::interval(poll);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            tick.tick().await;
            loop {
                #[cfg(unix)]
                let forced = match hup.as_mut() {
                    Some(h) => tokio::select! {
                        _ = tick.tick() => false,
                        _ = h.recv() => true,
                    },
                    None => {
                        tick.tick().await;
                        false
                    }
                };
                #[cfg(not(unix))]
                let forced = {
                    tick.tick().await;
                    false
                };
                let Some(inner) = weak.upgrade() else { return };
                if let Some(store) = &inner.keys {
                    // File reads are small and rare: not worth a blocking thread.
                    store.reload(forced);
                }
            }
        });
    }

    /// Who `bearer` is.
    fn verify_bearer(&self, bearer: &str) -> Result<Caller, Refusal> {
        let looks_jwt = bearer.split('.').count() == 3;
        match (&self.inner.jwt, &self.inner.keys) {
            (Some(jwt), _) if looks_jwt || self.inner.keys.is_none() => jwt.verify(bearer),
            (_, Some(keys)) => keys.lookup(bearer).ok_or_else(|| {
                Refusal::invalid(
                    "invalid_token",
                    "the API key is not valid (unknown or revoked)",
                )
            }),
            _ => Ok(Caller::anonymous()),
        }
    }

    /// The caller of a request (`access_token` already taken out of its URI), or why not.
    fn caller_for(
        &self,
        method: &Method,
        path: &str,
        headers: &HeaderMap,
        access_token: Option<&str>,
    ) -> Result<Caller, Refusal> {
        if !self.enabled() || is_open(path, self.inner.protect_metrics) {
            return Ok(Caller::anonymous());
        }
        // CORS preflights carry no credentials; the CORS layer answers them itself.
        if method == Method::OPTIONS && headers.contains_key(header::ACCESS_CONTROL_REQUEST_METHOD)
        {
            return Ok(Caller::anonymous());
        }
        if let Some(value) = headers.get(header::AUTHORIZATION) {
            let bearer = bearer_token(value)?;
            return self.verify_bearer(bearer);
        }
        match access_token {
            Some(token) => match stream_token_job(method, path) {
                Some(job) => self.inner.stream.verify(token, job),
                None => Err(Refusal::invalid(
                    "invalid_request",
                    "a stream token (access_token) is accepted only on GET \
                     /v1/jobs/{id}/events and /v1/jobs/{id}/frames/{step}; send \
                     `Authorization: Bearer` elsewhere",
                )),
            },
            None => Err(Refusal {
                reason: "missing_credentials",
                detail: "this request needs credentials: send `Authorization: Bearer <API key \
                         or JWT>`"
                    .into(),
                invalid_token: false,
            }),
        }
    }
}

/// The token of an `Authorization: Bearer <token>` header.
fn bearer_token(value: &HeaderValue) -> Result<&str, Refusal> {
    let s = value.to_str().map_err(|_| {
        Refusal::invalid("invalid_request", "the Authorization header is not ASCII")
    })?;
    let (scheme, token) = s.trim().split_once(' ').unwrap_or((s.trim(), ""));
    if !scheme.eq_ignore_ascii_case("bearer") {
        return Err(Refusal::invalid(
            "invalid_request",
            "the Authorization header must use the Bearer scheme",
        ));
    }
    let token = token.trim();
    if token.is_empty() {
        return Err(Refusal::invalid(
            "invalid_request",
            "the Authorization header has no token after `Bearer`",
        ));
    }
    Ok(token)
}

/// Paths anyone may call: probes, docs, the web page, gRPC health and reflection, and
/// `/metrics` unless protected.
pub fn is_open(path: &str, protect_metrics: bool) -> bool {
    matches!(
        path,
        "/healthz" | "/readyz" | "/" | "/docs" | "/openapi.json"
    ) || (path == "/metrics" && !protect_metrics)
        || path.starts_with("/ui/")
        || path.starts_with("/grpc.health.v1.Health/")
        || path.starts_with("/grpc.reflection.v1.ServerReflection/")
        || path.starts_with("/grpc.reflection.v1alpha.ServerReflection/")
}

/// The job a stream token may open on this request: `GET /v1/jobs/{id}/events` and
/// `GET /v1/jobs/{id}/frames/{step}`.
fn stream_token_job<'a>(method: &Method, path: &'a str) -> Option<&'a str> {
    if method != Method::GET {
        return None;
    }
    let rest = path.strip_prefix("/v1/jobs/")?;
    let mut parts = rest.split('/');
    let id = parts.next().filter(|s| !s.is_empty())?;
    match (parts.next(), parts.next(), parts.next()) {
        (Some("events"), None, None) => Some(id),
        (Some("frames"), Some(step), None) if !step.is_empty() => Some(id),
        _ => None,
    }
}

/// Take every `access_token` out of the query: the first one's value is returned, and the
/// URI keeps only the other parameters, so no handler, error message or log below sees it.
pub fn strip_access_token(uri: &Uri) -> (Option<String>, Option<Uri>) {
    let Some(query) = uri.query() else {
        return (None, None);
    };
    let pairs: Vec<(String, String)> = form_urlencoded::parse(query.as_bytes())
        .map(|(k, v)| (k.into_owned(), v.into_owned()))
        .collect();
    if !pairs.iter().any(|(k, _)| k == ACCESS_TOKEN_PARAM) {
        return (None, None);
    }
    let mut token = None;
    let mut rest = form_urlencoded::Serializer::new(String::new());
    for (k, v) in &pairs {
        if k == ACCESS_TOKEN_PARAM {
            if token.is_none() {
                token = Some(v.clone());
            }
        } else {
            rest.append_pair(k, v);
        }
    }
    let rest = rest.finish();
    let pq = if rest.is_empty() {
        uri.path().to_string()
    } else {
        format!("{}?{rest}", uri.path())
    };
    let mut parts = uri.clone().into_parts();
    parts.path_and_query = pq.parse().ok();
    (token, Uri::from_parts(parts).ok())
}

/// Why a request is refused. `detail` never quotes the credentials.
#[derive(Debug)]
pub struct Refusal {
    /// `missing_credentials`, `invalid_request`, `invalid_token`, `expired_token`.
    pub reason: &'static str,
    pub detail: String,
    /// Credentials were sent but are wrong (`error="invalid_token"` in WWW-Authenticate).
    invalid_token: bool,
}

impl Refusal {
    fn invalid(reason: &'static str, detail: impl Into<String>) -> Refusal {
        Refusal {
            reason,
            detail: detail.into(),
            invalid_token: reason != "invalid_request",
        }
    }

    fn www_authenticate(&self) -> HeaderValue {
        let v = if self.invalid_token {
            "Bearer realm=\"willow\", error=\"invalid_token\"".to_string()
        } else if self.reason == "invalid_request" {
            "Bearer realm=\"willow\", error=\"invalid_request\"".to_string()
        } else {
            "Bearer realm=\"willow\"".to_string()
        };
        HeaderValue::from_str(&v).unwrap_or(HeaderValue::from_static("Bearer"))
    }

    fn http(&self, path: &str) -> Response {
        let mut res = Problem::new(StatusCode::UNAUTHORIZED, "unauthenticated", &self.detail)
            .with("reason", self.reason)
            .instance(path)
            .into_response();
        res.headers_mut()
            .insert(header::WWW_AUTHENTICATE, self.www_authenticate());
        res
    }

    fn grpc(&self) -> Response {
        let mut details = tonic_types::ErrorDetails::new();
        details.set_error_info(
            self.reason.to_ascii_uppercase(),
            "willow.v1",
            HashMap::new(),
        );
        use tonic_types::StatusExt as _;
        let status =
            tonic::Status::with_error_details(tonic::Code::Unauthenticated, &self.detail, details);
        status.into_http::<Body>()
    }
}

/// The middleware: authenticate, put the [`Caller`] in the request extensions, or refuse.
/// Wire it with `axum::middleware::from_fn_with_state(auth, auth::authenticate)`.
pub async fn authenticate(State(auth): State<Auth>, mut req: Request, next: Next) -> Response {
    let (access_token, stripped) = strip_access_token(req.uri());
    if let Some(uri) = stripped {
        *req.uri_mut() = uri;
    }
    let verdict = auth.caller_for(
        req.method(),
        req.uri().path(),
        req.headers(),
        access_token.as_deref(),
    );
    match verdict {
        Ok(caller) => {
            if auth.enabled() {
                tracing::Span::current().record("tenant", caller.tenant.as_str());
            }
            req.extensions_mut().insert(caller);
            next.run(req).await
        }
        Err(refusal) => {
            tracing::info!(reason = refusal.reason, "request refused: unauthenticated");
            let grpc = req
                .headers()
                .get(header::CONTENT_TYPE)
                .is_some_and(|v| v.as_bytes().starts_with(b"application/grpc"));
            if grpc {
                refusal.grpc()
            } else {
                refusal.http(req.uri().path())
            }
        }
    }
}

impl Auth {
    /// `router` behind this authentication (one layer for everything it serves).
    pub fn wrap(&self, router: Router) -> Router {
        router.layer(axum::middleware::from_fn_with_state(
            self.clone(),
            authenticate,
        ))
    }
}

// ---------------------------------------------------------------------------------------------
// Minting stream tokens

/// A stream token: pass it as `?access_token=` to the job's events (`EventSource`) or frame
/// downloads.
#[derive(Debug, Serialize, Deserialize, utoipa::ToSchema)]
pub struct StreamToken {
    /// The token. Valid only for this job, until `expires_at`.
    pub token: String,
    /// RFC 3339 UTC.
    pub expires_at: String,
    /// Seconds from now.
    pub expires_in: u64,
}

#[derive(Clone)]
pub struct MintState {
    jobs: Jobs,
    auth: Auth,
}

/// `POST /v1/jobs/{id}/stream-token`, to merge into the REST routes (behind the layer).
pub fn routes(jobs: Jobs, auth: Auth) -> Router {
    Router::new()
        .route("/v1/jobs/{id}/stream-token", post(mint_stream_token))
        .with_state(MintState { jobs, auth })
}

/// A short-lived token for this job's events and frames, for clients that cannot send headers
/// (a browser's `EventSource`): `GET /v1/jobs/{id}/events?access_token=…`.
#[utoipa::path(post, path = "/v1/jobs/{id}/stream-token", tag = "jobs",
    params(("id" = String, Path)),
    responses((status = 200, description = "A token for `?access_token=` on this job's events and frames", body = StreamToken),
        (status = 401, description = "No or bad credentials", body = Problem, content_type = "application/problem+json"),
        (status = 404, description = "No such job", body = Problem, content_type = "application/problem+json")))]
pub async fn mint_stream_token(
    State(st): State<MintState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Response {
    let instance = format!("/v1/jobs/{id}/stream-token");
    // The caller's own job only: another tenant's is 404, like one that does not exist.
    if let Err(e) = st.jobs.get(&caller, &id).await {
        return Problem::from(e).instance(instance).into_response();
    }
    let (token, exp) = st.inner_mint(&caller, &id);
    let body = StreamToken {
        token,
        expires_at: rfc3339(exp.saturating_mul(1000)),
        expires_in: exp.saturating_sub(now_secs()),
    };
    let mut res = (StatusCode::OK, Json(body)).into_response();
    res.headers_mut()
        .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    res
}

impl MintState {
    fn inner_mint(&self, caller: &Caller, job_id: &str) -> (String, u64) {
        self.auth.inner.stream.mint(caller, job_id)
    }
}

/// OpenAPI: the `bearer` scheme, required everywhere but on the open routes.
pub struct SecurityAddon;

impl utoipa::Modify for SecurityAddon {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{
            ApiKey, ApiKeyValue, HttpAuthScheme, HttpBuilder, SecurityRequirement, SecurityScheme,
        };
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(
                HttpBuilder::new()
                    .scheme(HttpAuthScheme::Bearer)
                    .bearer_format("API key (wlw_…) or JWT")
                    .description(Some(
                        "With --auth keys or jwt. An EventSource, which cannot send headers, \
                         passes a stream token from POST /v1/jobs/{id}/stream-token as \
                         ?access_token= instead.",
                    ))
                    .build(),
            ),
        );
        components.add_security_scheme(
            "stream_token",
            SecurityScheme::ApiKey(ApiKey::Query(ApiKeyValue::with_description(
                ACCESS_TOKEN_PARAM,
                "A stream token from POST /v1/jobs/{id}/stream-token, for this job's events \
                 and frames only",
            ))),
        );
        openapi.security = Some(vec![SecurityRequirement::new(
            "bearer",
            Vec::<String>::new(),
        )]);
        for (path, item) in openapi.paths.paths.iter_mut() {
            if is_open(path, false) {
                for op in [&mut item.get, &mut item.post].into_iter().flatten() {
                    op.security = Some(vec![SecurityRequirement::default()]);
                }
            } else if stream_token_job(&Method::GET, path).is_some() {
                // Either a bearer or this job's stream token.
                if let Some(op) = item.get.as_mut() {
                    op.security = Some(vec![
                        SecurityRequirement::new("bearer", Vec::<String>::new()),
                        SecurityRequirement::new("stream_token", Vec::<String>::new()),
                    ]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_parse() {
        assert_eq!(AuthMode::parse("none"), Ok(AuthMode::default()));
        assert_eq!(
            AuthMode::parse("keys,jwt"),
            Ok(AuthMode {
                keys: true,
                jwt: true
            })
        );
        assert!(AuthMode::parse("basic").is_err());
        assert!(AuthMode::parse("").is_err());
    }

    #[test]
    fn loopback_rule() {
        let none = AuthMode::default();
        let keys = AuthMode {
            keys: true,
            jwt: false,
        };
        let lo: SocketAddr = "127.0.0.1:8080".parse().unwrap();
        let lo6: SocketAddr = "[::1]:8080".parse().unwrap();
        let any: SocketAddr = "0.0.0.0:8080".parse().unwrap();
        assert!(check_bind(lo, none, false).is_ok());
        assert!(check_bind(lo6, none, false).is_ok());
        let e = check_bind(any, none, false).unwrap_err();
        assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
        assert!(check_bind(any, none, true).is_ok());
        assert!(check_bind(any, keys, false).is_ok());
    }

    #[test]
    fn from_args_refuses_network_without_auth() {
        let args = AuthArgs::default();
        let e = AuthConfig::from_args(&args, "0.0.0.0:80".parse().unwrap()).unwrap_err();
        assert!(e.contains("--insecure-allow-unauthenticated"), "{e}");
        let jwt = AuthArgs {
            auth: "jwt".into(),
            jwt_algorithm: Some("HS256".into()),
            ..AuthArgs::default()
        };
        let e = AuthConfig::from_args(&jwt, "127.0.0.1:80".parse().unwrap()).unwrap_err();
        assert!(e.contains("--jwt-key-file"), "{e}");
    }

    #[test]
    fn key_lines() {
        let (key, line) = new_key("acme", "ci").unwrap();
        assert!(key.starts_with(KEY_PREFIX));
        assert!(!line.contains(&key));
        let mut map = KeyMap::new();
        parse_keys(&format!("# keys\n\n{line}  # the CI\n"), "f", &mut map).unwrap();
        assert_eq!(map.len(), 1);
        let entry = map.get(&key_digest(&key)).unwrap();
        assert_eq!(entry.caller.tenant, "acme");
        assert_eq!(entry.caller.subject, "ci");
        let e = parse_keys(&format!("{line}\n{line}\n"), "f", &mut KeyMap::new()).unwrap_err();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_keys("acme ci sha256:zz\n", "f", &mut KeyMap::new()).unwrap_err();
        assert!(e.contains("line 1") && !e.contains("zz"), "{e}");
        assert!(parse_keys("a/b ci sha256:00\n", "f", &mut KeyMap::new()).is_err());
        assert!(new_key("acme", "two words").is_err());
        assert!(new_key("bad tenant!", "x").is_err());
    }

    #[test]
    fn access_token_is_stripped() {
        let uri: Uri = "/v1/jobs/a/events?from_step=2&access_token=wst_x.y&z=1"
            .parse()
            .unwrap();
        let (token, uri) = strip_access_token(&uri);
        assert_eq!(token.as_deref(), Some("wst_x.y"));
        let uri = uri.unwrap();
        assert_eq!(uri.path(), "/v1/jobs/a/events");
        assert_eq!(uri.query(), Some("from_step=2&z=1"));
        assert!(!uri.to_string().contains("wst_"));
        let only: Uri = "/v1/jobs/a/events?access_token=s".parse().unwrap();
        let (t, u) = strip_access_token(&only);
        assert_eq!(t.as_deref(), Some("s"));
        assert_eq!(u.unwrap().to_string(), "/v1/jobs/a/events");
        let none: Uri = "/v1/jobs?page_size=2".parse().unwrap();
        assert_eq!(strip_access_token(&none).0, None);
    }

    #[test]
    fn stream_token_routes() {
        let g = Method::GET;
        assert_eq!(stream_token_job(&g, "/v1/jobs/j1/events"), Some("j1"));
        assert_eq!(stream_token_job(&g, "/v1/jobs/j1/frames/3"), Some("j1"));
        assert_eq!(stream_token_job(&g, "/v1/jobs/j1/frames"), None);
        assert_eq!(stream_token_job(&g, "/v1/jobs/j1"), None);
        assert_eq!(stream_token_job(&g, "/v1/jobs/j1/result"), None);
        assert_eq!(stream_token_job(&Method::POST, "/v1/jobs/j1/events"), None);
    }

    #[test]
    fn stream_tokens_bind_job_and_expire() {
        let st = StreamTokens::new(None, Duration::from_secs(60)).unwrap();
        let caller = Caller::new("acme", "ci").unwrap();
        let (token, _) = st.mint(&caller, "job-a");
        assert_eq!(st.verify(&token, "job-a").unwrap(), caller);
        assert_eq!(
            st.verify(&token, "job-b").unwrap_err().reason,
            "invalid_token"
        );
        // Another process's secret: refused.
        let other = StreamTokens::new(None, Duration::from_secs(60)).unwrap();
        assert!(other.verify(&token, "job-a").is_err());
        // A tampered payload: refused.
        let forged = token.replacen("wst_e", "wst_f", 1);
        assert!(st.verify(&forged, "job-a").is_err());
        let e = st.verify("garbage", "job-a").unwrap_err();
        assert!(!e.detail.contains("garbage"));
    }
}
