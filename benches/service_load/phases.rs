//! Part 4: where a submission's time goes, the port calls of one submission timed alone.

use super::common::*;
use super::nats_server::nats_backend;

/// p50 / p99 of milliseconds, as a table cell.
pub(crate) fn p50_p99(v: &mut [f64]) -> String {
    v.sort_by(f64::total_cmp);
    format!("{:.2} / {:.2}", pct(v, 0.5), pct(v, 0.99))
}

/// The port calls a small job makes until its first frame, in the order they happen, as
/// (table label, side).
pub(crate) const PHASES: [(&str, &str); 11] = [
    (
        "input blob `put` (embedded: file + fsync; NATS: object store)",
        "API",
    ),
    ("record `insert` (SQLite row; KV create)", "API"),
    (
        "queue `push` (in-memory FIFO; stream publish + ack, KV put of its sequence)",
        "API",
    ),
    ("status read (`GET /v1/jobs/{id}`)", "API"),
    ("watcher `subscribe` (SSE opens)", "API"),
    (
        "push → leased by a waiting worker (NATS: pull consumer delivery)",
        "worker",
    ),
    (
        "`start` (queued → running; NATS: KV compare-and-set)",
        "worker",
    ),
    ("input blob `get`", "worker"),
    (
        "step 0 positions: 2 frame blob `put`s (f32 + f64)",
        "worker",
    ),
    (
        "`record_frame` (SQLite row; NATS: frames stream + KV)",
        "worker",
    ),
    ("frame `publish` to watchers", "worker"),
];

/// The port calls of a small job until its first frame, `n` jobs one after the other: what
/// the API node does to admit it and open its stream, what the worker does to take it and
/// emit step 0 (parsing and the flow, the same for both backends, left out). Each job is then
/// finished and acked, so the queue is empty for the next.
pub(crate) async fn port_phases(
    backend: &Backend,
    obj: &str,
    n: usize,
) -> Result<Vec<Vec<f64>>, String> {
    let asset = Asset::read(
        obj.as_bytes(),
        Format::Obj,
        &willow::mesh::Limits::default(),
    )
    .map_err(|e| e.to_string())?;
    let (vertex_count, face_count) = (asset.file_vertex_count(), asset.surface().face_count());
    let flow = willow::flow::new_flow(asset.surface(), &JobSpec::default().flow_params())
        .map_err(|e| e.to_string())?;
    let metrics = flow.initial_metrics();
    let file_order = asset.file_positions(flow.positions());
    let (f32s, f64s) = (
        bytes::Bytes::from(willow_service::jobs::codec::f32s_to_bytes(&file_order)),
        bytes::Bytes::from(willow_service::jobs::codec::f64s_to_bytes(flow.positions())),
    );
    let data = bytes::Bytes::from(obj.to_string());
    let mut out = vec![Vec::new(); PHASES.len()];
    let err = |e: willow_service::jobs::JobError| e.to_string();
    let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    for _ in 0..n {
        // A worker waits for the job before it is pushed, as an idle worker does.
        let queue = backend.queue.clone();
        let leasing = tokio::spawn(async move {
            let lease = queue.lease().await;
            (lease, Instant::now())
        });
        tokio::time::sleep(Duration::from_millis(10)).await;
        let id = willow_service::jobs::JobId::random();
        let t = Instant::now();
        let input = BlobKey::Input {
            id: id.clone(),
            format: Format::Obj,
        };
        backend
            .blobs
            .put(input.clone(), data.clone())
            .await
            .map_err(err)?;
        out[0].push(ms(t));
        let t = Instant::now();
        backend
            .store
            .insert(NewJob {
                id: id.clone(),
                tenant: willow_service::jobs::DEFAULT_TENANT.to_string(),
                spec: JobSpec::default(),
                format: Format::Obj,
                vertex_count,
                face_count,
                repairs: None,
                notes: Vec::new(),
                input_bytes: data.len() as u64,
                // What the admission would reserve for frames (`jobs::stored`); the store's
                // cost does not depend on it.
                planned_bytes: 0,
                received: true,
                quotas: bench_quotas(),
                created_at: willow_service::jobs::now_ms(),
                idempotency: None,
            })
            .await
            .map_err(err)?;
        out[1].push(ms(t));
        let pushed = Instant::now();
        backend
            .queue
            .push(willow_service::jobs::DEFAULT_TENANT, &id)
            .await
            .map_err(err)?;
        out[2].push(ms(pushed));
        let t = Instant::now();
        backend.store.status(&id, None).await.map_err(err)?;
        out[3].push(ms(t));
        let t = Instant::now();
        let watching = backend.events.subscribe(&id).await.map_err(err)?;
        out[4].push(ms(t));
        let (lease, leased) = leasing.await.map_err(|e| e.to_string())?;
        let lease = lease.map_err(err)?;
        if lease.id != id {
            return Err(format!("leased {} instead of {id}", lease.id));
        }
        out[5].push((leased - pushed).as_secs_f64() * 1e3);
        let fence = willow_service::jobs::ports::Fence::new(Duration::from_secs(30));
        let t = Instant::now();
        backend
            .store
            .start(&id, &fence, willow_service::jobs::now_ms())
            .await
            .map_err(err)?;
        out[6].push(ms(t));
        let t = Instant::now();
        backend.blobs.get(input).await.map_err(err)?;
        out[7].push(ms(t));
        let t = Instant::now();
        for (welded, b) in [(false, &f32s), (true, &f64s)] {
            let key = BlobKey::Frame {
                id: id.clone(),
                step: 0,
                welded,
            };
            backend.blobs.put(key, b.clone()).await.map_err(err)?;
        }
        out[8].push(ms(t));
        let t = Instant::now();
        backend
            .store
            .record_frame(&id, metrics, true, &fence)
            .await
            .map_err(err)?;
        out[9].push(ms(t));
        let t = Instant::now();
        let frame = willow_service::jobs::Frame {
            step: 0,
            metrics,
            positions: Some(std::sync::Arc::new(willow_service::jobs::FramePositions {
                origin: [0.0; 3],
                relative: file_order.clone(),
            })),
            connectivity_changed: false,
        };
        backend
            .events
            .publish(&id, willow_service::jobs::JobEvent::Frame(frame))
            .await
            .map_err(err)?;
        out[10].push(ms(t));
        drop(watching);
        let now = willow_service::jobs::now_ms();
        backend
            .store
            .finish(
                &id,
                willow_service::jobs::JobState::Succeeded,
                None,
                now,
                now + 60_000,
                Some(&fence),
            )
            .await
            .map_err(err)?;
        backend.events.close(&id).await;
        lease.control.ack().await.map_err(err)?;
    }
    Ok(out)
}

pub(crate) async fn submit_phases(obj: &str) {
    let n = 200;
    println!();
    println!(
        "## 4. Where a small job's time goes until its first frame: the port calls alone \
         ({n} jobs in a row, p50 / p99 ms)"
    );
    println!(
        "No HTTP, no parsing and no flow (the same for both backends). On an API node, insert \
         and push run under the admission lock, so their sum bounds one node's submissions \
         per second."
    );
    println!();
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.queue_capacity = 10_000;
    let emb = match willow_service::jobs::embedded::open(dir.path(), config.queue_capacity) {
        Ok(b) => port_phases(&b, obj, n).await,
        Err(e) => Err(e.to_string()),
    };
    let nats = match nats_backend(&config, Duration::from_secs(30)).await {
        Ok((b, _process)) => port_phases(&b, obj, n).await,
        Err(e) => Err(e),
    };
    println!("| side | port call | embedded | NATS |");
    println!("|---|---|---|---|");
    let (mut emb, mut nats) = (emb, nats);
    let cell = |r: &mut Result<Vec<Vec<f64>>, String>, i: usize| match r {
        Ok(v) => p50_p99(&mut v[i]),
        Err(e) => format!("skipped: {e}"),
    };
    for (i, (what, side)) in PHASES.iter().enumerate() {
        println!(
            "| {side} | {what} | {} | {} |",
            cell(&mut emb, i),
            cell(&mut nats, i)
        );
    }
    let sum = |r: &Result<Vec<Vec<f64>>, String>, range: std::ops::Range<usize>| match r {
        Ok(v) => Some(range.map(|i| pct(&v[i], 0.5)).sum::<f64>()),
        Err(_) => None,
    };
    let show = |x: Option<f64>| x.map_or("—".to_string(), |ms| format!("{ms:.2}"));
    println!(
        "| API | sum of p50, submit (input … push) | {} | {} |",
        show(sum(&emb, 0..3)),
        show(sum(&nats, 0..3))
    );
    println!(
        "| API | insert + push p50 → one node's submissions/s ceiling | {} | {} |",
        sum(&emb, 1..3).map_or("—".into(), |ms| format!(
            "{ms:.2} ms → {:.0}/s",
            1e3 / ms.max(1e-3)
        )),
        sum(&nats, 1..3).map_or("—".into(), |ms| format!(
            "{ms:.2} ms → {:.0}/s",
            1e3 / ms.max(1e-3)
        ))
    );
    println!(
        "| worker | sum of p50, push → first frame published | {} | {} |",
        show(sum(&emb, 5..PHASES.len())),
        show(sum(&nats, 5..PHASES.len()))
    );
}
