//! Tenants on the NATS backend (issue 12), in process against a real nats-server: another
//! tenant's job is not found, idempotency keys are per tenant, quotas count one tenant, and the
//! per-tenant consumers make the queue fair: a burst of one tenant does not starve another.

mod nats_support;
mod service_http_support;

use nats_support::Nats;
use service_http_support::{
    assert_stored_upload_jobs_receive_no_mesh, obj, slow_obj, small_obj, spec,
};
use std::time::Duration;
use willow_service::jobs::nats::{connect, NatsOptions};
use willow_service::jobs::{Caller, Config, JobError, JobState, Jobs, Shutdown, TenantQuotas};

fn tenant(name: &str) -> Caller {
    Caller::new(name, "test").expect("tenant")
}

async fn start(nats: &Nats, dir: &std::path::Path, quotas: TenantQuotas) -> (Jobs, Shutdown) {
    start_with(nats, dir, quotas, |_| {}).await
}

async fn start_with(
    nats: &Nats,
    dir: &std::path::Path,
    quotas: TenantQuotas,
    tweak: impl FnOnce(&mut Config),
) -> (Jobs, Shutdown) {
    let mut config = Config::new(dir);
    config.workers = 1;
    config.queue_capacity = 32;
    config.quotas = quotas;
    tweak(&mut config);
    let backend = connect(&config, &NatsOptions::new(nats.url()))
        .await
        .expect("connect");
    Jobs::start_with(config, backend).await.expect("start")
}

async fn wait_running(jobs: &Jobs, who: &Caller, id: &str) {
    for _ in 0..400 {
        if jobs.get(who, id).await.expect("get").state == JobState::Running {
            return;
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    panic!("job {id} never started");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_tenants_are_isolated_and_the_queue_is_fair() {
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let (jobs, core) = start(
        &nats,
        &dir.path().join("node"),
        TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 8,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        },
    )
    .await;
    let (a, b) = (tenant("alpha"), tenant("beta.eu"));

    // A's long job holds the only worker; A then queues a burst, B one job.
    let running = jobs
        .submit(&a, obj(slow_obj()), spec(5000), Some("k".into()))
        .await
        .expect("running");
    wait_running(&jobs, &a, &running.id).await;
    let mut burst = Vec::new();
    for _ in 0..6 {
        burst.push(
            jobs.submit(&a, obj(small_obj()), spec(1), None)
                .await
                .expect("burst")
                .id,
        );
    }
    // A's quota of 8 live jobs: 7 are live, one more fits, the next is refused by name.
    burst.push(
        jobs.submit(&a, obj(small_obj()), spec(1), None)
            .await
            .expect("8th")
            .id,
    );
    match jobs.submit(&a, obj(small_obj()), spec(1), None).await {
        Err(JobError::QuotaExceeded {
            quota: "live_jobs",
            limit: 8,
            ..
        }) => {}
        other => panic!("expected the live_jobs quota, got {other:?}"),
    }
    // B's key `k` is B's own; B sees none of A's jobs.
    let single = jobs
        .submit(&b, obj(small_obj()), spec(1), Some("k".into()))
        .await
        .expect("B");
    assert_ne!(single.id, running.id);
    assert!(matches!(
        jobs.get(&b, &running.id).await,
        Err(JobError::NotFound(_))
    ));
    assert!(matches!(
        jobs.cancel(&b, &running.id).await,
        Err(JobError::NotFound(_))
    ));
    let (listed, _) = jobs.list(&b, None, 0, None).await.expect("list");
    let listed: Vec<&str> = listed.iter().map(|s| s.id.as_str()).collect();
    assert_eq!(listed, [single.id.as_str()]);

    jobs.cancel(&a, &running.id).await.expect("cancel");
    let b_done = jobs
        .wait(&b, &single.id, Duration::from_secs(120))
        .await
        .expect("wait B");
    assert_eq!(b_done.state, JobState::Succeeded, "{b_done:?}");
    let b_started = b_done.started_at.expect("started");
    let mut a_before_b = 0;
    for id in &burst {
        let s = jobs
            .wait(&a, id, Duration::from_secs(120))
            .await
            .expect("wait A");
        assert_eq!(s.state, JobState::Succeeded, "{s:?}");
        if s.started_at.expect("started") < b_started {
            a_before_b += 1;
        }
    }
    assert!(
        a_before_b <= 1,
        "B's job waited behind {a_before_b} of A's 7 queued jobs: the queue is not fair"
    );
    // Deleting: B cannot, A can.
    assert!(matches!(
        jobs.delete(&b, &burst[0]).await,
        Err(JobError::NotFound(_))
    ));
    jobs.delete(&a, &burst[0]).await.expect("A deletes its job");
    core.shutdown(Duration::from_secs(2)).await;
}

/// Quotas hold across API nodes: 16 submissions at once, half on each of two nodes, of jobs
/// that outlast the test, against a quota of 5 live jobs: exactly 5 are admitted (the check
/// and the count are one compare-and-set on the tenant's usage entry). A finished job frees
/// its unit. With the counters wiped, a restarted node recounts them from the records at
/// connect, and the quota holds again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_quotas_hold_across_nodes_and_are_recounted_at_connect() {
    use futures::StreamExt as _;
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let quotas = TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 5,
        max_stored_bytes: 0,
        uploads_per_minute: 0,
    };
    let (one, core_one) = start(&nats, &dir.path().join("one"), quotas.clone()).await;
    let (two, core_two) = start(&nats, &dir.path().join("two"), quotas.clone()).await;
    let a = tenant("alpha");
    let tasks: Vec<_> = (0..16)
        .map(|i| {
            let (jobs, a) = (if i % 2 == 0 { &one } else { &two }.clone(), a.clone());
            tokio::spawn(async move { jobs.submit(&a, obj(slow_obj()), spec(5000), None).await })
        })
        .collect();
    let (mut admitted, mut refused) = (Vec::new(), 0);
    for t in tasks {
        match t.await.expect("task") {
            Ok(s) => admitted.push(s.id),
            Err(JobError::QuotaExceeded {
                quota: "live_jobs", ..
            }) => refused += 1,
            Err(e) => panic!("expected admission or the live_jobs quota, got {e:?}"),
        }
    }
    assert_eq!((admitted.len(), refused), (5, 11), "{admitted:?}");
    let refused_now = |r: Result<willow_service::jobs::JobStatus, JobError>| {
        matches!(
            r,
            Err(JobError::QuotaExceeded {
                quota: "live_jobs",
                limit: 5,
                ..
            })
        )
    };

    // A finished job frees its unit, on either node.
    one.cancel(&a, &admitted[0]).await.expect("cancel");
    let done = one
        .wait(&a, &admitted[0], Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Cancelled);
    let sixth = two
        .submit(&a, obj(slow_obj()), spec(5000), None)
        .await
        .expect("room after the cancel");
    admitted.push(sixth.id);
    assert!(refused_now(
        one.submit(&a, obj(slow_obj()), spec(5000), None).await
    ));

    // Wipe the counters: the nodes running now would admit again; a node connecting recounts.
    let client = async_nats::connect(nats.url()).await.expect("client");
    let kv = async_nats::jetstream::new(client)
        .get_key_value(willow_service::jobs::nats::KV_BUCKET)
        .await
        .expect("bucket");
    let mut keys = kv.keys().await.expect("keys");
    let mut wiped = 0;
    while let Some(k) = keys.next().await {
        let k = k.expect("key");
        if k.starts_with("usage.") {
            kv.purge(&k).await.expect("purge");
            wiped += 1;
        }
    }
    assert_eq!(wiped, 1, "one tenant, one usage entry");
    core_two.shutdown(Duration::from_secs(2)).await;
    let (two, core_two) = start(&nats, &dir.path().join("two"), quotas).await;
    assert!(refused_now(
        two.submit(&a, obj(slow_obj()), spec(5000), None).await
    ));
    for id in &admitted[1..] {
        let _ = two.cancel(&a, id).await;
    }
    core_one.shutdown(Duration::from_secs(2)).await;
    core_two.shutdown(Duration::from_secs(2)).await;
}

/// The stored-bytes quota on NATS counts uploads and job inputs, and gets them back when a
/// job is deleted and when the sweeper retires expired jobs and uploads (on a node other
/// than the one that admitted them).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_stored_bytes_are_counted_and_given_back() {
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    // An upload's charge is its size; a job's, its input and what its frames, checkpoint
    // and result may store. Room for the upload and one job, or for two jobs.
    let size = small_obj().len() as u64;
    let job = size + service_http_support::small_plan(&spec(1));
    let quotas = TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 0,
        max_stored_bytes: 2 * job + size / 2,
        uploads_per_minute: 0,
    };
    // Node one's results and uploads expire 2 s after they finish or arrive; its own
    // sweeper (first run after a minute) never retires them here.
    let (one, core_one) = start_with(&nats, &dir.path().join("one"), quotas.clone(), |c| {
        c.result_ttl = Duration::from_secs(2);
    })
    .await;
    let a = tenant("alpha");
    let bytes_refused = |r: Result<willow_service::jobs::JobStatus, JobError>, used: u64| match r {
        Err(JobError::QuotaExceeded {
            quota: "stored_bytes",
            used: Some(u),
            ..
        }) => assert_eq!(u, used),
        other => panic!("expected the stored_bytes quota at {used}, got {other:?}"),
    };
    one.store_upload(&a, small_obj().into(), willow::mesh::io::Format::Obj)
        .await
        .expect("upload");
    let first = one
        .submit(&a, obj(small_obj()), spec(1), None)
        .await
        .expect("within the bytes");
    bytes_refused(
        one.submit(&a, obj(small_obj()), spec(1), None).await,
        size + job,
    );
    one.wait(&a, &first.id, Duration::from_secs(60))
        .await
        .expect("wait");
    one.delete(&a, &first.id).await.expect("delete");
    let second = one
        .submit(&a, obj(small_obj()), spec(1), None)
        .await
        .expect("room after the delete");
    one.wait(&a, &second.id, Duration::from_secs(60))
        .await
        .expect("wait");
    bytes_refused(
        one.submit(&a, obj(small_obj()), spec(1), None).await,
        size + job,
    );
    core_one.shutdown(Duration::from_secs(2)).await;

    // Another node, whose sweeper retires the finished job and the upload once expired.
    let (two, core_two) = start_with(&nats, &dir.path().join("two"), quotas, |c| {
        c.sweep_interval = Duration::from_millis(200);
    })
    .await;
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let mut admitted = Vec::new();
    while admitted.len() < 2 {
        match two.submit(&a, obj(small_obj()), spec(1), None).await {
            Ok(s) => admitted.push(s.id),
            Err(JobError::QuotaExceeded {
                quota: "stored_bytes",
                ..
            }) if std::time::Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("room after the sweep: {e:?}"),
        }
    }
    core_two.shutdown(Duration::from_secs(2)).await;
}

/// On NATS as on SQLite (tests/service_tenants.rs): a job made from a stored upload receives
/// no mesh, so it neither counts toward `uploads_per_minute` nor is refused by it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_jobs_from_a_stored_upload_do_not_count_as_meshes_received() {
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let quotas = TenantQuotas {
        server_max_stored_bytes: 0,
        max_live_jobs: 0,
        max_stored_bytes: 0,
        uploads_per_minute: 2,
    };
    let (jobs, core) = start(&nats, &dir.path().join("node"), quotas).await;
    assert_stored_upload_jobs_receive_no_mesh(&jobs, &tenant("alpha")).await;
    core.shutdown(Duration::from_secs(2)).await;
}

/// Downloads rendered and stored count in `stored_bytes` once (the names in the job's record),
/// are served from memory when the quota has no room for them, and are given back with their
/// job (deleted or expired), as on the embedded backend.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_rendered_downloads_count_in_stored_bytes() {
    use service_http_support::rendered::{
        assert_rendered_downloads_count_in_stored_bytes, RENDERED_QUOTA,
    };
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let ttl = Duration::from_secs(30);
    let (jobs, core) = start_with(
        &nats,
        &dir.path().join("node"),
        TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: RENDERED_QUOTA,
            uploads_per_minute: 0,
        },
        |c| {
            c.result_ttl = ttl;
            c.sweep_interval = Duration::from_millis(500);
        },
    )
    .await;
    assert_rendered_downloads_count_in_stored_bytes(&jobs, &tenant("alpha"), ttl).await;
    core.shutdown(Duration::from_secs(1)).await;
}

/// Kept frames count in `stored_bytes` on NATS as on SQLite: the job's objects in the blob
/// bucket, measured, stay within the tenant's quota.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_kept_frames_stay_within_the_stored_bytes_quota() {
    use futures::StreamExt;
    use service_http_support::kept_frames::{
        assert_kept_frames_stay_within_the_quota, FRAMES_QUOTA,
    };
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let (jobs, core) = start(
        &nats,
        &dir.path().join("node"),
        TenantQuotas {
            server_max_stored_bytes: 0,
            max_live_jobs: 0,
            max_stored_bytes: FRAMES_QUOTA,
            uploads_per_minute: 0,
        },
    )
    .await;
    let client = async_nats::connect(nats.url()).await.expect("connect");
    let bucket = async_nats::jetstream::new(client)
        .get_object_store(willow_service::jobs::nats::OBJECT_BUCKET)
        .await
        .expect("the blob bucket");
    let measure = |id: String| {
        let bucket = bucket.clone();
        async move {
            let prefix = format!("jobs/{id}/");
            let mut list = bucket.list().await.expect("list");
            let mut bytes = 0u64;
            while let Some(info) = list.next().await {
                let info = info.expect("an object");
                if info.name.starts_with(&prefix) && !info.deleted {
                    bytes += info.size as u64;
                }
            }
            bytes
        }
    };
    assert_kept_frames_stay_within_the_quota(&jobs, &tenant("alpha"), measure).await;
    core.shutdown(Duration::from_secs(1)).await;
}

/// The server's disk budget over NATS is the cluster's: tenant A fills it through node one,
/// and tenant B is refused on node two, named `server_stored_bytes`; A's delete gives B room.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_server_disk_budget_is_shared_by_tenants_and_nodes() {
    let dir = tempfile::tempdir().expect("dir");
    let nats = Nats::start(dir.path());
    let size = small_obj().len() as u64;
    let job = size + service_http_support::small_plan(&spec(1));
    let budget = 2 * job + size - 1;
    let quotas = TenantQuotas {
        server_max_stored_bytes: budget,
        max_live_jobs: 0,
        max_stored_bytes: 100 * job,
        uploads_per_minute: 0,
    };
    let (one, core_one) = start_with(&nats, &dir.path().join("one"), quotas.clone(), |_| {}).await;
    let (two, core_two) = start_with(&nats, &dir.path().join("two"), quotas, |_| {}).await;
    let (a, b) = (tenant("alpha"), tenant("beta"));
    let mut ids = Vec::new();
    for _ in 0..2 {
        ids.push(
            one.submit(&a, obj(small_obj()), spec(1), None)
                .await
                .expect("within the budget")
                .id,
        );
    }
    match two.submit(&b, obj(small_obj()), spec(1), None).await {
        Err(JobError::QuotaExceeded {
            quota: "server_stored_bytes",
            limit,
            used: Some(used),
            ..
        }) => {
            assert_eq!(limit, budget);
            assert_eq!(used, 2 * job, "A's two jobs, admitted by the other node");
        }
        other => panic!("expected the server's disk budget, got {other:?}"),
    }
    assert!(matches!(
        two.store_upload(&b, small_obj().into(), willow::mesh::io::Format::Obj)
            .await,
        Err(JobError::QuotaExceeded {
            quota: "server_stored_bytes",
            ..
        })
    ));
    one.wait(&a, &ids[0], Duration::from_secs(60))
        .await
        .expect("wait");
    one.delete(&a, &ids[0]).await.expect("delete");
    two.submit(&b, obj(small_obj()), spec(1), None)
        .await
        .expect("room after A's delete");
    core_one.shutdown(Duration::from_secs(2)).await;
    core_two.shutdown(Duration::from_secs(2)).await;
}
