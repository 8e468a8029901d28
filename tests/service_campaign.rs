//! The campaign (issue 12): 1000 submissions from 50 concurrent HTTP clients against a server
//! whose queue is far smaller than the burst. Every answer is 202 or 429 (never a 5xx, never
//! a dropped connection), every 429 says when to come back, every accepted job reaches a
//! terminal state, and the job list holds exactly the accepted jobs: nothing lost, nothing
//! extra.

mod service_http_support;

use service_http_support::{is_terminal, small_obj, start};
use std::collections::{BTreeMap, HashSet};
use std::time::{Duration, Instant};
use willow_service::jobs::TenantQuotas;

const CLIENTS: usize = 50;
const PER_CLIENT: usize = 20;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_submissions_from_fifty_clients_see_only_202_and_429_and_lose_nothing() {
    let server = start(|c| {
        c.workers = 2;
        c.queue_capacity = 64;
        // One tenant sends the whole burst: the queue, not a quota, is what pushes back here.
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        };
    })
    .await;
    let body = small_obj();
    let started = Instant::now();
    let mut tasks = Vec::new();
    for client_no in 0..CLIENTS {
        // Each client its own connection pool, as 50 separate programs would have.
        let client = reqwest::Client::new();
        let url = server.url("/v1/jobs?steps=2&method=conformal");
        let body = body.clone();
        tasks.push(tokio::spawn(async move {
            let mut seen = Vec::new();
            for n in 0..PER_CLIENT {
                let t = Instant::now();
                let res = client
                    .post(&url)
                    .header("content-type", "model/obj")
                    .body(body.clone())
                    .send()
                    .await
                    .unwrap_or_else(|e| panic!("client {client_no}, request {n}: {e}"));
                let status = res.status().as_u16();
                let retry_after = res.headers().get("retry-after").cloned();
                let json: serde_json::Value = res.json().await.unwrap_or_default();
                seen.push((status, retry_after.is_some(), json, t.elapsed()));
            }
            seen
        }));
    }
    let mut statuses: BTreeMap<u16, usize> = BTreeMap::new();
    let mut accepted = HashSet::new();
    let mut latencies = Vec::new();
    for task in tasks {
        for (status, has_retry_after, json, took) in task.await.expect("client task") {
            *statuses.entry(status).or_default() += 1;
            latencies.push(took);
            match status {
                202 => {
                    let id = json["id"]
                        .as_str()
                        .expect("a 202 names its job")
                        .to_string();
                    assert!(accepted.insert(id), "two 202s named one job");
                }
                429 => {
                    assert!(has_retry_after, "a 429 says when to retry: {json}");
                    assert_eq!(json["code"], "queue_full", "{json}");
                }
                other => panic!("status {other} in the campaign: {json}"),
            }
        }
    }
    latencies.sort();
    let pct = |p: f64| latencies[((latencies.len() - 1) as f64 * p) as usize];
    eprintln!(
        "campaign: {statuses:?} in {:.1} s; submit p50 {:?}, p99 {:?}",
        started.elapsed().as_secs_f64(),
        pct(0.5),
        pct(0.99)
    );
    assert_eq!(statuses.values().sum::<usize>(), CLIENTS * PER_CLIENT);
    assert!(
        statuses.get(&202).copied().unwrap_or(0) >= 64,
        "the queue's worth was accepted: {statuses:?}"
    );
    assert!(
        statuses.contains_key(&429),
        "a burst of 1000 on a queue of 64 must be pushed back: {statuses:?}"
    );

    // Every accepted job reaches a terminal state, and succeeds (the mesh is fine).
    for id in &accepted {
        let v = server
            .poll_until(id, Duration::from_secs(300), is_terminal)
            .await;
        assert_eq!(v["state"], "succeeded", "{v}");
    }
    // The list holds exactly the accepted jobs.
    let mut listed = HashSet::new();
    let mut token: Option<String> = None;
    loop {
        let path = match &token {
            None => "/v1/jobs?page_size=200".to_string(),
            Some(t) => format!("/v1/jobs?page_size=200&page_token={t}"),
        };
        let (status, page) = server.get_json(&path).await;
        assert_eq!(status, 200, "{page}");
        for job in page["jobs"].as_array().expect("jobs") {
            listed.insert(job["id"].as_str().expect("id").to_string());
        }
        match page["next_page_token"].as_str() {
            Some(t) if !t.is_empty() => token = Some(t.to_string()),
            _ => break,
        }
    }
    assert_eq!(
        listed, accepted,
        "the store holds exactly the accepted jobs"
    );
    server.stop().await;
}
