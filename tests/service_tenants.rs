//! Tenants in the job core (issue 12), without any transport: isolation of every call, per-tenant
//! idempotency keys and uploads, the quotas and their names, and the queue's fair order. The
//! transports' own tests (tests/service_auth/) show the same through HTTP and gRPC.

mod service_http_support;

use service_http_support::{
    assert_stored_upload_jobs_receive_no_mesh, obj, slow_obj, small_obj, small_plan, spec, Capture,
};
use std::time::Duration;
use willow::mesh::io::Format;
use willow_service::jobs::{Caller, Config, JobError, JobState, Jobs, TenantQuotas, UploadRef};

fn tenant(name: &str) -> Caller {
    Caller::new(name, &format!("{name}-key")).expect("a valid tenant id")
}

fn config(dir: &std::path::Path, tweak: impl FnOnce(&mut Config)) -> Config {
    let mut c = Config::new(dir);
    c.workers = 1;
    c.queue_capacity = 32;
    tweak(&mut c);
    c
}

fn is_not_found<T: std::fmt::Debug>(r: Result<T, JobError>) -> bool {
    matches!(r, Err(JobError::NotFound(_)))
}

#[test]
fn tenant_ids_are_checked() {
    assert!(Caller::new("acme-prod_1.eu", "k").is_ok());
    for bad in ["", "a/b", "a b", "a.b>", "ä", &"x".repeat(65)] {
        assert!(Caller::new(bad, "k").is_err(), "{bad:?} must be refused");
    }
}

/// A job made from a stored upload receives no mesh: the upload counted toward
/// `uploads_per_minute` when it arrived, and its jobs neither count again nor are refused by
/// that quota (they used to count as meshes received, so a tenant reached its limit at half
/// the meshes it sent).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_from_a_stored_upload_do_not_count_as_meshes_received() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: 0,
            uploads_per_minute: 2,
        }
    }))
    .await
    .expect("start");
    assert_stored_upload_jobs_receive_no_mesh(&jobs, &tenant("alpha")).await;
    core.shutdown(Duration::from_secs(1)).await;
}

/// Every call of tenant B on tenant A's job answers exactly as for a job that does not exist;
/// A's own calls keep working. Also after the job expired: B sees `NotFound`, A `Gone`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_tenants_job_is_not_found_by_every_call() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.result_ttl = Duration::from_secs(3)
    }))
    .await
    .expect("start");
    let (a, b) = (tenant("alpha"), tenant("beta"));
    let job = jobs
        .submit(&a, obj(small_obj()), spec(2), None)
        .await
        .expect("submit");
    assert_eq!(job.tenant, "alpha");
    let done = jobs
        .wait(&a, &job.id, Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded);

    assert!(is_not_found(jobs.get(&b, &job.id).await));
    assert!(is_not_found(jobs.watch(&b, &job.id, 0).await.map(|_| ())));
    assert!(is_not_found(jobs.frames(&b, &job.id, 0, 10).await));
    assert!(is_not_found(
        jobs.frame_mesh(&b, &job.id, 0, Format::Obj).await
    ));
    assert!(is_not_found(jobs.result(&b, &job.id, Format::Obj).await));
    assert!(is_not_found(
        jobs.wait(&b, &job.id, Duration::from_millis(10)).await
    ));
    // Cancel and delete: not `Conflict` (which would tell B the job exists).
    assert!(is_not_found(jobs.cancel(&b, &job.id).await));
    assert!(is_not_found(jobs.delete(&b, &job.id).await));
    let (listed, next) = jobs.list(&b, None, 0, None).await.expect("list");
    assert!(listed.is_empty() && next.is_none(), "{listed:?}");

    // A still has everything B tried to touch.
    assert_eq!(
        jobs.get(&a, &job.id).await.expect("get").state,
        JobState::Succeeded
    );
    assert!(jobs.result(&a, &job.id, Format::Obj).await.is_ok());
    let (listed, _) = jobs.list(&a, None, 0, None).await.expect("list");
    assert_eq!(listed.len(), 1);

    // Expired: the owner learns it is gone, anyone else still sees nothing.
    tokio::time::sleep(Duration::from_secs(4)).await;
    assert!(matches!(
        jobs.get(&a, &job.id).await,
        Err(JobError::Gone(_))
    ));
    assert!(is_not_found(jobs.get(&b, &job.id).await));
    core.shutdown(Duration::from_secs(1)).await;
}

/// Idempotency keys and uploads belong to their tenant: the same key from two tenants makes two
/// jobs, and an upload id is no use to another tenant.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idempotency_keys_and_uploads_are_per_tenant() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |_| {}))
        .await
        .expect("start");
    let (a, b) = (tenant("alpha"), tenant("beta"));
    let key = Some("order-42".to_string());
    let ja = jobs
        .submit(&a, obj(small_obj()), spec(1), key.clone())
        .await
        .expect("a");
    let jb = jobs
        .submit(&b, obj(small_obj()), spec(1), key.clone())
        .await
        .expect("b: the same key is B's own");
    assert_ne!(ja.id, jb.id, "one key, two tenants, two jobs");
    assert_eq!(jb.tenant, "beta");
    let again = jobs
        .submit(&a, obj(small_obj()), spec(1), key.clone())
        .await
        .expect("a again");
    assert_eq!(again.id, ja.id, "A's repeat finds A's job");
    // B's key with another request is B's mismatch, whatever A sent.
    assert!(matches!(
        jobs.submit(&b, obj(small_obj()), spec(2), key).await,
        Err(JobError::IdempotencyMismatch(_))
    ));

    let upload = jobs
        .store_upload(&a, bytes::Bytes::from(small_obj()), Format::Obj)
        .await
        .expect("upload");
    let stored = |id: &str| UploadRef::Stored {
        upload_id: id.to_string(),
    };
    assert!(matches!(
        jobs.submit(&b, stored(&upload), spec(1), None).await,
        Err(JobError::UploadNotFound(_))
    ));
    let from_upload = jobs
        .submit(&a, stored(&upload), spec(1), None)
        .await
        .expect("A uses its upload");
    assert_eq!(from_upload.tenant, "alpha");
    core.shutdown(Duration::from_secs(1)).await;
}

/// Each quota refuses with its own name, counts only its tenant, and frees up again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn quotas_are_per_tenant_and_named() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 2,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        }
    }))
    .await
    .expect("start");
    let (a, b) = (tenant("alpha"), tenant("beta"));
    // Two live jobs (one running, one queued: the single worker is busy with the first).
    let first = jobs
        .submit(&a, obj(slow_obj()), spec(5000), None)
        .await
        .expect("1st");
    jobs.submit(&a, obj(small_obj()), spec(1), None)
        .await
        .expect("2nd");
    match jobs.submit(&a, obj(small_obj()), spec(1), None).await {
        Err(JobError::QuotaExceeded {
            quota: "live_jobs",
            limit: 2,
            used: Some(2),
            retry_after_secs,
        }) => assert!(retry_after_secs >= 1),
        other => panic!("expected the live_jobs quota, got {other:?}"),
    }
    // Another tenant is not held back by A's quota.
    jobs.submit(&b, obj(small_obj()), spec(1), None)
        .await
        .expect("B has its own quota");
    // A cancelled job is no longer live: A may submit again.
    jobs.cancel(&a, &first.id).await.expect("cancel");
    jobs.wait(&a, &first.id, Duration::from_secs(60))
        .await
        .expect("wait");
    jobs.submit(&a, obj(small_obj()), spec(1), None)
        .await
        .expect("room again");
    core.shutdown(Duration::from_secs(1)).await;

    // Uploads per minute (jobs and stored uploads both count) and stored bytes.
    let dir = tempfile::tempdir().expect("dir");
    let size = small_obj().len() as u64;
    // A job's charge: its input and what its frames, checkpoint and result may store.
    let job = size + small_plan(&spec(1));
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: 0,
            uploads_per_minute: 3,
        }
    }))
    .await
    .expect("start");
    jobs.store_upload(&a, bytes::Bytes::from(small_obj()), Format::Obj)
        .await
        .expect("1");
    for n in 2..=3 {
        jobs.submit(&a, obj(small_obj()), spec(1), None)
            .await
            .unwrap_or_else(|e| panic!("{n}: {e}"));
    }
    let refused = jobs.submit(&a, obj(small_obj()), spec(1), None).await;
    assert!(
        matches!(
            refused,
            Err(JobError::QuotaExceeded {
                quota: "uploads_per_minute",
                limit: 3,
                retry_after_secs: 60,
                ..
            })
        ),
        "{refused:?}"
    );
    assert!(matches!(
        jobs.store_upload(&a, bytes::Bytes::from(small_obj()), Format::Obj)
            .await,
        Err(JobError::QuotaExceeded {
            quota: "uploads_per_minute",
            ..
        })
    ));
    jobs.submit(&b, obj(small_obj()), spec(1), None)
        .await
        .expect("B's minute is its own");
    core.shutdown(Duration::from_secs(1)).await;

    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: 2 * job + job / 2,
            uploads_per_minute: 0,
        }
    }))
    .await
    .expect("start");
    let mut ids = Vec::new();
    for _ in 0..2 {
        ids.push(
            jobs.submit(&a, obj(small_obj()), spec(1), None)
                .await
                .expect("within the bytes")
                .id,
        );
    }
    let refused = jobs.submit(&a, obj(small_obj()), spec(1), None).await;
    match refused {
        Err(JobError::QuotaExceeded {
            quota: "stored_bytes",
            limit,
            used: Some(used),
            ..
        }) => {
            assert_eq!(limit, 2 * job + job / 2);
            assert_eq!(used, 2 * job, "the bytes of A's two jobs");
        }
        other => panic!("expected the stored_bytes quota, got {other:?}"),
    }
    // Deleting a finished job gives its bytes back.
    jobs.wait(&a, &ids[0], Duration::from_secs(60))
        .await
        .expect("wait");
    jobs.delete(&a, &ids[0]).await.expect("delete");
    jobs.submit(&a, obj(small_obj()), spec(1), None)
        .await
        .expect("room after the delete");
    core.shutdown(Duration::from_secs(1)).await;
}

/// One worker, tenant A queues a burst behind its running job, then B queues one job: B's job
/// runs right after A's running one, not after A's whole burst.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_one_tenant_does_not_starve_another() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |_| {}))
        .await
        .expect("start");
    let (a, b) = (tenant("alpha"), tenant("beta"));
    let running = jobs
        .submit(&a, obj(slow_obj()), spec(5000), None)
        .await
        .expect("running");
    // Let the worker take it, so the burst below waits in the queue.
    for _ in 0..200 {
        if jobs.get(&a, &running.id).await.expect("get").state == JobState::Running {
            break;
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    let mut burst = Vec::new();
    for _ in 0..6 {
        burst.push(
            jobs.submit(&a, obj(small_obj()), spec(1), None)
                .await
                .expect("burst")
                .id,
        );
    }
    let single = jobs
        .submit(&b, obj(small_obj()), spec(1), None)
        .await
        .expect("B");
    jobs.cancel(&a, &running.id).await.expect("cancel");
    let b_done = jobs
        .wait(&b, &single.id, Duration::from_secs(60))
        .await
        .expect("wait B");
    assert_eq!(b_done.state, JobState::Succeeded);
    let b_started = b_done.started_at.expect("started");
    let mut a_before_b = 0;
    for id in &burst {
        let s = jobs
            .wait(&a, id, Duration::from_secs(60))
            .await
            .expect("wait A");
        if s.started_at.expect("started") < b_started {
            a_before_b += 1;
        }
    }
    assert!(
        a_before_b <= 1,
        "B's job waited behind {a_before_b} of A's burst: the queue is not fair"
    );
    core.shutdown(Duration::from_secs(1)).await;
}

/// Submissions of one tenant racing for the last units of its quota: the count and the insert
/// are one transaction, so exactly the quota is accepted (no admission lock is needed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_submissions_do_not_overshoot_a_quota() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 5,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        }
    }))
    .await
    .expect("start");
    let a = tenant("alpha");
    let tasks: Vec<_> = (0..24)
        .map(|_| {
            let (jobs, a) = (jobs.clone(), a.clone());
            tokio::spawn(async move { jobs.submit(&a, obj(slow_obj()), spec(5000), None).await })
        })
        .collect();
    let (mut accepted, mut refused) = (Vec::new(), 0);
    for t in tasks {
        match t.await.expect("task") {
            Ok(s) => accepted.push(s.id),
            Err(JobError::QuotaExceeded {
                quota: "live_jobs", ..
            }) => refused += 1,
            Err(e) => panic!("unexpected refusal: {e}"),
        }
    }
    assert_eq!(accepted.len(), 5, "exactly the quota is accepted");
    assert_eq!(refused, 19);
    for id in &accepted {
        jobs.cancel(&a, id).await.expect("cancel");
    }
    core.shutdown(Duration::from_secs(1)).await;
}

/// Create, cancel and delete each log one audit line naming the tenant, the caller and the job.
#[tokio::test]
async fn audit_lines_for_create_cancel_and_delete() {
    let capture = Capture::default();
    let subscriber = tracing_subscriber::fmt()
        .with_writer(capture.clone())
        .json()
        .finish();
    // A current-thread runtime: the core's calls run on this thread, under this subscriber.
    let _guard = tracing::subscriber::set_default(subscriber);
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |_| {}))
        .await
        .expect("start");
    let a = tenant("alpha");
    let job = jobs
        .submit(&a, obj(slow_obj()), spec(5000), None)
        .await
        .expect("submit");
    jobs.cancel(&a, &job.id).await.expect("cancel");
    jobs.wait(&a, &job.id, Duration::from_secs(60))
        .await
        .expect("wait");
    jobs.delete(&a, &job.id).await.expect("delete");
    // Refused calls (another tenant) change nothing and are not audited as changes.
    let _ = jobs.delete(&tenant("beta"), &job.id).await;
    core.shutdown(Duration::from_secs(1)).await;

    let audit: Vec<serde_json::Value> = capture
        .text()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["target"] == "audit")
        .collect();
    let actions: Vec<&str> = audit
        .iter()
        .filter_map(|v| v["fields"]["action"].as_str())
        .collect();
    assert_eq!(actions, ["create", "cancel", "delete"], "{audit:?}");
    for line in &audit {
        assert_eq!(line["fields"]["tenant"], "alpha", "{line}");
        assert_eq!(line["fields"]["subject"], "alpha-key", "{line}");
        assert_eq!(line["fields"]["job_id"], job.id.as_str(), "{line}");
    }
}

/// Downloads rendered and stored count in `stored_bytes` once, are served from memory when the
/// quota has no room for them, and are given back with their job (deleted or expired).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rendered_downloads_count_in_stored_bytes() {
    use service_http_support::rendered::{
        assert_rendered_downloads_count_in_stored_bytes, RENDERED_QUOTA,
    };
    let dir = tempfile::tempdir().expect("dir");
    let ttl = Duration::from_secs(30);
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: RENDERED_QUOTA,
            uploads_per_minute: 0,
        };
        c.result_ttl = ttl;
        c.sweep_interval = Duration::from_millis(200);
    }))
    .await
    .expect("start");
    assert_rendered_downloads_count_in_stored_bytes(&jobs, &tenant("alpha"), ttl).await;
    core.shutdown(Duration::from_secs(1)).await;
}

/// Kept frames count in `stored_bytes` (issue 42 item 1): the job's files in the data dir,
/// measured, stay within the tenant's quota.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kept_frames_stay_within_the_stored_bytes_quota() {
    use service_http_support::kept_frames::{
        assert_kept_frames_stay_within_the_quota, FRAMES_QUOTA,
    };
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: FRAMES_QUOTA,
            uploads_per_minute: 0,
        };
    }))
    .await
    .expect("start");
    let root = dir.path().to_path_buf();
    let measure = |id: String| {
        let job_dir = root.join("jobs").join(id);
        async move { files_bytes(&job_dir) }
    };
    assert_kept_frames_stay_within_the_quota(&jobs, &tenant("alpha"), measure).await;
    core.shutdown(Duration::from_secs(1)).await;
}

/// The bytes of every file under `dir`.
fn files_bytes(dir: &std::path::Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => files_bytes(&e.path()),
            _ => e.metadata().map_or(0, |m| m.len()),
        })
        .sum()
}

/// The server's disk budget is shared: tenant A, within its own quota, fills it; then B (with
/// nothing stored) is refused too, named `server_stored_bytes`, for jobs and uploads alike;
/// deleting A's job gives the room back to B.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_disk_budget_is_shared_by_every_tenant() {
    let dir = tempfile::tempdir().expect("dir");
    let size = small_obj().len() as u64;
    let job = size + small_plan(&spec(1));
    // Two of A's jobs fit, and then not even an upload more.
    let budget = 2 * job + size - 1;
    let (jobs, core) = Jobs::start(config(dir.path(), |c| {
        c.quotas = TenantQuotas {
            server_max_stored_bytes: budget,
            max_live_jobs: 0,
            max_stored_bytes: 100 * job,
            uploads_per_minute: 0,
        }
    }))
    .await
    .expect("start");
    let (a, b) = (tenant("alpha"), tenant("beta"));
    let mut ids = Vec::new();
    for _ in 0..2 {
        ids.push(
            jobs.submit(&a, obj(small_obj()), spec(1), None)
                .await
                .expect("within the budget")
                .id,
        );
    }
    fn is_server_budget<T>(r: &Result<T, JobError>, budget: u64, used_by_a: u64) -> bool {
        matches!(
            r,
            Err(JobError::QuotaExceeded {
                quota: "server_stored_bytes",
                limit,
                used: Some(used),
                ..
            }) if *limit == budget && *used == used_by_a
        )
    }
    let refused = jobs.submit(&b, obj(small_obj()), spec(1), None).await;
    assert!(
        is_server_budget(&refused, budget, 2 * job),
        "B's job: {refused:?}"
    );
    let refused = jobs
        .store_upload(&b, bytes::Bytes::from(small_obj()), Format::Obj)
        .await;
    assert!(
        is_server_budget(&refused, budget, 2 * job),
        "B's upload: {refused:?}"
    );
    // 507 and RESOURCE_EXHAUSTED at the edge, not the tenant's 429.
    let statuses = willow_service::api::status::of_error(refused.as_ref().expect_err("refused"));
    assert_eq!(statuses.http.as_u16(), 507);
    assert_eq!(statuses.grpc, tonic::Code::ResourceExhausted);
    // A's finished job deleted: its bytes are the room B gets.
    jobs.wait(&a, &ids[0], Duration::from_secs(60))
        .await
        .expect("wait");
    jobs.delete(&a, &ids[0]).await.expect("delete");
    jobs.submit(&b, obj(small_obj()), spec(1), None)
        .await
        .expect("room after A's delete");
    core.shutdown(Duration::from_secs(1)).await;
}
