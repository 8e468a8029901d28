//! Kept frames in the tenant's `stored_bytes` quota (issue 42 item 1), shared by the
//! embedded and the NATS tests: a job whose frames could never fit is refused at submission
//! with the `frame_interval` that would, the one that fits stores no more than the quota
//! (measured on the blobs the backend holds), a second one is refused while the first holds
//! its room, and a job that stops early, or is cancelled while it runs, gives back what it
//! did not keep.

use super::obj;
use super::rendered::padded_obj;
use std::future::Future;
use std::time::Duration;
use willow::flow::Method;
use willow::mesh::generate;
use willow_service::jobs::stored::{kept_bytes, planned_bytes, JobSizes};
use willow_service::jobs::{Caller, JobError, JobSpec, JobState, Jobs};

/// The quota the shared check runs under (`max_stored_bytes`).
pub const FRAMES_QUOTA: u64 = 2 << 20;

/// The tenant's `stored_bytes` as the quota sees it: an input larger than the whole quota is
/// refused with the usage.
async fn used(jobs: &Jobs, who: &Caller) -> u64 {
    let probe = padded_obj(FRAMES_QUOTA as usize + 1);
    match jobs.submit(who, obj(probe), long(1), None).await {
        Err(JobError::QuotaExceeded {
            quota: "stored_bytes",
            used: Some(used),
            ..
        }) => used,
        other => panic!("expected the stored_bytes quota to refuse the probe, got {other:?}"),
    }
}

/// Every frame kept, all steps run (no safeguard to stall it); Taubin's steps cost
/// microseconds.
fn long(frame_interval: usize) -> JobSpec {
    JobSpec {
        method: Method::Taubin,
        steps: 600,
        frame_interval,
        until_converged: false,
        safeguard: false,
        ..JobSpec::default()
    }
}

/// The check. `measure(id)` is the bytes the backend stores for job `id` (its files, its
/// objects).
pub async fn assert_kept_frames_stay_within_the_quota<F, Fut>(jobs: &Jobs, a: &Caller, measure: F)
where
    F: Fn(String) -> Fut,
    Fut: Future<Output = u64>,
{
    // 2,562 vertices: a kept frame is ~92 KB, so 601 of them would be ~55 MB.
    let mesh = generate::bumpy_sphere(4, 0.05);
    let text = super::obj_text(&mesh);
    let input = text.len() as u64;
    let sizes = JobSizes {
        file_vertices: mesh.vertex_count(),
        surface_vertices: mesh.vertex_count(),
    };
    assert!(input + planned_bytes(&long(1), sizes) > 20 * FRAMES_QUOTA);

    // Refused at submission, naming the interval that fits.
    let reason = match jobs.submit(a, obj(text.clone()), long(1), None).await {
        Err(JobError::InvalidSpec {
            field: "frame_interval",
            reason,
        }) => reason,
        other => panic!("expected frame_interval to be refused, got {other:?}"),
    };
    let interval: usize = reason
        .split("frame_interval=")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .and_then(|k| k.parse().ok())
        .unwrap_or_else(|| panic!("no interval named: {reason}"));
    assert!(reason.contains("kept frames"), "{reason}");
    let fits = long(interval);
    let plan = planned_bytes(&fits, sizes);
    assert!(
        input + plan <= FRAMES_QUOTA
            && input + planned_bytes(&long(interval - 1), sizes) > FRAMES_QUOTA
    );

    let id = jobs
        .submit(a, obj(text.clone()), fits.clone(), None)
        .await
        .expect("the interval that fits is accepted")
        .id
        .to_string();
    assert_eq!(
        used(jobs, a).await,
        input + plan,
        "its room is held from submission"
    );
    // While it holds its room, the same job again does not fit.
    match jobs.submit(a, obj(text.clone()), fits.clone(), None).await {
        Err(JobError::QuotaExceeded {
            quota: "stored_bytes",
            ..
        }) => {}
        other => panic!("expected the stored_bytes quota, got {other:?}"),
    }
    let done = jobs
        .wait(a, &id, Duration::from_secs(300))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded, "{:?}", done.error);
    assert_eq!(
        done.step, fits.steps,
        "{:?} {:?}",
        done.error_code, done.error
    );
    let stored = measure(id.clone()).await;
    println!(
        "kept frames: interval {interval}, {stored} bytes stored, {} counted, quota {FRAMES_QUOTA}",
        input + plan
    );
    assert!(
        stored <= input + plan,
        "{stored} stored past the plan {}",
        input + plan
    );
    assert!(stored <= FRAMES_QUOTA, "{stored} stored past the quota");
    // Not vacuous: the frames were kept, most of the quota is used.
    assert!(stored > FRAMES_QUOTA / 2, "{stored}");
    jobs.delete(a, &id).await.expect("delete");
    assert_eq!(used(jobs, a).await, 0);

    // Stopped at once (W is below any target): what it kept is all it counts afterwards.
    let early = JobSpec {
        until_willmore: Some(1e12),
        ..fits.clone()
    };
    let id = jobs
        .submit(a, obj(text.clone()), early.clone(), None)
        .await
        .expect("fits")
        .id
        .to_string();
    let done = jobs
        .wait(a, &id, Duration::from_secs(120))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded, "{:?}", done.error);
    assert!(done.step < early.steps, "{}", done.step);
    let kept = kept_bytes(&early, sizes, done.step);
    assert!(kept < plan / 4, "{kept} of {plan}");
    assert_eq!(done.planned_bytes, kept);
    assert_eq!(used(jobs, a).await, input + kept);
    assert!(measure(id.clone()).await <= input + kept);
    jobs.delete(a, &id).await.expect("delete");

    // Cancelled while running: the plan settles to what it kept when it stops, not when it
    // expires. The paper's flow (milliseconds a step here) runs long enough to be caught.
    let slow = JobSpec {
        method: Method::Conformal,
        safeguard: true,
        ..fits.clone()
    };
    let id = jobs
        .submit(a, obj(text.clone()), slow.clone(), None)
        .await
        .expect("fits")
        .id
        .to_string();
    let caught = tokio::time::Instant::now();
    loop {
        let now = jobs.get(a, &id).await.expect("status");
        assert!(!now.state.is_terminal(), "ended before the cancel: {now:?}");
        if now.state == JobState::Running && now.step >= 3 {
            break;
        }
        assert!(caught.elapsed() < Duration::from_secs(120), "never ran");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    jobs.cancel(a, &id).await.expect("cancel");
    let done = jobs
        .wait(a, &id, Duration::from_secs(120))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Cancelled, "{:?}", done.error);
    assert!(done.step < slow.steps / 2, "{}", done.step);
    let kept = kept_bytes(&slow, sizes, done.step);
    assert!(kept < plan, "{kept} of {plan}");
    assert_eq!(done.planned_bytes, kept, "settled at step {}", done.step);
    assert_eq!(used(jobs, a).await, input + kept);
    assert!(measure(id.clone()).await <= input + kept);
    jobs.delete(a, &id).await.expect("delete");
    assert_eq!(used(jobs, a).await, 0);
}
