//! The job core without any transport: fan-out and replay, slow watchers, deadline, graceful
//! shutdown with re-queue, restart recovery.

mod service_http_support;

use futures::StreamExt;
use service_http_support::{obj, obj_vertices, slow_obj, small_obj, spec};
use std::time::Duration;
use willow::mesh::io::Format;
use willow_service::jobs::{Caller, Config, JobEvent, JobSpec, JobState, Jobs, UploadRef};

/// Every call here is the default tenant's, as with `--auth none`.
fn me() -> Caller {
    Caller::anonymous()
}

fn config(dir: &std::path::Path) -> Config {
    let mut c = Config::new(dir);
    c.workers = 1;
    c.queue_capacity = 8;
    c
}

/// Collect a watch stream to its end; returns (frame steps, final status state).
async fn collect(
    stream: impl futures::Stream<Item = JobEvent>,
    per_event_delay: Duration,
) -> (Vec<usize>, Option<JobState>) {
    let mut stream = Box::pin(stream);
    let (mut steps, mut done) = (Vec::new(), None);
    while let Some(ev) = tokio::time::timeout(Duration::from_secs(120), stream.next())
        .await
        .expect("events keep coming")
    {
        match ev {
            JobEvent::Frame(f) => steps.push(f.step),
            JobEvent::Done(s) => done = Some(s.state),
            JobEvent::State(_) => {}
        }
        if !per_event_delay.is_zero() {
            tokio::time::sleep(per_event_delay).await;
        }
    }
    (steps, done)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn many_watchers_each_see_every_step_once_even_when_slow() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    // More steps than the live channel holds (128), so the slow watcher must lag and resume
    // from the store.
    let steps = 300;
    let job = jobs
        .submit(
            &me(),
            obj(small_obj()),
            JobSpec {
                include_positions: false,
                ..spec(steps)
            },
            None,
        )
        .await
        .expect("submit");
    let fast = jobs.watch(&me(), &job.id, 0).await.expect("watch");
    let slow = jobs.watch(&me(), &job.id, 0).await.expect("watch");
    let fast = tokio::spawn(collect(fast, Duration::ZERO));
    let slow = tokio::spawn(collect(slow, Duration::from_millis(3)));
    let (fast_steps, fast_done) = fast.await.expect("fast watcher");
    let (slow_steps, slow_done) = slow.await.expect("slow watcher");
    let expected: Vec<usize> = (0..=steps).collect();
    assert_eq!(fast_steps, expected);
    assert_eq!(
        slow_steps, expected,
        "a slow watcher still gets every step, in order"
    );
    assert_eq!(fast_done, Some(JobState::Succeeded));
    assert_eq!(slow_done, Some(JobState::Succeeded));

    // A late watcher replays from any step.
    let late = jobs.watch(&me(), &job.id, 290).await.expect("watch");
    let (late_steps, late_done) = collect(late, Duration::ZERO).await;
    assert_eq!(late_steps, (290..=steps).collect::<Vec<_>>());
    assert_eq!(late_done, Some(JobState::Succeeded));

    let (page, next) = jobs.frames(&me(), &job.id, 0, 100).await.expect("frames");
    assert_eq!(page.len(), 100);
    assert_eq!(next, Some(100));
    assert!(page.iter().enumerate().all(|(i, m)| m.step == i));
    core.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deadline_fails_a_job_between_steps() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    let job = jobs
        .submit(
            &me(),
            obj(slow_obj()),
            JobSpec {
                deadline_secs: Some(0.5),
                ..spec(5000)
            },
            None,
        )
        .await
        .expect("submit");
    let done = jobs
        .wait(&me(), &job.id, Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Failed, "{done:?}");
    assert_eq!(done.error_code.as_deref(), Some("deadline_exceeded"));
    assert!(done.step < 5000);
    let t = done.finished_at.expect("finished") - done.created_at;
    assert!(t < 30_000, "stopped soon after the deadline, took {t} ms");
    core.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_checkpoints_running_jobs_and_restart_resumes_them() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    let running = jobs
        .submit(&me(), obj(slow_obj()), spec(5000), None)
        .await
        .expect("submit");
    let queued = jobs
        .submit(&me(), obj(small_obj()), spec(3), None)
        .await
        .expect("submit");
    // Wait until the first job is running and has made progress.
    let mut events = Box::pin(jobs.watch(&me(), &running.id, 0).await.expect("watch"));
    while let Some(ev) = events.next().await {
        if matches!(ev, JobEvent::Frame(ref f) if f.step >= 1) {
            break;
        }
    }
    drop(events);
    // Zero grace: the running job is stopped at its next step, checkpointed and re-queued.
    core.shutdown(Duration::ZERO).await;
    assert!(!jobs.is_ready());
    let s = jobs.get(&me(), &running.id).await.expect("get");
    assert_eq!(s.state, JobState::Queued, "re-queued, not lost: {s:?}");
    assert!(s.step >= 1, "keeps its progress: {s:?}");
    let err = jobs.submit(&me(), obj(small_obj()), spec(1), None).await;
    assert!(matches!(
        err,
        Err(willow_service::jobs::JobError::ShuttingDown)
    ));
    drop(jobs);

    // Restart on the same data dir: both jobs are there and run (the short one first would
    // be wrong: order is kept).
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("restart");
    let q = jobs
        .wait(&me(), &queued.id, Duration::from_secs(1))
        .await
        .expect("get");
    assert_ne!(
        q.state,
        JobState::Succeeded,
        "the re-queued long job runs first"
    );
    // It resumes where it stopped: every step once, in order, from 0 for a new watcher, and
    // the first step run after the restart follows the checkpoint.
    let mut events = Box::pin(jobs.watch(&me(), &running.id, 0).await.expect("watch"));
    let mut next = 0;
    while let Some(ev) = events.next().await {
        if let JobEvent::Frame(f) = ev {
            assert_eq!(f.step, next, "steps complete and ordered");
            next += 1;
            if f.step > s.step + 2 {
                break;
            }
        }
    }
    drop(events);
    assert!(
        jobs.metrics_text().contains("willow_jobs_resumed_total 1"),
        "resumed from its checkpoint, not restarted"
    );
    jobs.cancel(&me(), &running.id)
        .await
        .expect("cancel the long one");
    let r = jobs
        .wait(&me(), &running.id, Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(r.state, JobState::Cancelled);
    let q = jobs
        .wait(&me(), &queued.id, Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(q.state, JobState::Succeeded);
    core.shutdown(Duration::from_secs(1)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stored_uploads_idempotency_and_errors_in_core_terms() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    let upload = jobs
        .store_upload(&me(), bytes::Bytes::from(small_obj()), Format::Obj)
        .await
        .expect("store upload");
    let a = jobs
        .submit(
            &me(),
            UploadRef::Stored {
                upload_id: upload.clone(),
            },
            spec(2),
            Some("k1".into()),
        )
        .await
        .expect("submit stored");
    let again = jobs
        .submit(
            &me(),
            UploadRef::Stored { upload_id: upload },
            spec(2),
            Some("k1".into()),
        )
        .await
        .expect("idempotent");
    assert_eq!(a.id, again.id);
    let mismatch = jobs
        .submit(&me(), obj(small_obj()), spec(3), Some("k1".into()))
        .await;
    assert!(matches!(
        mismatch,
        Err(willow_service::jobs::JobError::IdempotencyMismatch(_))
    ));
    let missing = jobs
        .submit(
            &me(),
            UploadRef::Stored {
                upload_id: "nope".into(),
            },
            spec(2),
            None,
        )
        .await;
    assert!(matches!(
        missing,
        Err(willow_service::jobs::JobError::UploadNotFound(_))
    ));
    let bad = jobs
        .store_upload(&me(), bytes::Bytes::from_static(b"f 1 2 3\n"), Format::Obj)
        .await;
    assert!(
        matches!(bad, Err(willow_service::jobs::JobError::InvalidMesh(_))),
        "{bad:?}"
    );
    let done = jobs
        .wait(&me(), &a.id, Duration::from_secs(60))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded);
    assert!(matches!(
        jobs.cancel(&me(), &a.id).await,
        Err(willow_service::jobs::JobError::Conflict(_))
    ));
    let mesh = jobs
        .result(&me(), &a.id, Format::Obj)
        .await
        .expect("result");
    assert!(!mesh.is_empty());
    assert!(matches!(
        jobs.frame_mesh(&me(), &a.id, 99, Format::Obj).await,
        Err(willow_service::jobs::JobError::FrameNotFound { .. })
    ));
    jobs.delete(&me(), &a.id).await.expect("delete");
    assert!(matches!(
        jobs.get(&me(), &a.id).await,
        Err(willow_service::jobs::JobError::NotFound(_))
    ));
    core.shutdown(Duration::from_secs(1)).await;
}

/// A region job (spot's ear, smooth seam) stopped by a shutdown, checkpointed and resumed
/// after the restart ends on the result of the same job run without a stop: the checkpoint
/// carries the curvature change the held border could not realize (`willow::flow::Carried`),
/// which the region's flow keeps from step to step; without it the resumed steps differ.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resumed_region_job_ends_where_an_uninterrupted_one_does() {
    use willow::flow::region::{Region, Seam};
    use willow_service::jobs::codec::decode_checkpoint;
    let spot = include_str!("../crates/willow/tests/data/spot_triangulated.obj").to_string();
    let ear = JobSpec {
        region: vec![Region::Sphere {
            center: [0.40, 0.72, -0.20],
            radius: 0.15,
        }],
        seam: Seam::Smooth,
        // Long enough that the job is still running when the shutdown comes.
        ..spec(150)
    };
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    let stopped = jobs
        .submit(&me(), obj(spot.clone()), ear.clone(), None)
        .await
        .expect("submit");
    let mut events = Box::pin(jobs.watch(&me(), &stopped.id, 0).await.expect("watch"));
    while let Some(ev) = events.next().await {
        if matches!(ev, JobEvent::Frame(ref f) if f.step >= 3) {
            break;
        }
    }
    drop(events);
    core.shutdown(Duration::ZERO).await;
    let s = jobs.get(&me(), &stopped.id).await.expect("get");
    assert_eq!(s.state, JobState::Queued, "stopped mid-run: {s:?}");
    let blob = std::fs::read(
        dir.path()
            .join("jobs")
            .join(&*stopped.id)
            .join("checkpoint"),
    )
    .expect("the shutdown wrote a checkpoint");
    let state = decode_checkpoint(&blob).expect("decodes");
    assert!(state.metrics.step >= 3 && state.metrics.step < 150);
    assert!(
        state.carried.absorbed.iter().any(|&d| d.abs() > 1e-3),
        "the checkpoint holds the absorbed curvature change"
    );
    drop(jobs);

    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("restart");
    let resumed = jobs
        .wait(&me(), &stopped.id, Duration::from_secs(120))
        .await
        .expect("wait");
    assert_eq!(resumed.state, JobState::Succeeded, "{resumed:?}");
    assert!(
        jobs.metrics_text().contains("willow_jobs_resumed_total 1"),
        "resumed from its checkpoint, not restarted"
    );
    let straight = jobs
        .submit(&me(), obj(spot.clone()), ear, None)
        .await
        .expect("submit");
    let done = jobs
        .wait(&me(), &straight.id, Duration::from_secs(120))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded, "{done:?}");
    let result = |id: willow_service::jobs::JobId| {
        let jobs = &jobs;
        async move {
            let bytes = jobs.result(&me(), &id, Format::Obj).await.expect("result");
            obj_vertices(&String::from_utf8(bytes).expect("OBJ text"))
        }
    };
    let (a, b) = (
        result(stopped.id.clone()).await,
        result(straight.id.clone()).await,
    );
    assert_eq!(a.len(), b.len());
    let input = obj_vertices(&spot);
    let moved = a.iter().zip(&input).filter(|(p, q)| p != q).count();
    assert!(moved > 0, "the ear moved");
    let worst = a
        .iter()
        .zip(&b)
        .flat_map(|(p, q)| (0..3).map(move |k| (p[k] - q[k]).abs()))
        .fold(0.0f64, f64::max);
    assert!(
        worst <= 1e-9,
        "resumed and uninterrupted results differ by {worst:e}"
    );
    core.shutdown(Duration::from_secs(1)).await;
}

/// Specs stored before the flow options existed (issue 4) still load after an upgrade, with
/// the options at their defaults, and the idempotency key stored with them still matches the
/// same request sent again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn specs_stored_before_the_flow_options_load_with_defaults() {
    let dir = tempfile::tempdir().expect("dir");
    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("start");
    let job = jobs
        .submit(
            &me(),
            obj(small_obj()),
            first_release_request(),
            Some("before-upgrade".into()),
        )
        .await
        .expect("submit");
    jobs.wait(&me(), &job.id, Duration::from_secs(60))
        .await
        .expect("wait");
    core.shutdown(Duration::from_secs(1)).await;

    // Rewrite the row as the first release stored it.
    let old = r#"{"method":"conformal","steps":1,"tau":0.5,"iterations":1,"frame_interval":1,"include_positions":true,"deadline_secs":null}"#;
    let db = rusqlite::Connection::open(dir.path().join("willow.sqlite3")).expect("open db");
    let changed = db
        .execute(
            "UPDATE jobs SET spec = ?1 WHERE id = ?2",
            rusqlite::params![old, job.id],
        )
        .expect("update");
    assert_eq!(changed, 1);
    // And its idempotency hash as the first release computed it: sha256 of format, 0, the
    // spec's JSON, 0, the mesh bytes.
    let old_hash: String = {
        use sha2::{Digest, Sha256};
        let mut h = Sha256::new();
        h.update(b"obj");
        h.update([0]);
        h.update(old.as_bytes());
        h.update([0]);
        h.update(small_obj().as_bytes());
        h.finalize().iter().map(|b| format!("{b:02x}")).collect()
    };
    let changed = db
        .execute(
            "UPDATE idempotency SET request_hash = ?1, key = 'before-upgrade'
             WHERE key = 'default/before-upgrade'",
            rusqlite::params![old_hash],
        )
        .expect("update");
    assert_eq!(changed, 1);
    // And without tenants (issue 12): no tenant column, keys unscoped, and no `received`
    // column (every job then brought its mesh). The upgrade gives the rows to the default
    // tenant and scopes their keys to it.
    db.execute_batch(
        "DROP TRIGGER tenant_usage_job_in; DROP TRIGGER tenant_usage_job_received;
         DROP TRIGGER tenant_usage_job_state;
         DROP TRIGGER tenant_usage_job_expired; DROP TRIGGER tenant_usage_job_out;
         DROP TRIGGER tenant_usage_job_planned;
         DROP TRIGGER tenant_usage_upload_in; DROP TRIGGER tenant_usage_upload_out;
         DROP TRIGGER tenant_usage_rendered_in; DROP TRIGGER tenant_usage_rendered_out;
         DROP TABLE rendered;
         DROP TABLE tenant_usage;
         DROP INDEX jobs_by_tenant; DROP INDEX jobs_by_tenant_state;
         DROP INDEX jobs_by_tenant_created; DROP INDEX uploads_by_tenant;
         ALTER TABLE jobs DROP COLUMN tenant; ALTER TABLE jobs DROP COLUMN input_bytes;
         ALTER TABLE jobs DROP COLUMN received;
         ALTER TABLE uploads DROP COLUMN tenant;",
    )
    .expect("drop the tenant columns");
    // The per-tenant bytes table of the first release with tenants, which the open replaces.
    db.execute_batch(
        "CREATE TABLE tenant_bytes (tenant TEXT PRIMARY KEY, bytes INTEGER NOT NULL);",
    )
    .expect("an older usage table");
    drop(db);

    let (jobs, core) = Jobs::start(config(dir.path())).await.expect("restart");
    let status = jobs.get(&me(), &job.id).await.expect("the old row loads");
    assert_eq!(
        status.spec,
        JobSpec {
            method: willow::flow::Method::Conformal,
            steps: 1,
            ..JobSpec::default()
        },
        "new fields take their defaults"
    );
    assert!(status.spec.safeguard, "an old row runs safeguarded");
    assert_eq!(status.state, JobState::Succeeded);
    let again = jobs
        .submit(
            &me(),
            obj(small_obj()),
            first_release_request(),
            Some("before-upgrade".into()),
        )
        .await
        .expect("the same request with the same key");
    assert_eq!(again.id, job.id, "still recognised as the same request");
    core.shutdown(Duration::from_secs(1)).await;
}

/// A curve request whose caller goes away stops at its next step and frees its slot: with
/// one slot, a second request is `Busy` while the first runs, and succeeds once the first
/// caller's future is dropped.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dropped_curve_request_frees_its_slot() {
    use willow_service::jobs::curve::{CurveInput, CurveSpec};
    use willow_service::jobs::JobError;
    let dir = tempfile::tempdir().expect("dir");
    let mut c = config(dir.path());
    c.curve_slots = 1;
    let (jobs, core) = Jobs::start(c).await.expect("start");
    let circle = |n: usize| CurveInput::Points {
        points: (0..n)
            .map(|i| {
                let t = std::f64::consts::TAU * i as f64 / n as f64;
                let r = 1.0 + 0.1 * (7.0 * t).sin();
                [r * t.cos(), r * t.sin()]
            })
            .collect(),
        closed: true,
    };
    let long_jobs = jobs.clone();
    let long = tokio::spawn(async move {
        long_jobs
            .fair_curve(
                circle(100_000),
                CurveSpec {
                    steps: 1000,
                    deadline_secs: Some(60.0),
                    ..CurveSpec::default()
                },
                None,
            )
            .await
    });
    tokio::time::sleep(Duration::from_millis(500)).await;
    let busy = jobs
        .fair_curve(circle(50), CurveSpec::default(), None)
        .await;
    assert!(
        matches!(busy, Err(JobError::Busy { slots: 1, .. })),
        "{busy:?}"
    );
    long.abort();
    let started = std::time::Instant::now();
    let freed = jobs
        .fair_curve(circle(50), CurveSpec::default(), None)
        .await;
    let outcome = freed.expect("the slot was freed");
    assert_eq!(outcome.metrics.len(), CurveSpec::default().steps + 1);
    assert!(
        started.elapsed() < Duration::from_secs(1),
        "{:?}",
        started.elapsed()
    );
    core.shutdown(Duration::from_secs(1)).await;
}

/// The request `steps=1` as the first release read it: the conformal flow, no repair, a free
/// boundary (the defaults before issue 39). Sent again after the upgrade it must hash as it did then.
fn first_release_request() -> JobSpec {
    JobSpec {
        method: willow::flow::Method::Conformal,
        repair: false,
        boundary: willow_service::jobs::spec::BoundarySpec::Free,
        steps: 1,
        ..JobSpec::default()
    }
}
