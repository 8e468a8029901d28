//! End-to-end tests of the HTTP API: the real router on an ephemeral loopback port, driven by
//! reqwest over real sockets (SSE parsed from the byte stream). One file a theme: `jobs`,
//! `errors`, `details` (issue 42), `probes`, `options`, `curves`, `body`.

#[path = "../service_http_support/mod.rs"]
mod service_http_support;

mod body;
mod creases;
mod curves;
mod details;
mod errors;
mod far;
mod jobs;
mod options;
mod probes;

use service_http_support::*;
use std::time::Duration;

/// Generous per-job timeout: small meshes finish in well under a second, but CI shares 2 cores.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
