//! What the parts share: the imports, the test server (the tests' own, sized for load),
//! percentiles and memory readings.

#[path = "../../tests/service_http_support/mod.rs"]
pub(crate) mod service_http_support;

pub(crate) use futures::StreamExt;
pub(crate) use service_http_support::{obj_text, slow_obj, start as start_server, TestServer};
pub(crate) use std::io::{BufRead, BufReader, Write};
pub(crate) use std::path::{Path, PathBuf};
pub(crate) use std::process::{Child, Command, Stdio};
pub(crate) use std::sync::OnceLock;
pub(crate) use std::time::{Duration, Instant};
pub(crate) use willow::mesh::io::{Asset, Format};
pub(crate) use willow_service::jobs::codec::encode_checkpoint;
pub(crate) use willow_service::jobs::embedded::files::FileBlobs;
pub(crate) use willow_service::jobs::embedded::sqlite::SqliteStore;
pub(crate) use willow_service::jobs::nats;
pub(crate) use willow_service::jobs::ports::{Backend, BlobKey, BlobStore, JobStore, NewJob};
pub(crate) use willow_service::jobs::{Caller, Config, JobSpec, Jobs};

/// Every request loop stops after this long, whatever its count: the benchmark must end.
pub(crate) const PHASE_BUDGET: Duration = Duration::from_secs(60);

pub(crate) fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

pub(crate) fn pct(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Quotas that are checked on every submission (their cost is part of what is measured) but
/// never refuse: the load here is one tenant's, far beyond the defaults.
pub(crate) fn bench_quotas() -> willow_service::jobs::TenantQuotas {
    willow_service::jobs::TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 1 << 30,
        max_stored_bytes: 1 << 50,
        uploads_per_minute: 1 << 30,
    }
}

/// The real router on loopback with `workers` workers and a queue of `queue_capacity` (the
/// tests' server, sized for load).
pub(crate) async fn start(workers: usize, queue_capacity: usize) -> TestServer {
    start_server(|c| {
        c.workers = workers;
        c.queue_capacity = queue_capacity;
        c.quotas = bench_quotas();
    })
    .await
}
