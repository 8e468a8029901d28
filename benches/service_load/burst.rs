//! Part 7: submissions at 50 concurrent clients while the workers are busy.

use super::common::*;

/// `clients` clients each submitting `per_client` jobs back to back (no watching), with `key`
/// as their bearer if given: the latency of each submission in ms, sorted.
pub(crate) async fn submit_burst(
    base: &str,
    obj: &str,
    clients: usize,
    per_client: usize,
    key: Option<&str>,
) -> Vec<f64> {
    let deadline = Instant::now() + PHASE_BUDGET;
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let (base, obj, key) = (base.to_string(), obj.to_string(), key.map(str::to_string));
            tokio::spawn(async move {
                let client = reqwest::Client::new();
                let mut out = Vec::new();
                for _ in 0..per_client {
                    if Instant::now() > deadline {
                        break;
                    }
                    let t = Instant::now();
                    let mut req = client
                        .post(format!("{base}/v1/jobs?steps=1&include_positions=false"))
                        .header("content-type", "model/obj")
                        .body(obj.clone());
                    if let Some(k) = &key {
                        req = req.bearer_auth(k);
                    }
                    if let Ok(res) = req.send().await {
                        if res.status() == 202 && res.bytes().await.is_ok() {
                            out.push(t.elapsed().as_secs_f64() * 1e3);
                        }
                    }
                }
                out
            })
        })
        .collect();
    let mut all = Vec::new();
    for t in tasks {
        if let Ok(v) = t.await {
            all.extend(v);
        }
    }
    all.sort_by(f64::total_cmp);
    all
}

/// A histogram as scraped: (upper bound, cumulative count) buckets, sum, count.
type Histogram = (Vec<(f64, u64)>, f64, u64);

/// Per phase of `willow_submit_phase_seconds`: (count, mean ms, the bucket bound under which
/// 99% fall, in ms).
pub(crate) async fn phase_table(base: &str) -> Vec<(String, u64, f64, f64)> {
    let text = match reqwest::get(format!("{base}/metrics")).await {
        Ok(r) => r.text().await.unwrap_or_default(),
        Err(_) => String::new(),
    };
    let mut phases: std::collections::BTreeMap<String, Histogram> = Default::default();
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("willow_submit_phase_seconds_") else {
            continue;
        };
        let Some((kind, rest)) = rest.split_once('{') else {
            continue;
        };
        let Some(phase) = rest
            .split("phase=\"")
            .nth(1)
            .and_then(|r| r.split('"').next())
        else {
            continue;
        };
        let value = rest.rsplit(' ').next().and_then(|v| v.parse::<f64>().ok());
        let entry = phases.entry(phase.to_string()).or_default();
        match (kind, value) {
            ("bucket", Some(v)) => {
                let le = rest
                    .split("le=\"")
                    .nth(1)
                    .and_then(|r| r.split('"').next())
                    .and_then(|b| b.parse::<f64>().ok())
                    .unwrap_or(f64::INFINITY);
                entry.0.push((le, v as u64));
            }
            ("sum", Some(v)) => entry.1 = v,
            ("count", Some(v)) => entry.2 = v as u64,
            _ => {}
        }
    }
    phases
        .into_iter()
        .map(|(phase, (buckets, sum, count))| {
            let target = (count as f64 * 0.99).ceil() as u64;
            let p99 = buckets
                .iter()
                .find(|(_, c)| *c >= target)
                .map_or(f64::INFINITY, |(le, _)| *le);
            (phase, count, sum * 1e3 / count.max(1) as f64, p99 * 1e3)
        })
        .collect()
}

pub(crate) async fn submit_under_load(obj: &str) {
    const CLIENTS: usize = 50;
    println!();
    println!(
        "## 7. Submissions at {CLIENTS} concurrent clients while both workers run (embedded, \
         small mesh, 1 step, no 429: queue and quotas out of the way)"
    );
    println!();
    let srv = start(2, 100_000).await;
    // A long job on each worker, so the flows compete with the submissions for the cores.
    let mut long = Vec::new();
    for _ in 0..2 {
        let res = srv
            .client
            .post(srv.url("/v1/jobs?steps=2000&include_positions=false&until_converged=false"))
            .header("content-type", "model/obj")
            .body(slow_obj())
            .send()
            .await
            .expect("long job");
        let v: serde_json::Value = res.json().await.unwrap_or_default();
        long.push(v["id"].as_str().unwrap_or_default().to_string());
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let idle = submit_burst(&srv.base, obj, 1, 50, None).await;
    let loaded = submit_burst(&srv.base, obj, CLIENTS, 20, None).await;
    println!("| clients | submissions | submit p50 ms | submit p99 ms | max ms |");
    println!("|---|---|---|---|---|");
    for (clients, v) in [(1, &idle), (CLIENTS, &loaded)] {
        println!(
            "| {clients} | {} | {:.1} | {:.1} | {:.1} |",
            v.len(),
            pct(v, 0.5),
            pct(v, 0.99),
            v.last().copied().unwrap_or(0.0)
        );
    }
    println!();
    println!("Where the time goes, server side (all submissions of both rows):");
    println!();
    println!("| phase | count | mean ms | p99 ≤ ms |");
    println!("|---|---|---|---|");
    for (phase, count, mean, p99) in phase_table(&srv.base).await {
        println!("| {phase} | {count} | {mean:.2} | {p99:.1} |");
    }
    for id in long {
        let _ = srv
            .client
            .post(srv.url(&format!("/v1/jobs/{id}/cancel")))
            .send()
            .await;
    }
    srv.stop().await;
}
