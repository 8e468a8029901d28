//! Request heads over the server's limits: `414 uri_too_long` and `431 headers_too_large` as
//! problem details, not hyper's empty answers.
//!
//! hyper refuses a head past *its* limits itself, with an empty body and no way to change
//! that (HTTP/1: `414` for a request target over 65 534 bytes, `431` past its read buffer of
//! ~400 KiB or its header count; HTTP/2: h2 answers `431` past `max_header_list_size`). So the
//! server's own limits ([`MAX_URI_BYTES`], [`MAX_HEADER_BYTES`], [`MAX_HEADERS`]) sit below
//! hyper's (`conn::builder` raises the HTTP/1 header count and the HTTP/2 list size above
//! them), and this layer answers every head between the two with a problem naming the limit.
//! A head past hyper's limits still gets hyper's empty answer (HTTP/1: a head over ~400 KiB
//! against our 16 KiB of fields, a target over 65 534 bytes against our 32 768, more than
//! 200 fields against our 100; HTTP/2: a header list over 64 KiB against our 48 KiB of target
//! and fields): hyper must stop reading somewhere, and raising its limits further would only
//! let a client make the server hold more before it refuses.

use crate::api::problem::Problem;
use axum::body::Body;
use axum::extract::Request;
use axum::http::{header, HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};

/// Longest request target (path and query), in bytes. RFC 9110 §4.1 asks for at least 8000;
/// a raw upload's query may carry lists (`region.vertices=…`), so 4 times that.
pub const MAX_URI_BYTES: usize = 32 << 10;

/// Most bytes of header fields, counted as HTTP/2 counts a header list (RFC 9113 §6.5.2:
/// name, value and 32 bytes per field), the request target excluded.
pub const MAX_HEADER_BYTES: usize = 16 << 10;

/// Most header fields (hyper's HTTP/1 default, kept as the limit on both versions).
pub const MAX_HEADERS: usize = 100;

/// Answer a request whose head is over the limits (see the module docs) with 414 or 431.
pub async fn refuse_oversized_head(req: Request<Body>, next: axum::middleware::Next) -> Response {
    let uri_len = req.uri().path_and_query().map_or(0, |pq| pq.as_str().len());
    let headers = req.headers();
    let count = headers.len();
    let bytes: usize = headers
        .iter()
        .map(|(k, v)| k.as_str().len() + v.len() + 32)
        .sum();
    let refusal = if uri_len > MAX_URI_BYTES {
        Some((
            StatusCode::URI_TOO_LONG,
            "uri_too_long",
            format!(
                "the request target (path and query) is {uri_len} bytes; the limit is \
                 {MAX_URI_BYTES} (send long parameter lists in a multipart `params` part)"
            ),
            MAX_URI_BYTES,
        ))
    } else if count > MAX_HEADERS {
        Some((
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            format!("the request has {count} header fields; the limit is {MAX_HEADERS}"),
            MAX_HEADERS,
        ))
    } else if bytes > MAX_HEADER_BYTES {
        Some((
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            format!(
                "the request's header fields are {bytes} bytes (name, value and 32 bytes each); \
                 the limit is {MAX_HEADER_BYTES}"
            ),
            MAX_HEADER_BYTES,
        ))
    } else {
        None
    };
    let Some((status, code, detail, limit)) = refusal else {
        return next.run(req).await;
    };
    let grpc = headers
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/grpc"));
    if grpc {
        // A gRPC client reads its status from the trailers-only answer, not a problem body.
        let message = HeaderValue::from_str(&detail).unwrap_or(HeaderValue::from_static(""));
        return (
            StatusCode::OK,
            [
                (
                    header::CONTENT_TYPE,
                    HeaderValue::from_static("application/grpc"),
                ),
                // RESOURCE_EXHAUSTED, as gRPC maps a header list over its limit.
                (
                    HeaderName::from_static("grpc-status"),
                    HeaderValue::from_static("8"),
                ),
                (HeaderName::from_static("grpc-message"), message),
            ],
        )
            .into_response();
    }
    let path = req.uri().path();
    // The path is the problem for a 414: echo only its start.
    let instance: String = path.chars().take(64).collect();
    Problem::new(status, code, detail)
        .with("limit", limit)
        .instance(instance)
        .into_response()
}
