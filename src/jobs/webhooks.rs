//! Webhooks: a job's end POSTed to its `callback_url`, signed as Standard Webhooks
//! (<https://www.standardwebhooks.com/>), retried with backoff until a receiver answers 2xx.
//!
//! - **Events**: `job.succeeded`, `job.failed`, `job.cancelled`. The body is
//!   `{"type", "timestamp", "data"}`, `data` the job's id, state, progress and outcome (see
//!   [`event_body`]).
//! - **Headers**: `webhook-id` (`msg_<job id>`: the same on every try and every node, so a
//!   receiver drops repeats by it), `webhook-timestamp` (unix seconds of this try) and
//!   `webhook-signature: v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">`.
//! - **Keys**: one per tenant, HMAC-SHA256(server secret, tenant id) ([`tenant_key`]): the
//!   operator hands each tenant its key (the raw 32 bytes, e.g. base64) and a tenant can check
//!   no other tenant's signatures; the server keeps one secret (`--webhook-secret-file`).
//! - **At least once, across restarts**: the job's record keeps a pending mark
//!   ([`JobStore::pending_callbacks`](super::ports::JobStore::pending_callbacks)) until a
//!   delivery is answered 2xx or given up after [`Config::webhook_max_attempts`] tries. The
//!   loop reads the pending jobs at start, whenever a job ends on this node and every
//!   [`POLL`], so a job that ended while the process was down, or on another node, is sent
//!   too. Tries back off 1 s, 2 s, 4 s, … up to [`MAX_BACKOFF`]; a restart starts the count
//!   again. The loop stops when draining begins (with the workers' polling): a job that ends
//!   in the grace period is delivered after the next start.
//! - **Addresses**: `https` only, and a host that resolves to public unicast addresses only
//!   ([`refusal`]: the IANA special-purpose ranges are refused, 198.18/15 and 2001:db8::/32
//!   among them, and an IPv6 address that embeds an IPv4 one, `::ffff:127.0.0.1`,
//!   `64:ff9b::7f00:1`, `2002:7f00:1::`, is judged by the IPv4 address inside). Checked at
//!   submission, [`check_callback`], and again at each delivery (an IP literal in
//!   [`deliver_once`], a name by the connector's resolver, so DNS that changes after
//!   submission cannot point the server at its own network), unless
//!   [`Config::allow_insecure_callbacks`].
//!
//! Nothing here knows a transport; the HTTP client is hyper-util's over rustls.

use super::{now_ms, rfc3339, Config, JobError, JobState, JobStatus, Jobs};
use base64::Engine as _;
use bytes::Bytes;
use http_body_util::Full;
use hyper::Uri;
use std::collections::{HashMap, HashSet};
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;
use tokio_util::sync::CancellationToken;

/// How often the pending callbacks are read even when no job ended on this node.
pub const POLL: Duration = Duration::from_secs(2);
/// The longest wait between two tries of one delivery.
pub const MAX_BACKOFF: Duration = Duration::from_secs(300);
/// The first retry's wait; each later one doubles it.
pub const FIRST_BACKOFF: Duration = Duration::from_secs(1);
/// How long one try may take, connection included.
const TRY_TIMEOUT: Duration = Duration::from_secs(10);
/// Pending callbacks read at once.
const BATCH: usize = 256;
/// Longest accepted `callback_url`.
const MAX_URL_LEN: usize = 2048;

/// The form of a callback URL: absolute `http` or `https`, a host, no user info, at most
/// 2048 characters. The scheme and address policy is [`check_callback`]'s.
pub fn parse_callback(url: &str) -> Result<Uri, String> {
    if url.len() > MAX_URL_LEN {
        return Err(format!("must be at most {MAX_URL_LEN} characters"));
    }
    let uri: Uri = url
        .parse()
        .map_err(|e| format!("is not a URL ({e}), got {:?}", short(url)))?;
    match uri.scheme_str() {
        Some("https") | Some("http") => {}
        _ => return Err(format!("must be an https URL, got {:?}", short(url))),
    }
    let Some(authority) = uri.authority() else {
        return Err(format!("must name a host, got {:?}", short(url)));
    };
    if authority.as_str().contains('@') {
        return Err("must not carry user info (user:password@)".into());
    }
    if authority.host().is_empty() {
        return Err(format!("must name a host, got {:?}", short(url)));
    }
    Ok(uri)
}

fn short(s: &str) -> String {
    s.chars().take(100).collect()
}

/// Why a callback may not reach `ip` without [`Config::allow_insecure_callbacks`], if it may
/// not: the special-purpose range it falls in (IANA's IPv4 and IPv6 special-purpose address
/// registries, the ranges that are not globally reachable unicast), or, for an IPv6 address
/// that carries an IPv4 address inside it, that IPv4 address's range.
///
/// IPv6 forms that embed an IPv4 address are judged by the IPv4 address inside: a packet to
/// `::ffff:127.0.0.1` is a packet to 127.0.0.1 on a dual-stack host, `64:ff9b::7f00:1` is
/// 127.0.0.1 behind any NAT64 gateway on the path, and `2002:7f00:1::` is 6to4's relay for
/// 127.0.0.1. Teredo (`2001::/32`) is refused outright: its client address is obfuscated
/// and its server address is a relay's, and no callback receiver needs it.
///
/// Outside those forms only the global unicast space `2000::/3` is accepted (every public
/// IPv6 address today; IANA has allocated nothing else), which refuses `::/128`, `::1`,
/// `fc00::/7`, `fe80::/10`, `ff00::/8`, `100::/64` and the reserved space by construction;
/// the special ranges inside `2000::/3` are listed.
pub fn refusal(ip: IpAddr) -> Option<Refusal> {
    match ip {
        IpAddr::V4(v4) => v4_range(v4).map(|range| Refusal {
            ip,
            inside: None,
            range,
        }),
        IpAddr::V6(v6) => {
            if let Some((form, v4)) = embedded_v4(v6) {
                return v4_range(v4).map(|range| Refusal {
                    ip,
                    inside: Some((form, v4)),
                    range,
                });
            }
            v6_range(v6).map(|range| Refusal {
                ip,
                inside: None,
                range,
            })
        }
    }
}

/// Whether `ip` is an address a callback may reach without
/// [`Config::allow_insecure_callbacks`]: see [`refusal`].
pub fn is_public(ip: IpAddr) -> bool {
    refusal(ip).is_none()
}

/// A special-purpose range: its prefix and what it is for, as IANA's registries name them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SpecialRange {
    pub prefix: &'static str,
    pub name: &'static str,
}

/// Why an address is refused (see [`refusal`]); its `Display` is the sentence clients read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Refusal {
    /// The address refused.
    pub ip: IpAddr,
    /// The IPv6 form and the IPv4 address it embeds, when that IPv4 address was judged.
    pub inside: Option<(&'static str, std::net::Ipv4Addr)>,
    /// The range it falls in.
    pub range: SpecialRange,
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let SpecialRange { prefix, name } = self.range;
        match self.inside {
            Some((form, v4)) => write!(
                f,
                "{} ({form}) embeds {v4}, which is in {prefix} ({name})",
                self.ip
            ),
            None => write!(f, "{} is in {prefix} ({name})", self.ip),
        }
    }
}

const fn range(prefix: &'static str, name: &'static str) -> SpecialRange {
    SpecialRange { prefix, name }
}

/// The IPv4 special-purpose range `v4` is in, among those a callback may not reach: IANA's
/// registry entries that are not globally reachable, plus multicast and the reserved 240/4.
/// (192.0.0.9 and .10, globally reachable anycast, are refused with the rest of 192.0.0/24:
/// no webhook receiver lives there.)
fn v4_range(v4: std::net::Ipv4Addr) -> Option<SpecialRange> {
    let bits = u32::from(v4);
    const RANGES: [(u32, u32, SpecialRange); 16] = [
        (0x0000_0000, 8, range("0.0.0.0/8", "this network")),
        (0x0a00_0000, 8, range("10.0.0.0/8", "private")),
        (
            0x6440_0000,
            10,
            range("100.64.0.0/10", "shared address space"),
        ),
        (0x7f00_0000, 8, range("127.0.0.0/8", "loopback")),
        (0xa9fe_0000, 16, range("169.254.0.0/16", "link-local")),
        (0xac10_0000, 12, range("172.16.0.0/12", "private")),
        (
            0xc000_0000,
            24,
            range("192.0.0.0/24", "IETF protocol assignments"),
        ),
        (0xc000_0200, 24, range("192.0.2.0/24", "documentation")),
        (
            0xc058_6300,
            24,
            range("192.88.99.0/24", "6to4 relay anycast"),
        ),
        (0xc0a8_0000, 16, range("192.168.0.0/16", "private")),
        (0xc612_0000, 15, range("198.18.0.0/15", "benchmarking")),
        (0xc633_6400, 24, range("198.51.100.0/24", "documentation")),
        (0xcb00_7100, 24, range("203.0.113.0/24", "documentation")),
        (0xe000_0000, 4, range("224.0.0.0/4", "multicast")),
        (
            0xffff_ffff,
            32,
            range("255.255.255.255/32", "limited broadcast"),
        ),
        (0xf000_0000, 4, range("240.0.0.0/4", "reserved")),
    ];
    RANGES
        .iter()
        .find(|(net, len, _)| bits >> (32 - len) == net >> (32 - len))
        .map(|(_, _, r)| *r)
}

/// The IPv6 special-purpose range `v6` is in, among those a callback may not reach (the
/// embedded-IPv4 forms are [`embedded_v4`]'s).
fn v6_range(v6: std::net::Ipv6Addr) -> Option<SpecialRange> {
    let bits = u128::from(v6);
    let within = |net: u128, len: u32| bits >> (128 - len) == net >> (128 - len);
    const NAMED: [(u128, u32, SpecialRange); 12] = [
        (0, 128, range("::/128", "unspecified")),
        (1, 128, range("::1/128", "loopback")),
        (0x0100 << 112, 64, range("100::/64", "discard-only")),
        (
            0x0064_ff9b_0001 << 80,
            48,
            range("64:ff9b:1::/48", "local-use IPv4/IPv6 translation"),
        ),
        (0xfc00 << 112, 7, range("fc00::/7", "unique local")),
        (0xfe80 << 112, 10, range("fe80::/10", "link-local")),
        (
            0xfec0 << 112,
            10,
            range("fec0::/10", "site-local (deprecated)"),
        ),
        (0xff00 << 112, 8, range("ff00::/8", "multicast")),
        (0x2001_0000 << 96, 32, range("2001::/32", "Teredo")),
        (0x2001_0002 << 96, 48, range("2001:2::/48", "benchmarking")),
        (
            0x2001_0db8 << 96,
            32,
            range("2001:db8::/32", "documentation"),
        ),
        (0x3fff << 112, 20, range("3fff::/20", "documentation")),
    ];
    const ORCHID: [(u128, u32, SpecialRange); 2] = [
        (
            0x2001_0010 << 96,
            28,
            range("2001:10::/28", "ORCHID (deprecated)"),
        ),
        (0x2001_0020 << 96, 28, range("2001:20::/28", "ORCHIDv2")),
    ];
    if let Some((_, _, r)) = NAMED.iter().chain(&ORCHID).find(|(n, l, _)| within(*n, *l)) {
        return Some(*r);
    }
    (!within(0x2000 << 112, 3)).then_some(range("outside 2000::/3", "not global unicast"))
}

/// The IPv4 address an IPv6 address carries, and the form's name: IPv4-mapped
/// (`::ffff:0:0/96`), IPv4-translated (SIIT, `::ffff:0:0:0/96`), IPv4-compatible
/// (`::/96`, deprecated; `::` and `::1` themselves are not), the NAT64 well-known prefix
/// (`64:ff9b::/96`) and 6to4 (`2002::/16`, the IPv4 address in bits 16 to 48).
fn embedded_v4(v6: std::net::Ipv6Addr) -> Option<(&'static str, std::net::Ipv4Addr)> {
    let bits = u128::from(v6);
    let low32 = std::net::Ipv4Addr::from(bits as u32);
    let high96 = bits >> 32;
    match high96 {
        0xffff => Some(("IPv4-mapped", low32)),
        0xffff_0000 => Some(("IPv4-translated", low32)),
        0 if bits > 1 => Some(("IPv4-compatible", low32)),
        0x0064_ff9b_0000_0000_0000_0000 => Some(("NAT64", low32)),
        _ if bits >> 112 == 0x2002 => Some(("6to4", std::net::Ipv4Addr::from((bits >> 80) as u32))),
        _ => None,
    }
}

/// The host of `uri` without IPv6 brackets, and its port (the scheme's by default).
fn host_port(uri: &Uri) -> Option<(String, u16)> {
    let host = uri.host()?.trim_start_matches('[').trim_end_matches(']');
    let port = uri
        .port_u16()
        .unwrap_or(if uri.scheme_str() == Some("http") {
            80
        } else {
            443
        });
    Some((host.to_string(), port))
}

/// The policy of a job's `callback_url` on this server, at submission: `https` unless
/// insecure callbacks are allowed, and a host that resolves, to public addresses only unless
/// allowed. Errors name the field `callback_url`.
pub async fn check_callback(url: &str, config: &Config) -> Result<(), JobError> {
    let bad = |reason: String| JobError::InvalidSpec {
        field: "callback_url",
        reason,
    };
    let uri = parse_callback(url).map_err(bad)?;
    if config.allow_insecure_callbacks {
        return Ok(());
    }
    if uri.scheme_str() != Some("https") {
        return Err(bad(format!(
            "must be an https URL (http only on a server run with --allow-insecure-callbacks), got {:?}",
            short(url)
        )));
    }
    let (host, port) = host_port(&uri).ok_or_else(|| bad("must name a host".into()))?;
    // Bounded: a submission must not wait on a slow resolver for long.
    let addrs: Vec<SocketAddr> =
        tokio::time::timeout(TRY_TIMEOUT, tokio::net::lookup_host((host.as_str(), port)))
            .await
            .map_err(|_| {
                bad(format!(
                    "host `{host}` did not resolve within {TRY_TIMEOUT:?}"
                ))
            })?
            .map_err(|e| bad(format!("host `{host}` does not resolve: {e}")))?
            .collect();
    if addrs.is_empty() {
        return Err(bad(format!("host `{host}` resolves to no address")));
    }
    // Every address: the connector may try any of them.
    if let Some(r) = addrs.iter().find_map(|a| refusal(a.ip())) {
        let what = if host.parse::<IpAddr>().is_ok() {
            r.to_string()
        } else {
            format!("host `{host}` resolves to {r}")
        };
        return Err(bad(format!(
            "{what}: a callback may reach public unicast addresses only \
             (others only on a server run with --allow-insecure-callbacks)"
        )));
    }
    Ok(())
}

/// A tenant's signing key: HMAC-SHA256(server secret, tenant id). Derived, so the server
/// keeps one secret and a leaked tenant key reveals neither the secret nor other tenants'.
pub fn tenant_key(server_secret: &[u8], tenant: &str) -> Vec<u8> {
    let k = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, server_secret);
    ring::hmac::sign(&k, tenant.as_bytes()).as_ref().to_vec()
}

/// The `webhook-signature` value of a message: `v1,` and the base64 HMAC-SHA256 of
/// `{id}.{timestamp}.{body}` under `key` (Standard Webhooks, symmetric signatures).
pub fn signature(key: &[u8], id: &str, timestamp: u64, body: &[u8]) -> String {
    let k = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, key);
    let mut ctx = ring::hmac::Context::with_key(&k);
    ctx.update(id.as_bytes());
    ctx.update(format!(".{timestamp}.").as_bytes());
    ctx.update(body);
    format!(
        "v1,{}",
        base64::engine::general_purpose::STANDARD.encode(ctx.sign().as_ref())
    )
}

/// The event type of a terminal state.
pub fn event_type(state: JobState) -> Option<&'static str> {
    match state {
        JobState::Succeeded => Some("job.succeeded"),
        JobState::Failed => Some("job.failed"),
        JobState::Cancelled => Some("job.cancelled"),
        JobState::Queued | JobState::Running => None,
    }
}

/// The `webhook-id` of a job's end: stable, so every try and every node send the same.
pub fn message_id(job: &JobStatus) -> String {
    format!("msg_{}", job.id.as_str())
}

/// The JSON body of a job's end event.
pub fn event_body(job: &JobStatus) -> Vec<u8> {
    let (outcome, reason) = job.outcome().unzip();
    let body = serde_json::json!({
        "type": event_type(job.state),
        "timestamp": rfc3339(job.finished_at.unwrap_or_else(now_ms)),
        "data": {
            "id": job.id.as_str(),
            "tenant": job.tenant,
            "state": job.state.as_str(),
            "step": job.step,
            "total_steps": job.total_steps,
            "percent_complete": job.percent_complete(),
            "outcome": outcome,
            "outcome_reason": reason,
            "error_code": if job.state == JobState::Succeeded { None } else { job.error_code.clone() },
            "error": if job.state == JobState::Succeeded { None } else { job.error.clone() },
            "created_at": rfc3339(job.created_at),
            "finished_at": job.finished_at.map(rfc3339),
        }
    });
    serde_json::to_vec(&body).unwrap_or_default()
}

/// The longest wait between two reads of the pending callbacks while the store cannot be
/// read (a NATS outage): a read that fails waits out its own timeout first, and a node that
/// read every [`POLL`] through a long outage logged a timeout every few seconds (issue 25).
pub const SCAN_MAX_BACKOFF: Duration = Duration::from_secs(30);

/// Whether the pending callbacks could be read lately: reads that fail back off from
/// [`POLL`] to [`SCAN_MAX_BACKOFF`], and an outage is logged twice, when it begins and when
/// it ends, not once per read.
#[derive(Debug, Default)]
pub struct ScanHealth {
    /// Reads failed in a row.
    failures: u32,
}

impl ScanHealth {
    /// A read failed: whether to log it (the first failure of an outage) and how long to
    /// wait before the next read (doubling from [`POLL`], capped at [`SCAN_MAX_BACKOFF`]).
    pub fn failed(&mut self) -> (bool, Duration) {
        self.failures = self.failures.saturating_add(1);
        let wait = POLL
            .saturating_mul(1u32 << (self.failures - 1).min(16))
            .min(SCAN_MAX_BACKOFF);
        (self.failures == 1, wait)
    }

    /// A read succeeded: the failures of the outage it ends (`Some`, to log once), if any.
    pub fn succeeded(&mut self) -> Option<u32> {
        let failures = std::mem::take(&mut self.failures);
        (failures > 0).then_some(failures)
    }
}

/// The wait before try `attempt + 1` (after `attempt` failed tries): 1 s, 2 s, 4 s, … up to
/// [`MAX_BACKOFF`].
pub fn backoff(attempt: u32) -> Duration {
    FIRST_BACKOFF
        .saturating_mul(1u32 << attempt.saturating_sub(1).min(20))
        .min(MAX_BACKOFF)
}

/// A resolver that drops non-public addresses (unless allowed): the submission check again at
/// connection time, against DNS that changed since.
#[derive(Clone)]
struct PublicResolver {
    allow_private: bool,
}

impl tower::Service<hyper_util::client::legacy::connect::dns::Name> for PublicResolver {
    type Response = std::vec::IntoIter<SocketAddr>;
    type Error = std::io::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Self::Error>> + Send>>;

    fn poll_ready(&mut self, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, name: hyper_util::client::legacy::connect::dns::Name) -> Self::Future {
        let allow = self.allow_private;
        Box::pin(async move {
            let (addrs, refused): (Vec<SocketAddr>, Vec<SocketAddr>) =
                tokio::net::lookup_host((name.as_str(), 0))
                    .await?
                    .partition(|a| allow || is_public(a.ip()));
            if addrs.is_empty() {
                let why = refused
                    .first()
                    .and_then(|a| refusal(a.ip()))
                    .map(|r| format!(" ({r})"))
                    .unwrap_or_default();
                return Err(std::io::Error::other(format!(
                    "`{}` resolves to no public address{why}",
                    name.as_str()
                )));
            }
            Ok(addrs.into_iter())
        })
    }
}

type Client = hyper_util::client::legacy::Client<
    hyper_rustls::HttpsConnector<
        hyper_util::client::legacy::connect::HttpConnector<PublicResolver>,
    >,
    Full<Bytes>,
>;

fn client(allow_insecure: bool) -> Result<Client, JobError> {
    let mut http =
        hyper_util::client::legacy::connect::HttpConnector::new_with_resolver(PublicResolver {
            allow_private: allow_insecure,
        });
    http.enforce_http(false);
    http.set_connect_timeout(Some(TRY_TIMEOUT));
    let builder = hyper_rustls::HttpsConnectorBuilder::new()
        .with_provider_and_native_roots(Arc::new(rustls::crypto::ring::default_provider()))
        .map_err(|e| JobError::Internal(format!("webhook TLS roots: {e}")))?;
    let https = if allow_insecure {
        builder.https_or_http()
    } else {
        builder.https_only()
    }
    .enable_http1()
    .wrap_connector(http);
    Ok(
        hyper_util::client::legacy::Client::builder(hyper_util::rt::TokioExecutor::new())
            .build(https),
    )
}

/// One try: `Ok` on a 2xx answer, else why not. An IP literal is judged here (the resolver
/// sees only names).
async fn deliver_once(
    client: &Client,
    config: &Config,
    key: &[u8],
    job: &JobStatus,
) -> Result<(), String> {
    let url = job.spec.callback_url.as_deref().ok_or("no callback_url")?;
    let uri = parse_callback(url)?;
    if !config.allow_insecure_callbacks {
        if uri.scheme_str() != Some("https") {
            return Err("not https".into());
        }
        if let Some(ip) = host_port(&uri).and_then(|(h, _)| h.parse::<IpAddr>().ok()) {
            if let Some(r) = refusal(ip) {
                return Err(format!("{r}: not a public address"));
            }
        }
    }
    let body = event_body(job);
    let id = message_id(job);
    let timestamp = now_ms() / 1000;
    let request = hyper::Request::post(uri)
        .header("content-type", "application/json")
        .header("user-agent", "willow-webhooks/1")
        .header("webhook-id", &id)
        .header("webhook-timestamp", timestamp.to_string())
        .header("webhook-signature", signature(key, &id, timestamp, &body))
        .body(Full::new(Bytes::from(body)))
        .map_err(|e| e.to_string())?;
    let response = tokio::time::timeout(TRY_TIMEOUT, client.request(request))
        .await
        .map_err(|_| format!("no answer within {TRY_TIMEOUT:?}"))?
        .map_err(|e| format!("{e:?}"))?;
    let status = response.status();
    if status.is_success() {
        Ok(())
    } else {
        Err(format!("answered {status}"))
    }
}

/// The server secret when none is configured: random per process (see
/// [`Config::webhook_secret`]).
fn process_secret() -> Vec<u8> {
    use ring::rand::SecureRandom as _;
    let mut s = vec![0u8; 32];
    // The system RNG does not fail on the platforms we run on; a zero secret would still
    // sign, only predictably, so say so.
    if ring::rand::SystemRandom::new().fill(&mut s).is_err() {
        tracing::error!("system RNG failed: webhook signatures use a fixed secret");
    }
    s
}

/// What the loop knows of one pending delivery between polls.
struct Attempts {
    tries: u32,
    next_at: tokio::time::Instant,
}

/// Deliver every pending callback until `stop`: read the pending jobs, try each that is due
/// (each try on a task of its own, one at a time per job), mark it settled on 2xx or after
/// the last try, and wait for a job to end ([`Jobs::callbacks_due`]) or [`POLL`].
pub(crate) async fn delivery_loop(jobs: Jobs, stop: CancellationToken) {
    let config = jobs.config().clone();
    let client = match client(config.allow_insecure_callbacks) {
        Ok(c) => c,
        Err(e) => {
            tracing::error!(error = %e, "webhooks disabled: no HTTP client");
            return;
        }
    };
    let secret = config.webhook_secret.clone().unwrap_or_else(process_secret);
    let attempts: Arc<Mutex<HashMap<String, Attempts>>> = Default::default();
    let in_flight: Arc<Mutex<HashSet<String>>> = Default::default();
    let due = jobs.inner.callbacks_due.clone();
    let mut health = ScanHealth::default();
    loop {
        let mut scan_wait = POLL;
        let pending = match jobs.inner.backend.store.pending_callbacks(BATCH).await {
            Ok(p) => {
                if let Some(failures) = health.succeeded() {
                    tracing::info!(failed_reads = failures, "pending webhooks readable again");
                }
                p
            }
            Err(e) => {
                let (log, wait) = health.failed();
                if log {
                    tracing::warn!(error = %e, "reading pending webhooks failed: reading again with backoff, logged again once it recovers");
                } else {
                    tracing::debug!(error = %e, retry_in = ?wait, "reading pending webhooks");
                }
                scan_wait = wait;
                Vec::new()
            }
        };
        if pending.len() < BATCH {
            // Every pending job was read: forget the tries of jobs no longer pending (deleted,
            // expired, or settled by another node).
            let ids: HashSet<&str> = pending.iter().map(|j| j.id.as_str()).collect();
            attempts
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .retain(|id, _| ids.contains(id.as_str()));
        }
        let now = tokio::time::Instant::now();
        let mut next_wake = now + scan_wait;
        for job in pending {
            let id = job.id.as_str().to_string();
            {
                let a = attempts.lock().unwrap_or_else(|p| p.into_inner());
                if let Some(a) = a.get(&id) {
                    if a.next_at > now {
                        next_wake = next_wake.min(a.next_at);
                        continue;
                    }
                }
            }
            if !in_flight
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .insert(id.clone())
            {
                continue;
            }
            let (jobs, client, config) = (jobs.clone(), client.clone(), config.clone());
            let key = tenant_key(&secret, &job.tenant);
            let (attempts, in_flight, due) = (attempts.clone(), in_flight.clone(), due.clone());
            tokio::spawn(async move {
                let result = deliver_once(&client, &config, &key, &job).await;
                let tries = {
                    let mut a = attempts.lock().unwrap_or_else(|p| p.into_inner());
                    let entry = a.entry(id.clone()).or_insert(Attempts {
                        tries: 0,
                        next_at: tokio::time::Instant::now(),
                    });
                    entry.tries += 1;
                    entry.next_at = tokio::time::Instant::now() + backoff(entry.tries);
                    entry.tries
                };
                let settle = match &result {
                    Ok(()) => {
                        tracing::info!(job_id = %id, tries, "webhook delivered");
                        true
                    }
                    Err(e) if tries >= config.webhook_max_attempts => {
                        tracing::warn!(job_id = %id, tries, error = %e, "webhook given up");
                        true
                    }
                    Err(e) => {
                        tracing::info!(job_id = %id, tries, error = %e, retry_in = ?backoff(tries), "webhook failed");
                        false
                    }
                };
                if settle {
                    if let Err(e) = jobs.inner.backend.store.settle_callback(&id).await {
                        tracing::warn!(job_id = %id, error = %e, "marking a webhook settled");
                    } else {
                        attempts
                            .lock()
                            .unwrap_or_else(|p| p.into_inner())
                            .remove(&id);
                    }
                }
                in_flight
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .remove(&id);
                // The loop sleeps until the earliest retry it knew of: wake it for this one.
                due.notify_one();
            });
        }
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = due.notified() => {}
            _ = tokio::time::sleep_until(next_wake) => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Standard Webhooks specification's own example: secret
    /// `whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw` (base64 after the prefix), id
    /// `msg_p5jXN8AQM9LWM0D4loKWxJek`, timestamp 1614265330, body `{"test": 2432232314}`.
    #[test]
    fn signature_matches_the_specification_example() {
        let key = base64::engine::general_purpose::STANDARD
            .decode("MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw")
            .expect("base64");
        assert_eq!(
            signature(
                &key,
                "msg_p5jXN8AQM9LWM0D4loKWxJek",
                1614265330,
                br#"{"test": 2432232314}"#
            ),
            "v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE="
        );
    }

    #[test]
    fn private_and_loopback_addresses_are_not_public() {
        for ip in [
            "127.0.0.1",
            "10.1.2.3",
            "172.16.0.1",
            "192.168.1.1",
            "169.254.169.254",
            "100.64.0.1",
            "0.0.0.0",
            "::1",
            "fd00::1",
            "fe80::1",
            "::ffff:10.0.0.1",
        ] {
            assert!(!is_public(ip.parse().expect("ip")), "{ip}");
        }
        for ip in ["93.184.216.34", "1.1.1.1", "2606:4700:4700::1111"] {
            assert!(is_public(ip.parse().expect("ip")), "{ip}");
        }
    }

    /// One case per form and range of issue 42 item 4: the address, and the range (and for
    /// IPv6 forms that embed IPv4, the IPv4 address) it is refused for.
    #[test]
    fn each_special_range_and_embedded_form_is_refused_by_name() {
        for (ip, prefix, inside) in [
            // IPv4-compatible, -mapped, -translated (SIIT), NAT64 and 6to4 forms of 127.0.0.1.
            ("::127.0.0.1", "127.0.0.0/8", Some("127.0.0.1")),
            ("::ffff:127.0.0.1", "127.0.0.0/8", Some("127.0.0.1")),
            ("::ffff:0:7f00:1", "127.0.0.0/8", Some("127.0.0.1")),
            ("64:ff9b::7f00:1", "127.0.0.0/8", Some("127.0.0.1")),
            ("2002:7f00:1::", "127.0.0.0/8", Some("127.0.0.1")),
            (
                "2002:a9fe:a9fe::1",
                "169.254.0.0/16",
                Some("169.254.169.254"),
            ),
            ("64:ff9b::c612:1", "198.18.0.0/15", Some("198.18.0.1")),
            ("::ffff:10.0.0.1", "10.0.0.0/8", Some("10.0.0.1")),
            // IPv4.
            ("0.1.2.3", "0.0.0.0/8", None),
            ("10.1.2.3", "10.0.0.0/8", None),
            ("100.64.0.1", "100.64.0.0/10", None),
            ("100.127.255.255", "100.64.0.0/10", None),
            ("127.0.0.1", "127.0.0.0/8", None),
            ("169.254.169.254", "169.254.0.0/16", None),
            ("172.16.0.1", "172.16.0.0/12", None),
            ("172.31.255.255", "172.16.0.0/12", None),
            ("192.0.0.8", "192.0.0.0/24", None),
            ("192.0.2.1", "192.0.2.0/24", None),
            ("192.88.99.1", "192.88.99.0/24", None),
            ("192.168.1.1", "192.168.0.0/16", None),
            ("198.18.0.1", "198.18.0.0/15", None),
            ("198.19.255.255", "198.18.0.0/15", None),
            ("198.51.100.7", "198.51.100.0/24", None),
            ("203.0.113.9", "203.0.113.0/24", None),
            ("224.0.0.1", "224.0.0.0/4", None),
            ("239.255.255.250", "224.0.0.0/4", None),
            ("240.0.0.1", "240.0.0.0/4", None),
            ("255.255.255.255", "255.255.255.255/32", None),
            // IPv6.
            ("::", "::/128", None),
            ("::1", "::1/128", None),
            ("100::1", "100::/64", None),
            ("64:ff9b:1::a00:1", "64:ff9b:1::/48", None),
            ("fc00::1", "fc00::/7", None),
            ("fd12:3456::1", "fc00::/7", None),
            ("fe80::1", "fe80::/10", None),
            ("fec0::1", "fec0::/10", None),
            ("ff02::1", "ff00::/8", None),
            ("2001::1", "2001::/32", None),
            ("2001:2::1", "2001:2::/48", None),
            ("2001:db8::1", "2001:db8::/32", None),
            ("2001:10::1", "2001:10::/28", None),
            ("2001:20::1", "2001:20::/28", None),
            ("3fff::1", "3fff::/20", None),
            ("4000::1", "outside 2000::/3", None),
        ] {
            let addr: IpAddr = ip.parse().expect(ip);
            let r = refusal(addr).unwrap_or_else(|| panic!("{ip} must be refused"));
            assert_eq!(r.range.prefix, prefix, "{ip}: {r}");
            assert_eq!(
                r.inside.map(|(_, v4)| v4.to_string()).as_deref(),
                inside,
                "{ip}"
            );
            assert!(!is_public(addr));
        }
        let r = refusal("::ffff:0:7f00:1".parse().expect("ip")).expect("refused");
        assert_eq!(
            r.to_string(),
            "::ffff:0:7f00:1 (IPv4-translated) embeds 127.0.0.1, which is in 127.0.0.0/8 (loopback)"
        );
        let r = refusal("198.18.0.1".parse().expect("ip")).expect("refused");
        assert_eq!(
            r.to_string(),
            "198.18.0.1 is in 198.18.0.0/15 (benchmarking)"
        );
    }

    /// The neighbours of the refused ranges, and public addresses in every embedded form, pass.
    #[test]
    fn public_addresses_pass_in_every_form() {
        for ip in [
            "1.1.1.1",
            "93.184.216.34",
            "100.63.255.255",
            "100.128.0.0",
            "172.15.255.255",
            "172.32.0.0",
            "192.0.1.1",
            "192.88.98.1",
            "198.17.255.255",
            "198.20.0.0",
            "223.255.255.255",
            "2606:4700:4700::1111",
            "2a00:1450:4001:80b::200e",
            "2001:4:112::1",
            "::ffff:1.1.1.1",
            "::ffff:0:101:101",
            "::1.1.1.1",
            "64:ff9b::101:101",
            "2002:101:101::1",
        ] {
            let addr: IpAddr = ip.parse().expect(ip);
            assert_eq!(refusal(addr), None, "{ip}");
        }
    }

    #[test]
    fn backoff_doubles_from_one_second_to_the_cap() {
        let secs: Vec<u64> = (1..=10).map(|a| backoff(a).as_secs()).collect();
        assert_eq!(secs, [1, 2, 4, 8, 16, 32, 64, 128, 256, 300]);
    }

    /// Through an outage the reads back off 2, 4, 8, 16, 30, 30 s and only the first failure
    /// is logged; the success that ends it reports the count once, and the next outage starts
    /// over from [`POLL`].
    #[test]
    fn the_scan_backs_off_in_an_outage_and_logs_its_start_and_end_once() {
        let mut h = ScanHealth::default();
        assert_eq!(h.succeeded(), None, "no outage, nothing to log");
        let tries: Vec<(bool, u64)> = (0..6)
            .map(|_| h.failed())
            .map(|(log, wait)| (log, wait.as_secs()))
            .collect();
        assert_eq!(
            tries,
            [
                (true, 2),
                (false, 4),
                (false, 8),
                (false, 16),
                (false, 30),
                (false, 30)
            ]
        );
        for _ in 0..100 {
            assert_eq!(h.failed(), (false, SCAN_MAX_BACKOFF));
        }
        assert_eq!(h.succeeded(), Some(106));
        assert_eq!(h.succeeded(), None);
        assert_eq!(h.failed(), (true, POLL));
    }

    #[test]
    fn callback_form_is_checked() {
        assert!(parse_callback("https://example.com/hook").is_ok());
        assert!(parse_callback("http://127.0.0.1:9/x").is_ok());
        for bad in [
            "ftp://example.com/",
            "/relative",
            "https://u:p@example.com/",
            "nonsense",
        ] {
            assert!(parse_callback(bad).is_err(), "{bad}");
        }
    }

    #[tokio::test]
    async fn policy_refuses_http_and_private_hosts_unless_allowed() {
        let mut config = Config::new("/nonexistent");
        for url in [
            "http://example.com/",
            "https://127.0.0.1/",
            "https://[::1]:8443/x",
            "https://localhost/",
            "https://[::127.0.0.1]/",
            "https://[::ffff:0:7f00:1]/",
            "https://[64:ff9b::7f00:1]/",
            "https://[2002:7f00:1::]/",
            "https://198.18.0.1/",
        ] {
            match check_callback(url, &config).await {
                Err(JobError::InvalidSpec { field, .. }) => {
                    assert_eq!(field, "callback_url", "{url}")
                }
                other => panic!("{url}: {other:?}"),
            }
        }
        config.allow_insecure_callbacks = true;
        assert!(check_callback("http://127.0.0.1:9/x", &config)
            .await
            .is_ok());
    }
}
