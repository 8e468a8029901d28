//! A full disk on the embedded backend (issue 25, item 5): submissions answer 507
//! `storage_full` with `Retry-After`, `/readyz` says "storage full", a running job is
//! re-queued (never failed) and resumes once there is room, DELETE works, earlier results stay
//! readable, and the server starts on a full disk.
//!
//! Two ways: a fault-injection seam (a blob store that answers ENOSPC while a switch is on),
//! which runs anywhere; and a real, small tmpfs filled to the last byte, which needs root
//! (to mount it) and says why it skips otherwise.

mod service_http_support;

use async_trait::async_trait;
use service_http_support::*;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use willow_service::jobs::ports::{BlobKey, BlobStore};
use willow_service::jobs::{Config, JobError, Jobs};

const JOB_TIMEOUT: Duration = Duration::from_secs(120);

/// The embedded blob store, but every `put` fails as a full disk does while `full` is on.
struct FullSwitch {
    inner: Arc<dyn BlobStore>,
    full: Arc<AtomicBool>,
    refused: Arc<AtomicUsize>,
}

#[async_trait]
impl BlobStore for FullSwitch {
    async fn put(&self, key: BlobKey, data: bytes::Bytes) -> Result<(), JobError> {
        if self.full.load(Ordering::SeqCst) {
            self.refused.fetch_add(1, Ordering::SeqCst);
            // What `std::fs` gives for ENOSPC, through the same conversion the store uses.
            return Err(JobError::from(std::io::Error::from(
                std::io::ErrorKind::StorageFull,
            )));
        }
        self.inner.put(key, data).await
    }
    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError> {
        self.inner.get(key).await
    }
    async fn delete(&self, key: BlobKey) -> Result<(), JobError> {
        self.inner.delete(key).await
    }
    async fn delete_job(&self, id: &str) -> Result<(), JobError> {
        self.inner.delete_job(id).await
    }
}

/// An HTTP server on loopback over `jobs` (the support's servers start their own core).
async fn serve(jobs: Jobs, core: willow_service::jobs::Shutdown) -> String {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let base = format!("http://{}", listener.local_addr().expect("local addr"));
    tokio::spawn(willow_service::api::server::serve_with(
        listener,
        jobs,
        core,
        std::future::pending(),
        Duration::from_secs(2),
        willow_service::api::server::ServeOptions::default(),
    ));
    base
}

async fn submit(client: &reqwest::Client, base: &str, obj: &str, query: &str) -> Submitted {
    let res = client
        .post(format!(
            "{base}/v1/jobs?{}",
            service_http_support::conformal_unless_named(query)
        ))
        .header("content-type", "model/obj")
        .body(obj.to_string())
        .send()
        .await
        .expect("POST /v1/jobs");
    let status = res.status().as_u16();
    let headers = res.headers().clone();
    let body: serde_json::Value = res.json().await.unwrap_or(serde_json::Value::Null);
    Submitted {
        status,
        headers,
        body,
    }
}

struct Submitted {
    status: u16,
    headers: reqwest::header::HeaderMap,
    body: serde_json::Value,
}

impl Submitted {
    fn id(&self) -> String {
        assert_eq!(self.status, 202, "{}", self.body);
        self.body["id"].as_str().expect("job id").to_string()
    }

    /// The answer of a full disk: 507, `storage_full`, a `Retry-After`, no file names.
    fn assert_storage_full(&self) {
        assert_eq!(self.status, 507, "{}", self.body);
        assert_eq!(self.body["code"], "storage_full");
        assert_eq!(self.body["status"], 507);
        let retry: u64 = self
            .headers
            .get("retry-after")
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.parse().ok())
            .expect("Retry-After in seconds");
        assert!(retry >= 1);
        let detail = self.body["detail"].as_str().expect("detail");
        assert!(!detail.contains('/'), "no paths for the client: {detail}");
    }
}

async fn readyz(client: &reqwest::Client, base: &str) -> (u16, String) {
    let res = client
        .get(format!("{base}/readyz"))
        .send()
        .await
        .expect("GET /readyz");
    let status = res.status().as_u16();
    (status, res.text().await.unwrap_or_default())
}

/// Poll `/readyz` until it answers `status` (or panic after `JOB_TIMEOUT`).
async fn wait_ready(client: &reqwest::Client, base: &str, status: u16) -> String {
    let start = std::time::Instant::now();
    loop {
        let (s, body) = readyz(client, base).await;
        if s == status {
            return body;
        }
        assert!(start.elapsed() < JOB_TIMEOUT, "/readyz stayed {s} ({body})");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn result_vertices(client: &reqwest::Client, base: &str, id: &str) -> Vec<[f64; 3]> {
    let res = client
        .get(format!("{base}/v1/jobs/{id}/result?format=obj"))
        .send()
        .await
        .expect("GET result");
    assert_eq!(res.status().as_u16(), 200, "result of {id}");
    obj_vertices(&res.text().await.expect("result body"))
}

/// The seam: a job running when the disk fills is re-queued, not failed, and ends exactly as
/// an undisturbed run of the same job; meanwhile submissions answer 507 and readiness says why.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_requeues_the_running_job_and_refuses_submissions() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.workers = 1;
    config.queue_capacity = 8;
    config.checkpoint_steps = 5;
    let mut backend =
        willow_service::jobs::embedded::open(dir.path(), config.queue_capacity).expect("open");
    let (full, refused) = (
        Arc::new(AtomicBool::new(false)),
        Arc::new(AtomicUsize::new(0)),
    );
    backend.blobs = Arc::new(FullSwitch {
        inner: backend.blobs.clone(),
        full: full.clone(),
        refused: refused.clone(),
    });
    let (jobs, core) = Jobs::start_with(config, backend).await.expect("start");
    let base = serve(jobs, core).await;
    let client = reqwest::Client::new();
    assert_eq!(readyz(&client, &base).await.0, 200);

    // An earlier result, and a job to delete on the full disk.
    let kept = submit(&client, &base, &small_obj(), "steps=3").await.id();
    let doomed = submit(&client, &base, &small_obj(), "steps=3").await.id();
    for id in [&kept, &doomed] {
        poll_until(&client, &base, id, JOB_TIMEOUT, |v| {
            v["state"] == "succeeded"
        })
        .await;
    }
    let kept_before = result_vertices(&client, &base, &kept).await;

    let query = "steps=400&frame_interval=1&until_converged=false";
    let running = submit(&client, &base, &slow_obj(), query).await.id();
    poll_until(&client, &base, &running, JOB_TIMEOUT, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().is_some_and(|s| s >= 12)
    })
    .await;

    full.store(true, Ordering::SeqCst);
    assert_eq!(wait_ready(&client, &base, 503).await, "storage full");
    let requeued = poll_until(&client, &base, &running, JOB_TIMEOUT, |v| {
        v["state"] != "running"
    })
    .await;
    assert_eq!(
        requeued["state"], "queued",
        "re-queued, not failed: {requeued}"
    );
    assert!(refused.load(Ordering::SeqCst) >= 1);

    submit(&client, &base, &small_obj(), "steps=3")
        .await
        .assert_storage_full();
    // Reads and deletes go on.
    assert_eq!(result_vertices(&client, &base, &kept).await, kept_before);
    let res = client
        .delete(format!("{base}/v1/jobs/{doomed}"))
        .send()
        .await
        .expect("DELETE");
    assert_eq!(res.status().as_u16(), 204);
    let res = client
        .get(format!("{base}/v1/jobs/{doomed}"))
        .send()
        .await
        .expect("GET");
    assert_eq!(res.status().as_u16(), 404);

    // Room again: the probe (a real write in the data dir) clears it, the job resumes.
    full.store(false, Ordering::SeqCst);
    wait_ready(&client, &base, 200).await;
    let done = poll_until(&client, &base, &running, JOB_TIMEOUT, |v| {
        v["state"] != "running" && v["state"] != "queued"
    })
    .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"]["step"], 400);

    // The same job undisturbed ends on the same surface (resumed from its checkpoint).
    let reference = submit(&client, &base, &slow_obj(), query).await.id();
    poll_until(&client, &base, &reference, JOB_TIMEOUT, |v| {
        v["state"] == "succeeded"
    })
    .await;
    let (got, want) = (
        result_vertices(&client, &base, &running).await,
        result_vertices(&client, &base, &reference).await,
    );
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(&want) {
        for k in 0..3 {
            assert!(
                (g[k] - w[k]).abs() <= 1e-9 * (1.0 + w[k].abs()),
                "{g:?} vs {w:?}"
            );
        }
    }
}

/// A tmpfs mounted for the test, unmounted when dropped.
struct Tmpfs(PathBuf);

impl Tmpfs {
    /// `None` (with the reason) where mounting is not possible: not root, or no mount rights.
    fn mount(size_mib: u64) -> Result<Tmpfs, String> {
        let uid = std::process::Command::new("id")
            .arg("-u")
            .output()
            .map_err(|e| format!("cannot run `id -u`: {e}"))?;
        if String::from_utf8_lossy(&uid.stdout).trim() != "0" {
            return Err("not root: mounting a tmpfs needs root".into());
        }
        let dir = std::env::temp_dir().join(format!("willow-disk-full-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size_mib}m"), "tmpfs"])
            .arg(&dir)
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "mount refused (no CAP_SYS_ADMIN?): {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(Tmpfs(dir))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.0)
            .status();
        let _ = std::fs::remove_dir(&self.0);
    }
}

/// Write zeros to `path` until the file system refuses: the disk is then full to its last
/// block. Panics on any error other than a full disk.
fn fill(path: &Path) {
    let mut f = std::fs::File::create(path).expect("filler file");
    for chunk in [1 << 20, 4 << 10, 512] {
        let zeros = vec![0u8; chunk];
        loop {
            match f.write_all(&zeros).and_then(|()| f.flush()) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::StorageFull => break,
                Err(e) => panic!("filling {}: {e}", path.display()),
            }
        }
    }
}

/// A real full disk: a 32 MiB tmpfs filled to the last block while a job runs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_full_tmpfs_refuses_writes_keeps_reads_and_restarts() {
    let fs = match Tmpfs::mount(32) {
        Ok(fs) => fs,
        // Mounting needs root (CI has it). Elsewhere the test fails unless it is turned off
        // by name: it never passes having filled no disk.
        Err(why) if std::env::var("WILLOW_SKIP_TMPFS").as_deref() == Ok("1") => {
            eprintln!("skipped (WILLOW_SKIP_TMPFS=1): {why}");
            return;
        }
        Err(why) => panic!("a tmpfs could not be mounted ({why}); set WILLOW_SKIP_TMPFS=1 on a machine without root"),
    };
    let tweak = |c: &mut Config| c.checkpoint_steps = 5;
    let dir = tempfile::tempdir_in(&fs.0).expect("data dir on the tmpfs");
    let srv = start_in(dir, tweak).await;
    let kept = srv.submit_obj(&small_obj(), "steps=3").await.2["id"]
        .as_str()
        .expect("id")
        .to_string();
    let doomed = srv.submit_obj(&small_obj(), "steps=3").await.2["id"]
        .as_str()
        .expect("id")
        .to_string();
    for id in [&kept, &doomed] {
        srv.poll_until(id, JOB_TIMEOUT, |v| v["state"] == "succeeded")
            .await;
    }
    let kept_before = result_vertices(&srv.client, &srv.base, &kept).await;
    let (st, _, running) = srv
        .submit_obj(
            &slow_obj(),
            "steps=400&frame_interval=10&until_converged=false",
        )
        .await;
    assert_eq!(st, 202, "{running}");
    let running = running["id"].as_str().expect("id").to_string();
    srv.poll_until(&running, JOB_TIMEOUT, |v| {
        v["state"] == "running" && v["progress"]["step"].as_u64().is_some_and(|s| s >= 6)
    })
    .await;

    fill(&fs.0.join("filler-1"));
    // The job's next frame or checkpoint meets ENOSPC: re-queued, not failed.
    let requeued = srv
        .poll_until(&running, JOB_TIMEOUT, |v| v["state"] != "running")
        .await;
    assert_eq!(requeued["state"], "queued", "{requeued}");
    assert_eq!(
        wait_ready(&srv.client, &srv.base, 503).await,
        "storage full"
    );
    let (st, headers, body) = srv.submit_obj(&small_obj(), "steps=3").await;
    Submitted {
        status: st.as_u16(),
        headers,
        body,
    }
    .assert_storage_full();
    assert_eq!(
        result_vertices(&srv.client, &srv.base, &kept).await,
        kept_before
    );
    let res = srv
        .client
        .delete(srv.url(&format!("/v1/jobs/{doomed}")))
        .send()
        .await
        .expect("DELETE");
    assert_eq!(res.status().as_u16(), 204, "DELETE on a full disk");
    assert_eq!(srv.get(&format!("/v1/jobs/{doomed}")).await.status(), 404);

    // Restart on a disk full again (the delete freed a little): it starts and serves reads.
    let dir = srv.stop().await;
    fill(&fs.0.join("filler-2"));
    let srv = start_in(dir, tweak).await;
    assert_eq!(
        wait_ready(&srv.client, &srv.base, 503).await,
        "storage full"
    );
    assert_eq!(
        result_vertices(&srv.client, &srv.base, &kept).await,
        kept_before
    );
    let (st, job) = srv.get_json(&format!("/v1/jobs/{running}")).await;
    assert_eq!(st, 200);
    assert_eq!(job["state"], "queued", "{job}");

    // Room again: ready, and the job resumes and finishes.
    for f in ["filler-1", "filler-2"] {
        std::fs::remove_file(fs.0.join(f)).expect("remove filler");
    }
    wait_ready(&srv.client, &srv.base, 200).await;
    let done = srv
        .poll_until(&running, JOB_TIMEOUT, |v| {
            v["state"] != "running" && v["state"] != "queued"
        })
        .await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"]["step"], 400);
    srv.stop().await;
}
