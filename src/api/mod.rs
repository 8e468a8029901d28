//! The transports: thin layers that turn wire requests into calls on [`crate::jobs::Jobs`].
//!
//! - [`http`]: the REST API (axum), Server-Sent Events, probes, metrics, OpenAPI and docs.
//! - [`status`]: the one table from a job error or a failed job's outcome to an HTTP status and
//!   a gRPC code.
//! - [`problem`]: RFC 9457 problem details: a job error's HTTP body.
//! - [`server`]: the single router serving HTTP/1.1, h2c and gRPC on one port (assembled in
//!   [`server::app`] from the routes of the modules below, none of which imports it), and
//!   `willow serve`.
//! - [`web`]: the web page at `/` (issue 13), its files embedded at build time.
//! - `state`: [`http::AppState`], what the REST and web handlers share.
//! - [`grpc`]: the tonic services (package `willow.v1`, longrunning Operations, health,
//!   reflection), merged into the same router by [`server::app`].
//! - [`auth`]: authentication (API keys, JWT, stream tokens), one layer for HTTP and gRPC.
//! - [`codec`]: their protobuf codec (a request that does not decode is INVALID_ARGUMENT).
//! - [`conn`]: the accept loop: connection and request timeouts and limits.
//! - [`download`]: mesh downloads with bounded memory and a deadline.

pub mod auth;
pub mod codec;
pub mod conn;
pub mod download;
pub mod grpc;
pub mod http;
pub mod problem;
pub mod schema;
pub mod server;
mod state;
pub mod status;
pub mod web;
