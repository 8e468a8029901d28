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
//! One file per part: `config.rs` (flags, the bind rule), `keys.rs`, `jwt.rs`, `tokens.rs` (stream
//! tokens and their minting route); this one holds the layer itself.
//!
//! Secrets never reach a log line: `access_token` is removed from the URI before anything
//! below this layer sees it, the request span records only the path, and refusals log the
//! reason, never the token.

// `Problem` is large; errors are the cold path (see http.rs).
#![allow(clippy::result_large_err)]

use super::problem::Problem;
use crate::jobs::Caller;
use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Router;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, RwLock, Weak};
use std::time::Duration;

mod config;
mod jwt;
mod keys;
mod tokens;

pub use config::{check_bind, AuthArgs, AuthConfig, AuthMode, JwtConfig};
pub use keys::new_key;
// utoipa's path item for the OpenAPI document, beside its handler.
use jwt::JwtVerifier;
use keys::{read, KeyStore};
use sha2::{Digest, Sha256};
pub use tokens::__path_mint_stream_token;
use tokens::StreamTokens;
pub use tokens::{mint_stream_token, routes, MintState, StreamToken};

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
// The authenticator

/// The authentication state shared by every request: cheap to clone.
#[derive(Clone)]
pub struct Auth {
    inner: Arc<Inner>,
}

struct Inner {
    keys: Option<KeyStore>,
    jwt: Option<JwtKey>,
    stream: StreamTokens,
    protect_metrics: bool,
    /// How often the reloader looks at the key files.
    poll: Duration,
}

/// The JWT verifier, rebuilt when its key file changes.
struct JwtKey {
    config: JwtConfig,
    verifier: RwLock<JwtVerifier>,
    /// SHA-256 of the key in use, to tell a changed file from a touched one.
    digest: Mutex<[u8; 32]>,
}

impl JwtKey {
    fn new(config: &JwtConfig) -> Result<JwtKey, String> {
        Ok(JwtKey {
            verifier: RwLock::new(JwtVerifier::new(config)?),
            digest: Mutex::new(Sha256::digest(&config.key).into()),
            config: config.clone(),
        })
    }

    /// Re-read the key file; a key that is the same (unless `forced`), unreadable or invalid
    /// keeps the one in use.
    fn reload(&self, forced: bool) {
        let Some(path) = &self.config.key_file else {
            return;
        };
        let key = match config::read_jwt_key(path, self.config.algorithm) {
            Ok(k) => k,
            Err(e) => {
                tracing::warn!(error = %e, "JWT key not reloaded; keeping the one in use");
                return;
            }
        };
        let digest: [u8; 32] = Sha256::digest(&key).into();
        let mut current = self.digest.lock().unwrap_or_else(|e| e.into_inner());
        if digest == *current && !forced {
            return;
        }
        let config = JwtConfig {
            key,
            ..self.config.clone()
        };
        match JwtVerifier::new(&config) {
            Ok(v) => {
                *keys::write(&self.verifier) = v;
                *current = digest;
                tracing::info!(file = %path.display(), "JWT key reloaded");
            }
            Err(e) => {
                tracing::warn!(error = %e, "JWT key file changed but holds no valid key; keeping the one in use");
            }
        }
    }
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
                poll: Duration::from_secs(5),
            }),
        })
    }

    /// Load the keys (a bad key file is an error here, at start-up), the JWT key and the
    /// stream-token secret. Call [`Auth::spawn_reloader`] to follow key file changes.
    pub fn new(config: &AuthConfig) -> Result<Auth, String> {
        let keys = if config.mode.keys {
            let store = KeyStore::load(config.keys_file.clone(), config.keys_env.clone())?;
            let n = read(&store.keys).len();
            tracing::info!(keys = n, "API keys loaded");
            Some(store)
        } else {
            None
        };
        let jwt = match (&config.jwt, config.mode.jwt) {
            (Some(c), true) => Some(JwtKey::new(c)?),
            (None, true) => return Err("--auth jwt needs the --jwt-* settings".into()),
            _ => None,
        };
        Ok(Auth {
            inner: Arc::new(Inner {
                keys,
                jwt,
                stream: StreamTokens::new(config.stream_secret.as_deref(), config.stream_ttl)?,
                protect_metrics: config.protect_metrics,
                poll: config.keys_poll.max(Duration::from_millis(100)),
            }),
        })
    }

    /// Whether requests are authenticated at all (`--auth` other than `none`).
    pub fn enabled(&self) -> bool {
        self.inner.keys.is_some() || self.inner.jwt.is_some()
    }

    /// Follow the key files (API keys, the JWT key): re-read each when its content changes
    /// (checked every `--api-keys-poll-secs`) and on SIGHUP. The task ends when the last
    /// `Auth` clone is dropped. Needs a tokio runtime; a no-op without a key file.
    pub fn spawn_reloader(&self) {
        let keys_file = self.inner.keys.as_ref().is_some_and(|k| k.file.is_some());
        let jwt_file = self
            .inner
            .jwt
            .as_ref()
            .is_some_and(|j| j.config.key_file.is_some());
        if !keys_file && !jwt_file {
            return;
        }
        let poll = self.inner.poll;
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
                // File reads are small and rare: not worth a blocking thread.
                if let Some(store) = &inner.keys {
                    store.reload(forced);
                }
                if let Some(jwt) = &inner.jwt {
                    jwt.reload(forced);
                }
            }
        });
    }

    /// Who `bearer` is.
    fn verify_bearer(&self, bearer: &str) -> Result<Caller, Refusal> {
        let looks_jwt = bearer.split('.').count() == 3;
        match (&self.inner.jwt, &self.inner.keys) {
            (Some(jwt), _) if looks_jwt || self.inner.keys.is_none() => {
                read(&jwt.verifier).verify(bearer)
            }
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
}
