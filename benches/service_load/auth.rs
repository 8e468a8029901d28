//! Part 8: what authentication and the tenant checks cost a submission.

use super::burst::{phase_table, submit_burst};
use super::common::*;

pub(crate) async fn auth_overhead(obj: &str) {
    const CLIENTS: usize = 8;
    const PER_CLIENT: usize = 15;
    const ROUNDS: usize = 16;
    println!();
    println!(
        "## 8. Authentication and tenant checks: submit latency at {CLIENTS} clients \
         (embedded, small mesh, 1 step; {ROUNDS} interleaved rounds of {} submissions per server, \
         the order rotated each round, every server's jobs finished before the next burst)",
        CLIENTS * PER_CLIENT
    );
    println!();
    let off = willow_service::jobs::TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 0,
        max_stored_bytes: 0,
        uploads_per_minute: 0,
    };
    let keys_dir = tempfile::tempdir().expect("dir");
    let (key, line) = willow_service::api::auth::new_key("bench", "load").expect("key");
    let file = keys_dir.path().join("keys");
    std::fs::write(&file, format!("{line}\n")).expect("key file");
    let keys = || {
        willow_service::api::auth::Auth::new(&willow_service::api::auth::AuthConfig {
            mode: willow_service::api::auth::AuthMode {
                keys: true,
                jwt: false,
            },
            keys_file: Some(file.clone()),
            ..Default::default()
        })
        .expect("auth")
    };
    // Auth off/on × quotas off/on, so each cost shows on its own.
    let variants = [
        ("`--auth none`, quotas off", false, false),
        ("`--auth none`, quotas on", false, true),
        ("API key, quotas off", true, false),
        ("API key, quotas on", true, true),
    ];
    let mut servers = Vec::new();
    for (_, with_key, with_quotas) in variants {
        let auth = if with_key {
            keys()
        } else {
            willow_service::api::auth::Auth::none()
        };
        let server = service_http_support::start_with(
            tempfile::tempdir().expect("dir"),
            |c| {
                c.workers = 2;
                c.queue_capacity = 100_000;
                c.quotas = if with_quotas {
                    bench_quotas()
                } else {
                    off.clone()
                };
            },
            willow_service::api::server::ServeOptions {
                app: willow_service::api::server::AppOptions {
                    auth,
                    ..Default::default()
                },
                ..Default::default()
            },
        )
        .await;
        servers.push(server);
    }
    let mut samples: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    // Each round's p50 of every server against the first server's in the same round: the
    // rounds are a second apart, so a machine whose load drifts (another build, a neighbour)
    // moves both alike, and the median over rounds drops the rounds it hit unevenly.
    let mut round_ratios: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    // The jobs a burst queues run after it: unless they finish first, they load whichever
    // server comes next, and a fixed order would charge that load to the same variant.
    for round in 0..ROUNDS {
        let mut p50 = vec![f64::NAN; variants.len()];
        for j in 0..variants.len() {
            let i = (round + j) % variants.len();
            let k = variants[i].1.then_some(key.as_str());
            let mut burst = submit_burst(&servers[i].base, obj, CLIENTS, PER_CLIENT, k).await;
            burst.sort_by(f64::total_cmp);
            p50[i] = pct(&burst, 0.5);
            samples[i].extend(burst);
            let jobs = &servers[i].jobs;
            let deadline = Instant::now() + PHASE_BUDGET;
            while (jobs.queue_depth() > 0 || jobs.running() > 0) && Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
        for (i, ratios) in round_ratios.iter_mut().enumerate() {
            ratios.push(p50[i] / p50[0]);
        }
    }
    println!(
        "| server | submissions | submit p50 ms | submit p99 ms | p50 against the first | \
         median of the rounds' p50 ratios |"
    );
    println!("|---|---|---|---|---|---|");
    let base = {
        let v = &mut samples[0];
        v.sort_by(f64::total_cmp);
        pct(v, 0.5)
    };
    for (i, (name, _, _)) in variants.iter().enumerate() {
        let v = &mut samples[i];
        v.sort_by(f64::total_cmp);
        let ratios = &mut round_ratios[i];
        ratios.sort_by(f64::total_cmp);
        println!(
            "| {name} | {} | {:.2} | {:.2} | {:+.1}% | {:+.1}% |",
            v.len(),
            pct(v, 0.5),
            pct(v, 0.99),
            (pct(v, 0.5) / base - 1.0) * 100.0,
            (pct(ratios, 0.5) - 1.0) * 100.0
        );
    }
    // What each check costs the server, apart from the noise of the whole request: the
    // store's insert (where the quotas are read, in its transaction) per server, and the
    // auth layer in process. A submission at 8 clients on this machine spends about
    // p50 × cores / clients of CPU, which these costs are a fraction of.
    println!();
    println!("| server | store insert, mean ms (quota read inside) |");
    println!("|---|---|");
    for (i, (name, _, _)) in variants.iter().enumerate() {
        let insert = phase_table(&servers[i].base)
            .await
            .into_iter()
            .find(|(phase, ..)| phase == "insert")
            .map_or(f64::NAN, |(_, _, mean, _)| mean);
        println!("| {name} | {insert:.3} |");
    }
    let (none_us, key_us) = auth_layer_cost(keys(), &key).await;
    println!();
    println!(
        "Auth layer in process (a trivial handler behind it, {AUTH_CALLS} requests, \
         interleaved): without {none_us:.2} µs, with an API key {key_us:.2} µs a request \
         ({:+.2} µs)",
        key_us - none_us
    );
    for server in servers {
        server.stop().await;
    }
}

pub(crate) const AUTH_CALLS: usize = 200_000;

/// Mean µs per request through a router with a trivial handler, without and with `auth`'s
/// layer checking `key`, alternating blocks of 1000 so that drift hits both alike.
pub(crate) async fn auth_layer_cost(
    auth: willow_service::api::auth::Auth,
    key: &str,
) -> (f64, f64) {
    use tower::ServiceExt as _;
    let app = || {
        axum::Router::new().route(
            "/v1/jobs",
            axum::routing::post(|| async { axum::http::StatusCode::ACCEPTED }),
        )
    };
    let plain = app();
    let guarded = auth.wrap(app());
    let request = || {
        axum::http::Request::post("/v1/jobs")
            .header("authorization", format!("Bearer {key}"))
            .body(axum::body::Body::empty())
            .expect("request")
    };
    let mut spent = [0.0f64; 2];
    for _ in 0..AUTH_CALLS / 1000 {
        for (slot, router) in [&plain, &guarded].into_iter().enumerate() {
            let t = Instant::now();
            for _ in 0..1000 {
                let res = router.clone().oneshot(request()).await.expect("infallible");
                assert_eq!(res.status(), 202);
            }
            spent[slot] += t.elapsed().as_secs_f64();
        }
    }
    let per = |s: f64| s * 1e6 / AUTH_CALLS as f64;
    (per(spent[0]), per(spent[1]))
}
