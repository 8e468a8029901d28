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
//! - **Addresses**: `https` only, and a host that resolves to a public address only (checked
//!   at submission, [`check_callback`], and again at each delivery by the connector's
//!   resolver, so DNS that changes after submission cannot point the server at its own
//!   network), unless [`Config::allow_insecure_callbacks`].
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

/// Whether `ip` is an address a callback may reach without
/// [`Config::allow_insecure_callbacks`]: not loopback, private (RFC 1918, unique local
/// fc00::/7), link-local, shared (100.64/10), unspecified, broadcast, multicast or
/// documentation; IPv4-mapped IPv6 is judged as its IPv4.
pub fn is_public(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => {
            let [a, b, ..] = v4.octets();
            !(v4.is_loopback()
                || v4.is_private()
                || v4.is_link_local()
                || v4.is_unspecified()
                || v4.is_broadcast()
                || v4.is_multicast()
                || v4.is_documentation()
                || a == 0
                || (a == 100 && (64..128).contains(&b))
                || a >= 240)
        }
        IpAddr::V6(v6) => {
            if let Some(v4) = v6.to_ipv4_mapped() {
                return is_public(IpAddr::V4(v4));
            }
            let first = v6.segments()[0];
            !(v6.is_loopback()
                || v6.is_unspecified()
                || v6.is_multicast()
                || (first & 0xfe00) == 0xfc00
                || (first & 0xffc0) == 0xfe80
                || first == 0x2001 && v6.segments()[1] == 0x0db8)
        }
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
    if let Some(a) = addrs.iter().find(|a| !is_public(a.ip())) {
        return Err(bad(format!(
            "host `{host}` resolves to {}, a loopback, private or link-local address",
            a.ip()
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
            let addrs: Vec<SocketAddr> = tokio::net::lookup_host((name.as_str(), 0))
                .await?
                .filter(|a| allow || is_public(a.ip()))
                .collect();
            if addrs.is_empty() {
                return Err(std::io::Error::other(format!(
                    "`{}` resolves to no public address",
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
            if !is_public(ip) {
                return Err(format!("{ip} is not a public address"));
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
