//! A webhook receiver for the tests: an axum server on loopback that checks each delivery's
//! Standard Webhooks signature with its own HMAC-SHA256 and answers as scripted.
#![allow(dead_code)]

use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use base64::Engine as _;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Upper bound on the wait for one delivery.
pub const TIMEOUT: Duration = Duration::from_secs(90);
pub const SECRET: &[u8] = b"a test webhook secret of 32 byte";

/// One request the receiver got, with whether its signature checked out.
#[derive(Debug)]
pub struct Delivery {
    pub id: String,
    pub timestamp: u64,
    pub signature_ok: bool,
    pub body: serde_json::Value,
    pub answered: u16,
}

#[derive(Clone)]
struct Receiver {
    /// Status codes to answer, in order; 200 once empty.
    script: Arc<Mutex<VecDeque<u16>>>,
    got: tokio::sync::mpsc::UnboundedSender<Delivery>,
}

/// The receiver's own check, written from the Standard Webhooks specification: the key is
/// HMAC-SHA256(server secret, tenant) (the server's documented derivation), the signature
/// `v1,` + base64 HMAC-SHA256(key, "{id}.{timestamp}.{body}").
fn expected_signature(tenant: &str, id: &str, timestamp: &str, body: &[u8]) -> String {
    let server = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, SECRET);
    let tenant_key = ring::hmac::sign(&server, tenant.as_bytes());
    let key = ring::hmac::Key::new(ring::hmac::HMAC_SHA256, tenant_key.as_ref());
    let mut signed = format!("{id}.{timestamp}.").into_bytes();
    signed.extend_from_slice(body);
    let tag = ring::hmac::sign(&key, &signed);
    format!(
        "v1,{}",
        base64::engine::general_purpose::STANDARD.encode(tag.as_ref())
    )
}

async fn hook(
    State(r): State<Receiver>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> StatusCode {
    let header = |name: &str| {
        headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string()
    };
    let (id, timestamp) = (header("webhook-id"), header("webhook-timestamp"));
    let json: serde_json::Value = serde_json::from_slice(&body).unwrap_or_default();
    let tenant = json["data"]["tenant"].as_str().unwrap_or("").to_string();
    let expected = expected_signature(&tenant, &id, &timestamp, &body);
    // The header may carry several space-separated signatures; one must match.
    let signature_ok = header("webhook-signature")
        .split(' ')
        .any(|s| s == expected);
    let answered = r
        .script
        .lock()
        .expect("script lock")
        .pop_front()
        .unwrap_or(200);
    let _ = r.got.send(Delivery {
        id,
        timestamp: timestamp.parse().unwrap_or(0),
        signature_ok,
        body: json,
        answered,
    });
    StatusCode::from_u16(answered).unwrap_or(StatusCode::OK)
}

/// Start a receiver answering `script` in order (then 200); its URL and the deliveries.
pub async fn receiver(
    script: &[u16],
) -> (
    String,
    tokio::sync::mpsc::UnboundedReceiver<Delivery>,
    Arc<Mutex<VecDeque<u16>>>,
) {
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let script = Arc::new(Mutex::new(script.iter().copied().collect()));
    let app = axum::Router::new()
        .route("/hook", axum::routing::post(hook))
        .with_state(Receiver {
            script: script.clone(),
            got: tx,
        });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let url = format!("http://{}/hook", listener.local_addr().expect("addr"));
    tokio::spawn(async move { axum::serve(listener, app).await });
    (url, rx, script)
}

pub async fn next(rx: &mut tokio::sync::mpsc::UnboundedReceiver<Delivery>) -> Delivery {
    tokio::time::timeout(TIMEOUT, rx.recv())
        .await
        .expect("a delivery within the timeout")
        .expect("receiver alive")
}

pub fn query_escape(s: &str) -> String {
    form_urlencoded::byte_serialize(s.as_bytes()).collect()
}
