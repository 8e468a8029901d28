//! Crash recovery with the real binary: `willow serve` is SIGKILLed while a job runs, started
//! again on the same data dir, and every accepted job is found completed, or resumed from its
//! last checkpoint.

mod service_http_support;

use service_http_support::*;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

const JOB_TIMEOUT: Duration = Duration::from_secs(90);

/// Start `willow serve` on an ephemeral port; returns the child and its base URL.
fn spawn_server(data_dir: &std::path::Path) -> (Child, String) {
    spawn_server_with(data_dir, &[])
}

/// [`spawn_server`] with more flags.
fn spawn_server_with(data_dir: &std::path::Path, extra: &[&str]) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_willow"))
        .args([
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--workers",
            "1",
            "--queue-capacity",
            "8",
        ])
        // Every 3 steps unless the test says otherwise (a flag may be given once).
        .args(if extra.contains(&"--checkpoint-steps") {
            &[][..]
        } else {
            &["--checkpoint-steps", "3"][..]
        })
        .args(extra)
        .arg("--data-dir")
        .arg(data_dir)
        .args(["--log-format", "json"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn willow serve");
    let stdout = child.stdout.take().expect("piped stdout");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("listening on ") {
                let _ = tx.send(url.trim().to_string());
            }
        }
    });
    let base = rx
        .recv_timeout(Duration::from_secs(30))
        .expect("server prints its address");
    (child, base)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_mid_job_then_restart_completes_every_accepted_job() {
    let dir = tempfile::tempdir().expect("dir");
    let client = reqwest::Client::new();
    let (mut server, base) = spawn_server(dir.path());

    // A finished job before the crash keeps its result.
    let finished = submit_obj_to(&client, &base, "steps=2", &small_obj()).await;
    poll_until(&client, &base, &finished, JOB_TIMEOUT, is_terminal).await;
    // One job running when the process dies, two waiting behind it.
    let running = submit_obj_to(
        &client,
        &base,
        "steps=40&frame_interval=10&until_converged=false",
        &slow_obj(),
    )
    .await;
    let queued: Vec<String> = vec![
        submit_obj_to(&client, &base, "steps=3", &small_obj()).await,
        submit_obj_to(&client, &base, "steps=4", &small_obj()).await,
    ];
    // Past its first checkpoints (every 3 steps) when the process dies.
    let before = poll_until(&client, &base, &running, JOB_TIMEOUT, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 7
    })
    .await;

    server.kill().expect("SIGKILL"); // Child::kill is SIGKILL on Unix
    let _ = server.wait();

    let (mut server, base) = spawn_server(dir.path());
    // Right after the restart the job is queued or running again, at its checkpoint or
    // later: never back at step 0.
    let after = poll_until(&client, &base, &running, JOB_TIMEOUT, |_| true).await;
    assert!(
        after["progress"]["step"].as_u64().unwrap_or(0) >= 6,
        "resumes from its checkpoint: before the kill {before}, after {after}"
    );
    let v = poll_until(&client, &base, &running, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(v["state"], "succeeded", "the interrupted job went on: {v}");
    assert_eq!(
        v["started_time"], before["started_time"],
        "it has been running since its first start"
    );
    let metrics = client
        .get(format!("{base}/metrics"))
        .send()
        .await
        .expect("metrics")
        .text()
        .await
        .expect("text");
    assert!(
        metrics.contains("willow_jobs_resumed_total 1"),
        "one job resumed from a checkpoint:\n{metrics}"
    );
    for id in &queued {
        let v = poll_until(&client, &base, id, JOB_TIMEOUT, is_terminal).await;
        assert_eq!(v["state"], "succeeded", "{v}");
    }
    let v = poll_until(&client, &base, &finished, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(v["state"], "succeeded");
    let res = client
        .get(format!("{base}/v1/jobs/{finished}/result?format=obj"))
        .send()
        .await
        .expect("result");
    assert_eq!(res.status(), 200, "results survive the crash");

    // The resumed job's frames are complete and in order.
    let res = client
        .get(format!("{base}/v1/jobs/{running}/frames"))
        .send()
        .await
        .expect("frames");
    let frames: serde_json::Value = res.json().await.expect("json");
    let steps: Vec<u64> = frames["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .filter_map(|f| f["step"].as_u64())
        .collect();
    assert_eq!(steps, (0..=40).collect::<Vec<u64>>());
    // And its kept frames replay over SSE after the restart.
    let res = client
        .get(format!("{base}/v1/jobs/{running}/events?from_step=30"))
        .send()
        .await
        .expect("events");
    let events = read_sse(res, JOB_TIMEOUT).await;
    assert_eq!(frame_steps(&events), (30..=40).collect::<Vec<u64>>());
    let with_positions: Vec<u64> = events
        .iter()
        .filter(|e| e.event == "frame" && e.data.get("positions_b64").is_some())
        .filter_map(|e| e.data["step"].as_u64())
        .collect();
    assert_eq!(with_positions, vec![30, 40]);

    // SIGTERM: a graceful stop (exit status 0).
    #[cfg(unix)]
    {
        let pid = server.id().to_string();
        let status = Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .expect("kill -TERM");
        assert!(status.success());
        let exit = tokio::task::spawn_blocking(move || server.wait())
            .await
            .expect("join")
            .expect("wait");
        assert!(exit.success(), "graceful exit: {exit:?}");
    }
    #[cfg(not(unix))]
    {
        let _ = server.kill();
    }
}

/// A job that dies with its server, before any new checkpoint, more often than
/// `--max-deliveries` allows fails with code `redelivered` on the next start, instead of taking the server down in a loop (a mesh that
/// runs a worker out of memory, say).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_that_keeps_killing_the_server_fails_as_redelivered() {
    let dir = tempfile::tempdir().expect("dir");
    let client = reqwest::Client::new();
    // No checkpoint in the job's life: the run the kill ends made no progress that lasts.
    let flags = ["--max-deliveries", "1", "--checkpoint-steps", "100000"];
    let (mut server, base) = spawn_server_with(dir.path(), &flags);
    let id = submit_obj_to(
        &client,
        &base,
        "steps=400&until_converged=false",
        &slow_obj(),
    )
    .await;
    // Past its first steps, not only `running`: a worker marks the job running before it
    // counts the delivery (`JobStore::delivered`), and a kill between the two is a delivery
    // that never ran the job, so it rightly does not count.
    poll_until(&client, &base, &id, JOB_TIMEOUT, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().unwrap_or(0) >= 2
    })
    .await;
    server.kill().expect("SIGKILL");
    let _ = server.wait();
    let (mut server, base) = spawn_server_with(dir.path(), &flags);
    let v = poll_until(&client, &base, &id, JOB_TIMEOUT, is_terminal).await;
    let _ = server.kill();
    let _ = server.wait();
    assert_eq!(v["state"], "failed", "{v}");
    assert_eq!(v["error_code"], "redelivered", "{v}");
    assert!(
        v["error"].as_str().is_some_and(
            |m| m.contains("delivered 2 times in a row without reaching a new checkpoint")
        ),
        "{v}"
    );
}

/// `--max-deliveries` counts only deliveries that made no progress (issue 25 item 4), on the
/// embedded backend too: with `--max-deliveries 1`, the server is killed three times while
/// the job runs, each time past a checkpoint newer than where its run resumed, and the job
/// still succeeds after the third restart.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_killed_with_its_server_after_progress_is_not_failed_redelivered() {
    const N: u64 = 300;
    let dir = tempfile::tempdir().expect("dir");
    let client = reqwest::Client::new();
    let flags = ["--max-deliveries", "1", "--checkpoint-steps", "5"];
    let (mut server, mut base) = spawn_server_with(dir.path(), &flags);
    let id = submit_obj_to(
        &client,
        &base,
        &format!("steps={N}&frame_interval=50&until_converged=false"),
        &slow_obj(),
    )
    .await;
    let mut resumed_at = 0;
    let mut killed_at = Vec::new();
    for kill in 1..=3 {
        let v = poll_until(&client, &base, &id, JOB_TIMEOUT, |v| {
            is_terminal(v)
                || (v["state"] == "running"
                    && v["progress"]["step"].as_u64().unwrap_or(0) >= resumed_at + 8)
        })
        .await;
        if v["state"] != "running" {
            let _ = server.kill();
            let _ = server.wait();
            panic!("still running at kill {kill}: {v}");
        }
        let step = v["progress"]["step"].as_u64().unwrap_or(0);
        server.kill().expect("SIGKILL");
        let _ = server.wait();
        killed_at.push(step);
        // Checkpoints fall on multiples of 5 (every 5 steps from 0, and from a resume
        // point): the next run resumes at or below this one, and once it shows 8 steps past
        // it, the checkpoint 5 past it is written.
        resumed_at = step / 5 * 5;
        (server, base) = spawn_server_with(dir.path(), &flags);
    }
    let v = poll_until(&client, &base, &id, JOB_TIMEOUT, is_terminal).await;
    let _ = server.kill();
    let _ = server.wait();
    assert_eq!(
        v["state"], "succeeded",
        "killed at steps {killed_at:?}, each past a new checkpoint: {v}"
    );
    assert_eq!(v["progress"]["step"], N, "{v}");
}
