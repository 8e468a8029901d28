//! Part 6: redelivery after a worker crash, with real processes of this build's `willow serve`.

use super::common::*;
use super::nats_server::{ChildGuard, NatsProcess};

/// `willow serve ARGS` (this build's binary); its base URL once it prints it. Its logs (JSON
/// on stdout, the worker's job events at info) and stderr go to `log`.
pub(crate) async fn spawn_willow(
    args: Vec<String>,
    log: &Path,
) -> Result<(ChildGuard, String), String> {
    let open = || {
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .map_err(|e| format!("{}: {e}", log.display()))
    };
    let mut child = Command::new(env!("CARGO_BIN_EXE_willow"))
        .arg("serve")
        .args(&args)
        .args(["--log-format", "json"])
        .env("RUST_LOG", "warn,willow_service::jobs::worker=info")
        .stdout(Stdio::piped())
        .stderr(open()?)
        .spawn()
        .map_err(|e| format!("willow serve: {e}"))?;
    let stdout = child.stdout.take().ok_or("no stdout")?;
    let guard = ChildGuard(Some(child));
    let (tx, rx) = std::sync::mpsc::channel();
    let mut log = open()?;
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("listening on ") {
                let _ = tx.send(url.trim().to_string());
            } else {
                let _ = writeln!(log, "{line}");
            }
        }
    });
    let base = tokio::task::spawn_blocking(move || rx.recv_timeout(Duration::from_secs(60)))
        .await
        .map_err(|e| e.to_string())?
        .map_err(|_| "willow serve printed no address in 60 s".to_string())?;
    Ok((guard, base))
}

/// A sample of a Prometheus text exposition at `{base}/metrics`.
pub(crate) async fn metric(client: &reqwest::Client, base: &str, name: &str) -> Option<f64> {
    let text = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .ok()?
        .text()
        .await
        .ok()?;
    text.lines().find_map(|l| {
        let mut words = l.split_whitespace();
        if words.next()? == name {
            words.next()?.parse().ok()
        } else {
            None
        }
    })
}

/// A job's completed steps, from `GET /v1/jobs/{id}`.
pub(crate) async fn job_step(client: &reqwest::Client, base: &str, id: &str) -> Option<u64> {
    let v: serde_json::Value = client
        .get(format!("{base}/v1/jobs/{id}"))
        .send()
        .await
        .ok()?
        .json()
        .await
        .ok()?;
    v["progress"]["step"].as_u64()
}

/// Submit `obj` with `query`; the job id.
pub(crate) async fn submit_obj(
    client: &reqwest::Client,
    base: &str,
    obj: &str,
    query: &str,
) -> Result<String, String> {
    let res = client
        .post(format!("{base}/v1/jobs?{query}"))
        .header("content-type", "model/obj")
        .body(obj.to_string())
        .send()
        .await
        .map_err(|e| e.to_string())?;
    if res.status() != 202 {
        return Err(format!("submit answered {}", res.status()));
    }
    let v: serde_json::Value = res.json().await.map_err(|e| e.to_string())?;
    v["id"]
        .as_str()
        .map(str::to_string)
        .ok_or_else(|| "no job id".into())
}

/// Poll every 10 ms until `ready` gives a value, or fail after the phase budget.
pub(crate) async fn poll<T, F, Fut>(
    what: &str,
    deadline: Instant,
    mut ready: F,
) -> Result<T, String>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    loop {
        if let Some(v) = ready().await {
            return Ok(v);
        }
        if Instant::now() > deadline {
            return Err(format!("timed out waiting for {what}"));
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The steps a worker logged `resumed from the checkpoint` at, in order, in a JSON log file.
pub(crate) fn resumed_steps(log: &Path) -> Vec<u64> {
    let Ok(text) = std::fs::read_to_string(log) else {
        return Vec::new();
    };
    text.lines()
        .filter_map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).ok()?;
            (v["fields"]["message"] == "resumed from the checkpoint")
                .then(|| v["fields"]["step"].as_u64())
                .flatten()
        })
        .collect()
}

/// What one crash measurement found (times from the SIGKILL, in seconds).
pub(crate) struct Recovery {
    /// The job's step when its worker died.
    pub(crate) dead_step: u64,
    /// The checkpoint it resumed from.
    pub(crate) resumed_from: Option<u64>,
    /// A new process listens (embedded: the restart).
    pub(crate) listening: Option<f64>,
    /// `willow_jobs_resumed_total` = 1 on the worker that took the job over.
    pub(crate) resumed: f64,
    /// The job's step beyond `dead_step`: the lost steps are taken again and one more.
    pub(crate) progress: f64,
    /// NATS: when the redelivery is due after the kill, from the heartbeat schedule
    /// (`ack_wait` after the last heartbeat, or after the delivery if none was sent yet).
    pub(crate) due: Option<f64>,
}

/// The job's step once it is past `min` (its first checkpoints).
pub(crate) async fn wait_past(
    client: &reqwest::Client,
    base: &str,
    id: &str,
    min: u64,
    deadline: Instant,
) -> Result<u64, String> {
    poll(&format!("step {min}"), deadline, || async {
        job_step(client, base, id).await.filter(|s| *s >= min)
    })
    .await
}

/// After the kill at `t0`: until one of `nodes` (base URL, its `willow_jobs_resumed_total`
/// before the kill) reports one more resume, and the job at `api` passes `dead_step`. Which
/// node resumed it, and when. A node that resumed an earlier round's job counts from there
/// (comparing with 1 read an old resume as this one, at 0.01 s).
pub(crate) async fn wait_recovery(
    client: &reqwest::Client,
    api: &str,
    nodes: &[(String, f64)],
    id: &str,
    dead_step: u64,
    t0: Instant,
    deadline: Instant,
) -> Result<(usize, f64, f64), String> {
    let (node, resumed) = poll("the resume", deadline, || async {
        for (i, (base, before)) in nodes.iter().enumerate() {
            let n = metric(client, base, "willow_jobs_resumed_total")
                .await
                .unwrap_or(0.0);
            if n > *before {
                return Some((i, t0.elapsed().as_secs_f64()));
            }
        }
        None
    })
    .await?;
    let progress = poll("progress past the crash", deadline, || async {
        let s = job_step(client, api, id).await?;
        (s > dead_step).then(|| t0.elapsed().as_secs_f64())
    })
    .await?;
    Ok((node, resumed, progress))
}

/// Crashes per backend: each round kills the process running the job once.
pub(crate) const CRASH_ROUNDS: usize = 3;

/// NATS: an API node and two worker nodes with `ack_wait`. Each round submits a job, SIGKILLs
/// the worker running it (past its first checkpoints), measures until the other one has
/// resumed it, and starts a new worker node to be the next round's spare.
pub(crate) async fn crash_nats(
    obj: &str,
    ack_wait_secs: u64,
    checkpoint_steps: u64,
) -> Vec<Result<Recovery, String>> {
    let mut out = Vec::new();
    if let Err(e) = crash_nats_rounds(obj, ack_wait_secs, checkpoint_steps, &mut out).await {
        out.push(Err(e));
    }
    out
}

pub(crate) async fn crash_nats_rounds(
    obj: &str,
    ack_wait_secs: u64,
    checkpoint_steps: u64,
    out: &mut Vec<Result<Recovery, String>>,
) -> Result<(), String> {
    let client = reqwest::Client::new();
    let nats = NatsProcess::start().await?;
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let node = |role: &str, name: &str| -> Vec<String> {
        let mut a: Vec<String> = [
            "--backend",
            &nats.url,
            "--role",
            role,
            "--addr",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--grace-secs",
            "1",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend([
            "--nats-ack-wait-secs".into(),
            ack_wait_secs.to_string(),
            "--checkpoint-steps".into(),
            checkpoint_steps.to_string(),
            "--data-dir".into(),
            dir.path().join(name).display().to_string(),
        ]);
        a
    };
    let (_api, api) = spawn_willow(node("api", "api"), &dir.path().join("api.log")).await?;
    // (process, base URL, log)
    let mut workers = Vec::new();
    let spawn_worker = |n: usize| {
        let log = dir.path().join(format!("w{n}.log"));
        let args = node("worker", &format!("w{n}"));
        async move {
            let (child, base) = spawn_willow(args, &log).await?;
            Ok::<_, String>((child, base, log))
        }
    };
    for n in 0..2 {
        workers.push(spawn_worker(n).await?);
    }
    for round in 0..CRASH_ROUNDS {
        // A fresh job each round: a job delivered more than `max_deliveries` (3) times fails
        // with `redelivered` instead of being resumed again.
        let deadline = Instant::now() + PHASE_BUDGET;
        let id = submit_obj(
            &client,
            &api,
            obj,
            "steps=10000&include_positions=false&until_converged=false",
        )
        .await?;
        let runner = poll("a worker to run the job", deadline, || async {
            for (i, (child, base, _)) in workers.iter().enumerate() {
                if child.0.is_some()
                    && metric(&client, base, "willow_jobs_running").await == Some(1.0)
                {
                    return Some(i);
                }
            }
            None
        })
        .await?;
        // The lease began about now (the worker reports its running job at once).
        let leased = Instant::now();
        wait_past(&client, &api, &id, 3 * checkpoint_steps, deadline).await?;
        // Kill at a different point of the heartbeat cycle each round (0, 1.25 s, 2.5 s into
        // the job): the redelivery is due `ack_wait` after the last heartbeat.
        let at = leased + Duration::from_millis(1250 * round as u64);
        tokio::time::sleep_until(at.into()).await;
        // Each node's resumes so far: the one that takes this job over counts one more.
        let mut resumes_before = Vec::new();
        for (_, base, _) in &workers {
            resumes_before.push(
                metric(&client, base, "willow_jobs_resumed_total")
                    .await
                    .unwrap_or(0.0),
            );
        }
        let t0 = Instant::now();
        workers[runner].0.kill();
        let heartbeat = ack_wait_secs as f64 / 3.0;
        let due = ack_wait_secs as f64 - (t0 - leased).as_secs_f64() % heartbeat;
        // Nothing writes the job's step any more: this is where the crash left it.
        let dead_step = job_step(&client, &api, &id)
            .await
            .ok_or("status after the kill")?;
        let mut survivors = Vec::new();
        for (i, (child, base, log)) in workers.iter().enumerate() {
            if child.0.is_some() {
                survivors.push((i, base.clone(), resumes_before[i], resumed_steps(log).len()));
            }
        }
        let nodes: Vec<(String, f64)> = survivors.iter().map(|s| (s.1.clone(), s.2)).collect();
        let recovery = wait_recovery(&client, &api, &nodes, &id, dead_step, t0, deadline)
            .await
            .map(|(node, resumed, progress)| Recovery {
                dead_step,
                resumed_from: resumed_steps(&workers[survivors[node].0].2)
                    .get(survivors[node].3)
                    .copied(),
                listening: None,
                resumed,
                progress,
                due: Some(due),
            });
        let failed = recovery.is_err();
        out.push(recovery);
        // Cancel the job and wait until it is over, so the next round's runner is the worker
        // that reports one running job.
        let _ = client
            .post(format!("{api}/v1/jobs/{id}/cancel"))
            .send()
            .await;
        poll("the cancel", deadline, || async {
            for (base, _) in &nodes {
                if metric(&client, base, "willow_jobs_running").await != Some(0.0) {
                    return None;
                }
            }
            Some(())
        })
        .await?;
        if failed {
            break;
        }
        if round + 1 < CRASH_ROUNDS {
            workers.push(spawn_worker(workers.len()).await?);
        }
    }
    Ok(())
}

/// Embedded: each round SIGKILLs `willow serve` mid-job (a fresh job each round, as for
/// NATS) and starts it again at once on the same data dir.
pub(crate) async fn crash_embedded(
    obj: &str,
    checkpoint_steps: u64,
) -> Vec<Result<Recovery, String>> {
    let mut out = Vec::new();
    if let Err(e) = crash_embedded_rounds(obj, checkpoint_steps, &mut out).await {
        out.push(Err(e));
    }
    out
}

pub(crate) async fn crash_embedded_rounds(
    obj: &str,
    checkpoint_steps: u64,
    out: &mut Vec<Result<Recovery, String>>,
) -> Result<(), String> {
    let client = reqwest::Client::new();
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let data = dir.path().join("data");
    let args: Vec<String> = vec![
        "--addr".into(),
        "127.0.0.1:0".into(),
        "--workers".into(),
        "1".into(),
        "--grace-secs".into(),
        "1".into(),
        "--checkpoint-steps".into(),
        checkpoint_steps.to_string(),
        "--data-dir".into(),
        data.display().to_string(),
    ];
    let (mut process, mut base) = spawn_willow(args.clone(), &dir.path().join("0.log")).await?;
    for round in 0..CRASH_ROUNDS {
        let deadline = Instant::now() + PHASE_BUDGET;
        let id = submit_obj(
            &client,
            &base,
            obj,
            "steps=10000&include_positions=false&until_converged=false",
        )
        .await?;
        wait_past(&client, &base, &id, 3 * checkpoint_steps, deadline).await?;
        let t0 = Instant::now();
        process.kill();
        // Where the crash left the job, read from its SQLite file before the restart (a few
        // ms, counted in the times below).
        let store = SqliteStore::open(&data).map_err(|e| e.to_string())?;
        let dead_step = store
            .status(&id, None)
            .await
            .map_err(|e| e.to_string())?
            .step as u64;
        drop(store);
        let log = dir.path().join(format!("{}.log", round + 1));
        (process, base) = spawn_willow(args.clone(), &log).await?;
        let listening = t0.elapsed().as_secs_f64();
        // A new process: its resume counter starts at 0.
        let nodes = [(base.clone(), 0.0)];
        let recovery = wait_recovery(&client, &base, &nodes, &id, dead_step, t0, deadline)
            .await
            .map(|(_, resumed, progress)| Recovery {
                dead_step,
                resumed_from: resumed_steps(&log).first().copied(),
                listening: Some(listening),
                resumed,
                progress,
                due: None,
            });
        let failed = recovery.is_err();
        out.push(recovery);
        let _ = client
            .post(format!("{base}/v1/jobs/{id}/cancel"))
            .send()
            .await;
        poll("the cancel", deadline, || async {
            (metric(&client, &base, "willow_jobs_running").await == Some(0.0)).then_some(())
        })
        .await?;
        if failed {
            break;
        }
    }
    Ok(())
}

pub(crate) async fn redelivery() {
    let (ack_wait, checkpoint_steps) = (5u64, 2u64);
    let obj = slow_obj();
    println!();
    println!(
        "## 6. Recovery after a worker crash (SIGKILL mid-job, {CRASH_ROUNDS} jobs per backend; \
         2562-vertex sphere, checkpoint every {checkpoint_steps} steps; times from the kill)"
    );
    println!(
        "NATS: nats-server, 1 API node and 2 worker nodes (a new one started after each round), \
         `--nats-ack-wait-secs {ack_wait}`: heartbeats every ack_wait / 3 = {:.2} s, so \
         redelivery is due between ack_wait − heartbeat and ack_wait after the kill, to the \
         other worker's pending fetch. Embedded: `willow serve` started again at once on the \
         same data dir (its queue lives in the process).",
        ack_wait as f64 / 3.0
    );
    println!();
    println!("| backend | round | step at the kill | resumed from | new process listening s | job resumed s | progress past the crash step s | redelivery due s | configured |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let rows = |name: &str, rounds: Vec<Result<Recovery, String>>, configured: &str| {
        for (k, r) in rounds.into_iter().enumerate() {
            match r {
                Ok(r) => println!(
                    "| {name} | {} | {} | {} | {} | {:.2} | {:.2} | {} | {configured} |",
                    k + 1,
                    r.dead_step,
                    r.resumed_from
                        .map_or("—".to_string(), |s| format!("step {s}")),
                    r.listening.map_or("—".to_string(), |s| format!("{s:.2}")),
                    r.resumed,
                    r.progress,
                    r.due.map_or("—".to_string(), |s| format!("≈ {s:.2}")),
                ),
                Err(e) => println!(
                    "| {name} | {} | skipped: {e} | | | | | | {configured} |",
                    k + 1
                ),
            }
        }
    };
    let nats = crash_nats(&obj, ack_wait, checkpoint_steps).await;
    rows("nats", nats, &format!("ack_wait {ack_wait} s"));
    let embedded = crash_embedded(&obj, checkpoint_steps).await;
    rows("embedded", embedded, "restart at once");
}
