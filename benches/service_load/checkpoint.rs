//! Part 5: the cost of a checkpoint on a 100k-triangle job.

use super::common::*;
use super::nats_server::nats_backend;

pub(crate) async fn checkpoint_cost() {
    let steps: usize = std::env::var("WILLOW_BENCH_CHECKPOINT_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5)
        .max(1);
    let reps = 10;
    // 2 · 400 · 125 = 100 000 triangles, 50 000 vertices.
    let mesh = willow::mesh::generate::torus(1.0, 0.4, 400, 125);
    let (faces, vertices) = (mesh.face_count(), mesh.vertex_count());
    println!();
    println!(
        "## 5. Checkpoint cost on a {faces}-triangle job (torus 400×125, {vertices} vertices, \
         conformal, default parameters, 1 thread as a worker runs it)"
    );
    // The worker's params: one thread below `PARALLEL_JOB_VERTICES`.
    let params = JobSpec::default().flow_params();
    let run = tokio::task::spawn_blocking(move || {
        let t = Instant::now();
        let mut flow = match willow::flow::new_flow(&mesh, &params) {
            Ok(f) => f,
            Err(e) => return Err(format!("new_flow: {e}")),
        };
        let setup = t.elapsed().as_secs_f64();
        let mut step_ms = Vec::new();
        let budget = Instant::now() + PHASE_BUDGET;
        for _ in 0..steps {
            let t = Instant::now();
            if let Err(e) = flow.step() {
                return Err(format!("step {}: {e}", step_ms.len() + 1));
            }
            step_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if Instant::now() > budget {
                break;
            }
        }
        Ok((flow, setup, step_ms))
    })
    .await;
    let (flow, setup, step_ms) = match run {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => return println!("skipped: {e}"),
        Err(e) => return println!("skipped: the flow panicked: {e}"),
    };
    let step = step_ms.iter().sum::<f64>() / step_ms.len() as f64;
    let Some(state) = flow.checkpoint() else {
        return println!("skipped: the flow keeps no checkpoint");
    };
    let size = encode_checkpoint(&state).len();
    let id = willow_service::jobs::JobId::random();
    let key = || BlobKey::Checkpoint { id: id.clone() };
    // What the worker's `checkpoint` does: take the state, encode it, put it (replacing the
    // previous one). `sink` None is state + encode alone.
    async fn time_checkpoints(
        flow: &dyn willow::flow::Flow,
        sink: Option<(&dyn BlobStore, BlobKey)>,
        reps: usize,
    ) -> Result<Vec<f64>, String> {
        let mut out = Vec::new();
        for _ in 0..reps {
            let t = Instant::now();
            let state = flow.checkpoint().ok_or("no checkpoint")?;
            let bytes = bytes::Bytes::from(encode_checkpoint(&state));
            if let Some((blobs, key)) = &sink {
                blobs
                    .put(key.clone(), bytes)
                    .await
                    .map_err(|e| e.to_string())?;
            } else {
                std::hint::black_box(bytes);
            }
            out.push(t.elapsed().as_secs_f64() * 1e3);
        }
        Ok(out)
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let encode = time_checkpoints(flow.as_ref(), None, reps).await;
    let dir = tempfile::tempdir().expect("temp dir");
    let files = match FileBlobs::open(dir.path()) {
        Ok(f) => time_checkpoints(flow.as_ref(), Some((&f, key())), reps).await,
        Err(e) => Err(e.to_string()),
    };
    let nats = match nats_backend(&Config::new(dir.path()), Duration::from_secs(30)).await {
        Ok((b, _process)) => {
            time_checkpoints(flow.as_ref(), Some((b.blobs.as_ref(), key())), reps).await
        }
        Err(e) => Err(e),
    };
    println!(
        "Flow set-up {setup:.2} s; {} steps, each {step:.0} ms on average (min {:.0}, max {:.0}); \
         a checkpoint is {:.2} MB. Checkpoint times: mean of {reps} (min / max). The default \
         policy checkpoints every 10 steps (or 30 s, whichever comes first): the per-step cost \
         is the ratio / 10.",
        step_ms.len(),
        step_ms.iter().cloned().fold(f64::INFINITY, f64::min),
        step_ms.iter().cloned().fold(0.0, f64::max),
        size as f64 / 1e6
    );
    println!();
    println!("| checkpoint | ms | checkpoint / step | per step, every 10 steps | goal ≤ 2% |");
    println!("|---|---|---|---|---|");
    for (what, r) in [
        ("state + encode only", &encode),
        ("→ embedded files (write, fsync, rename, fsync dir)", &files),
        ("→ NATS object store (file storage, loopback)", &nats),
    ] {
        match r {
            Ok(v) => {
                let ratio = mean(v) / step;
                println!(
                    "| {what} | {:.2} ({:.2} / {:.2}) | {:.2}% | {:.3}% | {} |",
                    mean(v),
                    v.iter().cloned().fold(f64::INFINITY, f64::min),
                    v.iter().cloned().fold(0.0, f64::max),
                    ratio * 100.0,
                    ratio * 10.0,
                    if ratio / 10.0 <= 0.02 {
                        "met"
                    } else {
                        "missed"
                    }
                );
            }
            Err(e) => println!("| {what} | skipped: {e} | | | |"),
        }
    }
}
