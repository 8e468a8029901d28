//! Request bodies: the upload limits' multipart slack, the 413 (and 405) policy for errors
//! raised below the handlers, and the bounded reading and draining of bodies.

use crate::api::problem::Problem;
use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use futures::StreamExt;
use std::time::Duration;

/// Bytes a multipart upload may carry beyond the mesh itself: boundaries, part headers and the
/// `params` JSON part. 1 MiB is far more than those need and small next to a mesh.
pub const MULTIPART_SLACK: u64 = 1 << 20;

/// Turn the errors produced below the handlers into problems: a 413 from tower-http's body
/// limit (plain text, no limit named) and axum's 405 for a known path with another method
/// (empty body). The 405 keeps its `Allow` header, which axum adds outside the routes' own
/// layers: so this runs around the whole router (`server::app`), where the header is set.
pub async fn problem_for_plain_413(
    State(limit): State<u64>,
    req: Request<Body>,
    next: axum::middleware::Next,
) -> Response {
    let method = req.method().clone();
    let path = req.uri().path().to_string();
    let res = next.run(req).await;
    let is_problem = res
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/problem+json"));
    if is_problem {
        return res;
    }
    let problem = match res.status() {
        StatusCode::PAYLOAD_TOO_LARGE => {
            Problem::too_large("request body bytes", limit).instance(path)
        }
        StatusCode::METHOD_NOT_ALLOWED => {
            let allowed = res
                .headers()
                .get(header::ALLOW)
                .and_then(|v| v.to_str().ok())
                .unwrap_or("");
            Problem::new(
                StatusCode::METHOD_NOT_ALLOWED,
                "method_not_allowed",
                format!("{method} is not allowed on {path}; allowed: {allowed}"),
            )
            .instance(path)
        }
        _ => return res,
    };
    // The problem replaces the body; every other header stays (`Allow`, CORS, request id).
    let mut out = problem.into_response();
    for (name, value) in res.headers() {
        if name != header::CONTENT_TYPE && name != header::CONTENT_LENGTH {
            out.headers_mut().insert(name.clone(), value.clone());
        }
    }
    out
}

/// Refuse a request body sent with a content coding: 415 naming the coding, with
/// `Accept-Encoding: identity` (RFC 9110 §15.5.16: a 415 for a coding says which codings
/// would have been accepted). No REST route decodes one, and before this a gzip, `br` or
/// `deflate` body reached the mesh and JSON parsers as it was and failed there with a
/// misleading message (a compressed OBJ is "not UTF-8 text"). `identity` is no coding and
/// passes. Layered on the REST routes only: gRPC compresses messages with `grpc-encoding`.
pub async fn refuse_content_encoding(req: Request<Body>, next: axum::middleware::Next) -> Response {
    let codings: Vec<String> = req
        .headers()
        .get_all(header::CONTENT_ENCODING)
        .iter()
        .flat_map(|v| {
            String::from_utf8_lossy(v.as_bytes())
                .split(',')
                .map(|c| c.trim().to_ascii_lowercase())
                .collect::<Vec<_>>()
        })
        .filter(|c| !c.is_empty() && c != "identity")
        .collect();
    if codings.is_empty() {
        return next.run(req).await;
    }
    let path = req.uri().path().to_string();
    let list = codings.join(", ");
    // Read (bounded) what the client is still sending, so that it gets the answer.
    drain_refused(req.into_body()).await;
    let mut res = Problem::new(
        StatusCode::UNSUPPORTED_MEDIA_TYPE,
        "unsupported_content_encoding",
        format!(
            "request bodies are read as sent, with no content coding: `Content-Encoding: {}` \
             is not supported (send the body uncompressed, or with `Content-Encoding: identity`)",
            crate::api::problem::clip(&list)
        ),
    )
    .with("field", "Content-Encoding")
    .with("encoding", list)
    .instance(path)
    .into_response();
    res.headers_mut().insert(
        header::ACCEPT_ENCODING,
        axum::http::HeaderValue::from_static("identity"),
    );
    res
}

/// How much of a refused oversized body the server still reads before it answers, and for
/// how long. A server that answers 413 and closes while the client is still sending leaves
/// that client a broken pipe instead of the answer (seen in CI: a 120 KB curve against a
/// 64 KB limit). Bounded, so a hostile body costs the server at most this much.
pub(in crate::api) const DRAIN_MAX_BYTES: usize = 1 << 20;
const DRAIN_MAX_TIME: Duration = Duration::from_secs(2);

/// Reads and discards up to [`DRAIN_MAX_BYTES`] of `body` within [`DRAIN_MAX_TIME`].
pub(super) async fn drain_refused(body: Body) {
    drain(body.into_data_stream(), 0).await;
}

async fn drain(mut stream: axum::body::BodyDataStream, mut read: usize) {
    let _ = tokio::time::timeout(DRAIN_MAX_TIME, async {
        while read < DRAIN_MAX_BYTES {
            match stream.next().await {
                Some(Ok(chunk)) => read += chunk.len(),
                _ => break,
            }
        }
    })
    .await;
}

/// The body, or `Err` when it is longer than `limit` bytes; then the rest is drained
/// ([`drain_refused`]) so that the client reads the refusal.
pub(super) async fn read_limited(body: Body, limit: u64) -> Result<bytes::Bytes, ()> {
    let limit = usize::try_from(limit).unwrap_or(usize::MAX);
    let mut stream = body.into_data_stream();
    let mut data = bytes::BytesMut::new();
    while let Some(chunk) = stream.next().await {
        let chunk = chunk.map_err(|_| ())?;
        if data.len() + chunk.len() > limit {
            drain(stream, 0).await;
            return Err(());
        }
        data.extend_from_slice(&chunk);
    }
    Ok(data.freeze())
}
