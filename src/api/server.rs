//! The one server: a single axum `Router` serving HTTP/1.1, h2c and gRPC on one port, and the
//! `willow serve` command that runs it.
//!
//! Layers, outermost first: request id (set, then propagated to the response), tracing (one
//! span per request carrying the request id and, once a handler knows it, the job id), then
//! for the REST routes only: CORS and the body limits. gRPC routes get their own limits on the
//! generated services.

use super::auth::{Auth, AuthArgs, AuthConfig};
use super::conn::ConnLimits;
use super::http::{self, MULTIPART_SLACK};
use super::state::AppState;
use crate::jobs::{Config, Jobs, Shutdown};
use axum::extract::DefaultBodyLimit;
use axum::http::{header, HeaderName, HeaderValue, Method, Request};
use axum::Router;
use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;
use tokio_util::sync::CancellationToken;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::limit::RequestBodyLimitLayer;
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

/// How long the HTTP server waits for open requests once the job core has drained; SSE streams
/// are ended first, so this only covers downloads in flight.
const HTTP_DRAIN: Duration = Duration::from_secs(10);

const REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// `willow serve`: flags. Every default works on a fresh machine.
#[derive(Debug, Clone, clap::Args)]
pub struct ServeArgs {
    /// Address to listen on (HTTP/1.1, h2c and gRPC share it).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Where jobs, frames and results are kept (created if missing).
    #[arg(long, default_value = "./willow-data")]
    pub data_dir: PathBuf,
    /// Blocking workers, each running one flow (default: number of cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Jobs that may wait for a worker before submissions get 429.
    #[arg(long, default_value_t = 64)]
    pub queue_capacity: usize,
    /// Largest upload in MiB.
    #[arg(long, default_value_t = 64)]
    pub max_upload_mib: u64,
    /// Most steps per job.
    #[arg(long, default_value_t = 10_000)]
    pub max_steps: usize,
    /// Hours a finished job's results are kept (then 410 Gone).
    #[arg(long, default_value_t = 24.0)]
    pub result_ttl_hours: f64,
    /// Seconds running jobs get to finish on SIGTERM/Ctrl-C before they are re-queued.
    #[arg(long, default_value_t = 30.0)]
    pub grace_secs: f64,
    /// Log format: `json` (one object per line) or `text`.
    #[arg(long, default_value = "json")]
    pub log_format: String,
    /// A running job checkpoints after this many steps (or `--checkpoint-secs`, whichever
    /// comes first); after a crash it resumes from there.
    #[arg(long, default_value_t = 10)]
    pub checkpoint_steps: usize,
    /// Seconds between a running job's checkpoints at most.
    #[arg(long, default_value_t = 30.0)]
    pub checkpoint_secs: f64,
    /// `embedded` (SQLite and files in --data-dir, one process) or `nats://HOST:PORT`
    /// (NATS JetStream: many API and worker nodes; --data-dir is then scratch).
    #[arg(long, default_value = "embedded")]
    pub backend: String,
    /// `api` (requests, no workers), `worker` (runs jobs; serves only probes and metrics) or
    /// `all`. The embedded backend needs `all`: its queue lives in the process.
    #[arg(long, default_value = "all")]
    pub role: String,
    /// A job delivered this many times in a row without reaching a new checkpoint (its
    /// workers kept dying on it before any progress that lasts: killed, out of memory) fails
    /// with code `redelivered` instead of taking down one more worker. Runs that died after a
    /// new checkpoint do not count.
    #[arg(long, default_value_t = 3)]
    pub max_deliveries: u32,
    /// NATS: seconds without a heartbeat after which a job goes to another worker.
    #[arg(long, default_value_t = 30.0)]
    pub nats_ack_wait_secs: f64,
    /// Per tenant: queued plus running jobs at most (0 = no limit).
    #[arg(long, default_value_t = 32)]
    pub tenant_max_live_jobs: usize,
    /// Per tenant: MiB kept (stored uploads; unexpired jobs' inputs and what they may store:
    /// kept frames, checkpoint, result, metrics, stored renderings; 0 = no limit).
    #[arg(long, default_value_t = 1024)]
    pub tenant_max_stored_mib: u64,
    /// The whole server: MiB kept by every tenant together, counted as
    /// `--tenant-max-stored-mib` counts them; past it submissions and uploads of every tenant
    /// answer 507 `quota_exceeded`, quota `server_stored_bytes` (0 = no budget).
    #[arg(long, default_value_t = 0)]
    pub disk_budget_mib: u64,
    /// Per tenant: meshes received (jobs and uploads) in any minute (0 = no limit).
    #[arg(long, default_value_t = 120)]
    pub tenant_uploads_per_minute: usize,
    /// Let jobs' `callback_url` use plain `http` and reach loopback, private and link-local
    /// addresses. For tests and closed networks: otherwise a client could make the server
    /// probe its own network.
    #[arg(long)]
    pub allow_insecure_callbacks: bool,
    /// A file holding the server secret of webhook signatures (at least 16 bytes, surrounding
    /// whitespace ignored; a file, so the secret is not in the process list). Each tenant's
    /// key is HMAC-SHA256(secret, tenant id). Default: random per process, so receivers cannot
    /// check signatures across a restart.
    #[arg(long)]
    pub webhook_secret_file: Option<PathBuf>,
    /// Tries of one webhook before it is given up (retries wait 1 s, 2 s, 4 s, … up to 5 min).
    #[arg(long, default_value_t = 12)]
    pub webhook_max_attempts: u32,
    #[command(flatten)]
    pub auth: AuthArgs,
    /// An origin (`https://app.example`, exactly as browsers send it) whose pages may call the
    /// API (CORS); repeat for more. Default: none, no CORS headers at all (the built-in page
    /// at `/` is same-origin and needs none).
    #[arg(long = "cors-origin", value_name = "ORIGIN")]
    pub cors_origins: Vec<String>,
    /// Seconds a client has to send a complete request head; for HTTP/1 this also bounds the
    /// wait for the next request on a keep-alive connection.
    #[arg(long, default_value_t = 10.0)]
    pub header_read_timeout_secs: f64,
    /// Seconds a request body may stall; also the grace period before --body-min-rate-kib
    /// applies.
    #[arg(long, default_value_t = 30.0)]
    pub body_timeout_secs: f64,
    /// Minimum average request-body rate (KiB/s) once --body-timeout-secs has passed; 0: only
    /// the stall limit.
    #[arg(long, default_value_t = 32)]
    pub body_min_rate_kib: u64,
    /// Seconds a connection with no request in flight stays open.
    #[arg(long, default_value_t = 60.0)]
    pub idle_timeout_secs: f64,
    /// Seconds between HTTP/2 keep-alive pings (unanswered for 20 s: the connection closes).
    #[arg(long, default_value_t = 30.0)]
    pub keepalive_interval_secs: f64,
    /// Connections served at once; further ones wait in the listen backlog until one closes.
    #[arg(long, default_value_t = 1024)]
    pub max_connections: usize,
    /// Requests per connection (HTTP/1: the last response says `Connection: close`; HTTP/2:
    /// graceful GOAWAY); 0: no limit.
    #[arg(long, default_value_t = 1000)]
    pub max_requests_per_connection: u64,
    /// HTTP/2 streams (gRPC calls, requests) open at once on one connection.
    #[arg(long, default_value_t = 128)]
    pub max_streams_per_connection: u32,
    /// Seconds a socket write may stay blocked (the client stopped reading) before the
    /// connection closes; also the grace period of a download before --write-min-rate-kib.
    #[arg(long, default_value_t = 30.0)]
    pub write_timeout_secs: f64,
    /// Minimum rate (KiB/s) at which a client must take a mesh download: one of n bytes must
    /// be read within --write-timeout-secs + n / rate, or it is dropped; event streams (SSE,
    /// StreamFrames) keep the same floor or are cut off; 0: only the timeout.
    #[arg(long, default_value_t = 64)]
    pub write_min_rate_kib: u64,
    /// MiB held for mesh downloads waiting for their clients, server-wide (a download streamed
    /// from storage holds 256 KiB, one that could not be stored all of it); beyond it
    /// downloads answer 503 `downloads_busy` (gRPC UNAVAILABLE) with Retry-After.
    #[arg(long, default_value_t = 256)]
    pub download_memory_mib: u64,
    /// MiB held for mesh downloads at once for one connection.
    #[arg(long, default_value_t = 32)]
    pub download_memory_per_connection_mib: u64,
}

/// Longest timeout the flags accept (a day): beyond it `Duration` conversions could overflow
/// and no client needs it.
const MAX_TIMEOUT_SECS: f64 = 86_400.0;

/// Seconds from a flag, validated: positive, finite, at most a day.
fn secs(flag: &str, v: f64) -> Result<Duration, String> {
    if !(v.is_finite() && v > 0.0 && v <= MAX_TIMEOUT_SECS) {
        return Err(format!(
            "--{flag} must be a number of seconds above 0 and at most {MAX_TIMEOUT_SECS}, got {v}"
        ));
    }
    Ok(Duration::from_secs_f64(v))
}

/// A `--cors-origin` value as the `Origin` header carries it: `http` or `https`, a host, an
/// optional port, nothing else. Scheme and host are lower-cased and a default port dropped,
/// as browsers do, so the comparison is exact.
pub fn parse_origin(s: &str) -> Result<HeaderValue, String> {
    let bad = |why: &str| format!("--cors-origin `{}`: {why}", super::problem::clip(s));
    if s == "*" || s == "null" {
        return Err(bad(
            "give exact origins (`https://app.example`); CORS here is an allow-list",
        ));
    }
    let (scheme, rest) = s
        .split_once("://")
        .ok_or_else(|| bad("expected `http://HOST[:PORT]` or `https://HOST[:PORT]`"))?;
    let scheme = scheme.to_ascii_lowercase();
    if scheme != "http" && scheme != "https" {
        return Err(bad("the scheme must be http or https"));
    }
    if rest.contains(['/', '?', '#']) {
        return Err(bad(
            "an origin has no path, query or fragment (not even a trailing `/`)",
        ));
    }
    if rest.contains('@') {
        return Err(bad("an origin has no user name or password"));
    }
    let authority: axum::http::uri::Authority =
        rest.parse().map_err(|_| bad("not a valid host[:port]"))?;
    if authority.host().is_empty() {
        return Err(bad("the host is missing"));
    }
    let host = authority.host().to_ascii_lowercase();
    let port = match rest.get(authority.host().len()..).unwrap_or("") {
        "" => None,
        tail => Some(
            tail.strip_prefix(':')
                .filter(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
                .and_then(|p| p.parse::<u16>().ok())
                .ok_or_else(|| bad("the port must be a number up to 65535"))?,
        ),
    };
    let port = match (port, scheme.as_str()) {
        (Some(80), "http") | (Some(443), "https") | (None, _) => String::new(),
        (Some(p), _) => format!(":{p}"),
    };
    HeaderValue::from_str(&format!("{scheme}://{host}{port}"))
        .map_err(|_| bad("not a valid header value"))
}

/// What [`app`] needs beyond the job core; `Default` (no CORS grants, [`Auth::none`]) is what
/// tests usually want.
#[derive(Debug, Clone)]
pub struct AppOptions {
    /// Origins granted CORS (see [`parse_origin`]); empty: no CORS headers at all.
    pub cors_origins: Vec<HeaderValue>,
    /// Every request but the probes and open routes goes through it ([`Auth::none`]: everyone
    /// is the anonymous caller).
    pub auth: Auth,
}

impl Default for AppOptions {
    fn default() -> Self {
        AppOptions {
            cors_origins: Vec::new(),
            auth: Auth::none(),
        }
    }
}

/// [`serve_with`]'s options: the router's and the connections'.
#[derive(Debug, Clone, Default)]
pub struct ServeOptions {
    pub app: AppOptions,
    pub conn: ConnLimits,
}

impl ServeArgs {
    /// The HTTP options these flags describe, validated. Authentication is built here too,
    /// before anything starts: a non-loopback address without auth is refused, and a bad key
    /// file or JWT key too.
    pub fn serve_options(&self) -> Result<ServeOptions, String> {
        let auth = Auth::new(&AuthConfig::from_args(&self.auth, self.addr)?)?;
        let cors_origins = self
            .cors_origins
            .iter()
            .map(|o| parse_origin(o))
            .collect::<Result<Vec<_>, _>>()?;
        if self.max_connections == 0 || self.max_connections > 1_000_000 {
            return Err("--max-connections must be between 1 and 1000000".into());
        }
        if self.download_memory_mib == 0 || self.download_memory_per_connection_mib == 0 {
            return Err(
                "--download-memory-mib and --download-memory-per-connection-mib must be at least 1"
                    .into(),
            );
        }
        if self.max_streams_per_connection == 0 {
            return Err("--max-streams-per-connection must be at least 1".into());
        }
        Ok(ServeOptions {
            app: AppOptions { cors_origins, auth },
            conn: ConnLimits {
                header_read_timeout: secs(
                    "header-read-timeout-secs",
                    self.header_read_timeout_secs,
                )?,
                body_timeout: secs("body-timeout-secs", self.body_timeout_secs)?,
                body_min_rate: self.body_min_rate_kib.saturating_mul(1024),
                idle_timeout: secs("idle-timeout-secs", self.idle_timeout_secs)?,
                keepalive_interval: secs("keepalive-interval-secs", self.keepalive_interval_secs)?,
                max_connections: self.max_connections,
                max_requests_per_connection: self.max_requests_per_connection,
                max_streams_per_connection: self.max_streams_per_connection,
                write_timeout: secs("write-timeout-secs", self.write_timeout_secs)?,
                write_min_rate: self.write_min_rate_kib.saturating_mul(1024),
                download_memory: self.download_memory_mib.saturating_mul(1 << 20),
                download_memory_per_connection: self
                    .download_memory_per_connection_mib
                    .saturating_mul(1 << 20),
            },
        })
    }
}

impl ServeArgs {
    /// The NATS options, when `--backend` names a NATS server.
    pub fn nats(&self) -> Result<Option<crate::jobs::nats::NatsOptions>, String> {
        if self.backend == "embedded" {
            return Ok(None);
        }
        if !self.backend.starts_with("nats://") {
            return Err(format!(
                "--backend must be `embedded` or `nats://HOST:PORT`, got `{}`",
                self.backend
            ));
        }
        if !(self.nats_ack_wait_secs.is_finite() && self.nats_ack_wait_secs >= 1.0) {
            return Err("--nats-ack-wait-secs must be at least 1".into());
        }
        let mut o = crate::jobs::nats::NatsOptions::new(&self.backend);
        o.ack_wait = Duration::from_secs_f64(self.nats_ack_wait_secs);
        Ok(Some(o))
    }
}

impl ServeArgs {
    /// The job core's configuration these flags describe.
    pub fn config(&self) -> Result<Config, String> {
        let mut c = Config::new(&self.data_dir);
        if let Some(w) = self.workers {
            // Curve requests get as many blocking slots as jobs get workers (see jobs::curve).
            c.workers = w;
            c.curve_slots = w;
        }
        c.queue_capacity = self.queue_capacity;
        c.limits.max_upload_bytes = self.max_upload_mib.saturating_mul(1 << 20);
        c.limits.max_steps = self.max_steps;
        if !(self.result_ttl_hours.is_finite() && self.result_ttl_hours > 0.0) {
            return Err("--result-ttl-hours must be a positive number".into());
        }
        c.result_ttl = Duration::from_secs_f64(self.result_ttl_hours * 3600.0);
        if self.checkpoint_steps == 0 {
            return Err("--checkpoint-steps must be at least 1".into());
        }
        c.checkpoint_steps = self.checkpoint_steps;
        if !(self.checkpoint_secs.is_finite() && self.checkpoint_secs > 0.0) {
            return Err("--checkpoint-secs must be a positive number".into());
        }
        c.checkpoint_interval = Duration::from_secs_f64(self.checkpoint_secs);
        if self.max_deliveries == 0 {
            return Err("--max-deliveries must be at least 1".into());
        }
        c.max_deliveries = self.max_deliveries;
        c.allow_insecure_callbacks = self.allow_insecure_callbacks;
        if let Some(path) = &self.webhook_secret_file {
            let text = std::fs::read(path)
                .map_err(|e| format!("--webhook-secret-file {}: {e}", path.display()))?;
            let secret = text.trim_ascii();
            if secret.len() < 16 {
                return Err(format!(
                    "--webhook-secret-file {}: the secret must be at least 16 bytes",
                    path.display()
                ));
            }
            c.webhook_secret = Some(secret.to_vec());
        }
        if self.webhook_max_attempts == 0 {
            return Err("--webhook-max-attempts must be at least 1".into());
        }
        c.webhook_max_attempts = self.webhook_max_attempts;
        c.quotas = crate::jobs::TenantQuotas {
            server_max_stored_bytes: self.disk_budget_mib.saturating_mul(1 << 20),
            max_live_jobs: self.tenant_max_live_jobs,
            max_stored_bytes: self.tenant_max_stored_mib.saturating_mul(1 << 20),
            uploads_per_minute: self.tenant_uploads_per_minute,
        };
        c.role = crate::jobs::Role::parse(&self.role).ok_or_else(|| {
            format!(
                "--role must be `api`, `worker` or `all`, got `{}`",
                self.role
            )
        })?;
        if self.backend == "embedded" && c.role != crate::jobs::Role::All {
            return Err(
                "--role api|worker needs a shared backend (--backend nats://…): the embedded \
                 queue lives in one process"
                    .into(),
            );
        }
        if self.nats_ack_wait_secs.is_finite() && self.nats_ack_wait_secs >= 1.0 {
            // Heartbeats well inside the ack wait: a third leaves room for a lost one.
            c.heartbeat_interval = Duration::from_secs_f64(self.nats_ack_wait_secs / 3.0);
        }
        Ok(c)
    }
}

/// The whole application router for `jobs`, assembled here and nowhere else: REST + probes +
/// docs + the web page, with the gRPC services merged in, all behind `options.auth`.
/// `streams_stop` ends open SSE streams (for shutdown).
pub fn app(jobs: Jobs, streams_stop: CancellationToken, options: &AppOptions) -> Router {
    let auth = &options.auth;
    let limit = jobs.config().limits.max_upload_bytes;
    // Both limits must be raised together: axum's DefaultBodyLimit (2 MB by default) applies to
    // its extractors, tower-http's to the raw body stream. Same number, plus multipart slack.
    let body_limit = usize::try_from(limit.saturating_add(MULTIPART_SLACK)).unwrap_or(usize::MAX);
    // An allow-list: a listed origin is echoed (with `Vary: Origin`), any other gets no
    // `Access-Control-Allow-Origin`. With none listed there is no CORS layer at all.
    let cors = CorsLayer::new()
        .allow_origin(AllowOrigin::list(options.cors_origins.iter().cloned()))
        .allow_methods([Method::GET, Method::POST, Method::DELETE, Method::OPTIONS])
        .allow_headers([
            header::CONTENT_TYPE,
            header::AUTHORIZATION,
            HeaderName::from_static("idempotency-key"),
            HeaderName::from_static("last-event-id"),
            REQUEST_ID,
        ])
        // Without this a browser cannot read the 202's Location or a 429's Retry-After.
        .expose_headers([
            header::LOCATION,
            header::RETRY_AFTER,
            header::CONTENT_DISPOSITION,
            REQUEST_ID,
        ]);
    let state = AppState {
        jobs: jobs.clone(),
        streams_stop,
    };
    let rest = http::routes(state.clone())
        .merge(super::web::routes(state))
        .merge(super::auth::routes(jobs.clone(), auth.clone()))
        // The raw stream's safety net sits the drain's length above the handlers' own bound: the
        // mesh and curve handlers refuse a body past that bound themselves and read on up to
        // `DRAIN_MAX_BYTES` before their 413 (so a client still sending reads it); a net at the
        // bound itself would cut that drain short with a stream error.
        .layer(RequestBodyLimitLayer::new(
            body_limit.saturating_add(http::DRAIN_MAX_BYTES),
        ))
        .layer(DefaultBodyLimit::max(body_limit))
        // Outside the body limits: a coded body is refused whatever its length.
        .layer(axum::middleware::from_fn(http::refuse_content_encoding));
    let rest = if options.cors_origins.is_empty() {
        rest
    } else {
        rest.layer(cors)
    };

    // gRPC: the other transport, merged on the same port (its paths are /pkg.Service/Method,
    // so nothing collides). Its limits live on the generated services, not on these layers.
    // The merged router's fallback answers both worlds: tonic's own fallback would give every
    // unknown *HTTP* path a 200 with a grpc-status header.
    let app = rest
        .merge(super::grpc::routes(jobs.clone()))
        .fallback(http::no_route);
    // Outside the body limit: a Content-Length over it is refused by that layer itself, before
    // any inner layer runs, and that plain-text 413 must become a problem too. And outside the
    // whole router: axum sets a 405's `Allow` header after every layer `Router::layer` adds
    // (those wrap each route's handlers), so only a router around this one sees it.
    let app = Router::new()
        .fallback_service(app)
        .layer(axum::middleware::from_fn_with_state(
            limit.saturating_add(MULTIPART_SLACK),
            http::problem_for_plain_413,
        ));
    // Authentication: one layer for REST, SSE and gRPC alike, inside the request span (so a
    // refusal is logged with its request id) and outside everything else.
    let app = auth.wrap(app);
    // Outside authentication: a head over the limits is refused whoever sends it, and inside
    // the request span and id, so the refusal is logged and carries its `X-Request-Id`.
    let app = app.layer(axum::middleware::from_fn(http::refuse_oversized_head));

    app.layer(
        TraceLayer::new_for_http().make_span_with(|req: &Request<_>| {
            let request_id = req
                .headers()
                .get(REQUEST_ID)
                .and_then(|v| v.to_str().ok())
                .unwrap_or("");
            tracing::info_span!(
                "request",
                method = %req.method(),
                path = %req.uri().path(),
                request_id = %request_id,
                job_id = tracing::field::Empty,
                tenant = tracing::field::Empty,
            )
        }),
    )
    .layer(PropagateRequestIdLayer::new(REQUEST_ID))
    .layer(SetRequestIdLayer::new(REQUEST_ID, MakeRequestUuid))
    // Outermost: a client's id that is not a plausible id is dropped before the layer above
    // would keep it, so it is replaced by a fresh one instead of being echoed and logged.
    .layer(axum::middleware::map_request(drop_implausible_request_id))
}

/// Longest client-chosen `X-Request-Id` kept (a UUID is 36; a trace id with a prefix fits).
pub const MAX_REQUEST_ID_LEN: usize = 128;

/// Removes an `X-Request-Id` longer than [`MAX_REQUEST_ID_LEN`] or with characters outside
/// `A-Za-z0-9-_.:/+=`: every response and log line carries the id, so a client must not be
/// able to make either large or to inject text into them.
async fn drop_implausible_request_id(
    mut req: Request<axum::body::Body>,
) -> Request<axum::body::Body> {
    let plausible = |v: &axum::http::HeaderValue| {
        let b = v.as_bytes();
        !b.is_empty()
            && b.len() <= MAX_REQUEST_ID_LEN
            && b.iter()
                .all(|c| c.is_ascii_alphanumeric() || b"-_.:/+=".contains(c))
    };
    let all_plausible = req.headers().get_all(REQUEST_ID).iter().all(plausible);
    if !all_plausible || req.headers().get_all(REQUEST_ID).iter().count() > 1 {
        req.headers_mut().remove(REQUEST_ID);
    }
    req
}

/// Serve `jobs` on `listener` until `shutdown` resolves; then drain the job core for `grace`
/// (running jobs finish or are re-queued), end SSE streams and stop the HTTP server.
/// Default [`ServeOptions`] (no authentication, no CORS grants); see [`serve_with`].
pub async fn serve(
    listener: tokio::net::TcpListener,
    jobs: Jobs,
    core: Shutdown,
    shutdown: impl Future<Output = ()> + Send + 'static,
    grace: Duration,
) -> std::io::Result<()> {
    serve_with(
        listener,
        jobs,
        core,
        shutdown,
        grace,
        ServeOptions::default(),
    )
    .await
}

/// [`serve`] with authentication, CORS origins and connection limits (see [`super::conn`]).
pub async fn serve_with(
    listener: tokio::net::TcpListener,
    jobs: Jobs,
    core: Shutdown,
    shutdown: impl Future<Output = ()> + Send + 'static,
    grace: Duration,
    options: ServeOptions,
) -> std::io::Result<()> {
    let streams_stop = CancellationToken::new();
    let auth = options.app.auth.clone();
    let app = if jobs.config().role.serves_api() {
        app(jobs.clone(), streams_stop.clone(), &options.app)
    } else {
        // A worker serves probes and metrics only; --protect-metrics still applies.
        auth.wrap(http::probe_routes(AppState {
            jobs: jobs.clone(),
            streams_stop: streams_stop.clone(),
        }))
    };
    let http_stop = CancellationToken::new();
    // The accept loop sets TCP_NODELAY and closes connections gracefully on `http_stop`.
    let server = tokio::spawn(super::conn::serve(
        listener,
        app,
        options.conn,
        http_stop.clone(),
    ));
    shutdown.await;
    tracing::info!("shutdown requested: draining");
    // Readiness turns false and submissions get 503 while the jobs drain; status, events and
    // downloads keep working so clients see their jobs finish.
    jobs.begin_drain();
    core.shutdown(grace).await;
    streams_stop.cancel();
    http_stop.cancel();
    match tokio::time::timeout(HTTP_DRAIN, server).await {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => Err(std::io::Error::other(e)),
        Err(_) => {
            tracing::warn!("HTTP connections still open after the drain period; exiting");
            Ok(())
        }
    }
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if tokio::signal::ctrl_c().await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
}

/// Install the tracing subscriber: JSON lines (or text) filtered by `RUST_LOG` (default
/// `info`). A second call (tests) is a no-op.
pub fn init_logging(format: &str) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt().with_env_filter(filter);
    let _ = if format == "text" {
        builder.try_init()
    } else {
        builder
            .json()
            .with_current_span(true)
            .with_span_list(false)
            .try_init()
    };
}

/// `willow serve`: run until SIGTERM/Ctrl-C.
pub fn run(args: ServeArgs) -> Result<(), Box<dyn std::error::Error>> {
    init_logging(&args.log_format);
    let config = args.config()?;
    // Before anything starts: bad flags, a non-loopback address without auth, a bad key file.
    let options = args.serve_options()?;
    let auth = options.app.auth.clone();
    let grace = Duration::from_secs_f64(args.grace_secs.max(0.0));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    rt.block_on(async move {
        let (jobs, core) = match args.nats()? {
            None => Jobs::start(config.clone()).await?,
            Some(options) => {
                let backend = crate::jobs::nats::connect(&config, &options).await?;
                Jobs::start_with(config.clone(), backend).await?
            }
        };
        auth.spawn_reloader();
        let listener = tokio::net::TcpListener::bind(args.addr).await?;
        let local = listener.local_addr()?;
        tracing::info!(
            addr = %local,
            data_dir = %config.data_dir.display(),
            backend = %jobs.backend_name(),
            role = ?config.role,
            workers = config.workers,
            queue_capacity = config.queue_capacity,
            auth = %args.auth.auth,
            "willow serving HTTP/1.1, h2c and gRPC"
        );
        // One line on stdout for scripts (and the tests) that start us on port 0.
        println!("listening on http://{local}");
        serve_with(listener, jobs, core, shutdown_signal(), grace, options).await?;
        Ok::<(), Box<dyn std::error::Error>>(())
    })
}
