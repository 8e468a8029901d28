//! Tenants on the NATS backend (issue 12), in process against a real nats-server: another
//! tenant's job is not found, idempotency keys are per tenant, quotas count one tenant, and the
//! per-tenant consumers make the queue fair: a burst of one tenant does not starve another.

mod nats_support;
mod service_http_support;

use nats_support::Nats;
use service_http_support::{obj, slow_obj, small_obj, spec};
use std::time::Duration;
use willow::jobs::nats::{connect, NatsOptions};
use willow::jobs::{Caller, Config, JobError, JobState, Jobs, Shutdown, TenantQuotas};

fn tenant(name: &str) -> Caller {
    Caller::new(name, "test").expect("tenant")
}

async fn start(nats: &Nats, dir: &std::path::Path, quotas: TenantQuotas) -> (Jobs, Shutdown) {
    let mut config = Config::new(dir);
    config.workers = 1;
    config.queue_capacity = 32;
    config.quotas = quotas;
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
