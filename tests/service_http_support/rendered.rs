//! Rendered downloads in the tenant's `stored_bytes` quota, shared by the embedded and the
//! NATS tests (issue 25): what `Jobs::result_download` stores is counted once, a download
//! the quota has no room for is still served (whole, from memory, uncounted), and the count
//! goes with the job (deleted or expired).

use super::{obj, small_obj, spec};
use futures::StreamExt;
use std::time::Duration;
use willow::mesh::io::Format;
use willow_service::jobs::{Caller, JobError, JobState, Jobs, MeshDownload};

/// The quota the shared check runs under (`max_stored_bytes`).
pub const RENDERED_QUOTA: u64 = 256 << 10;

/// An OBJ of exactly `len` bytes: the small sphere and a comment that pads it.
pub fn padded_obj(len: usize) -> String {
    let mut text = small_obj();
    assert!(len > text.len() + 3, "{len} leaves no room for the sphere");
    text.push_str("\n# ");
    let pad = len - text.len() - 1;
    text.push_str(&"x".repeat(pad));
    text.push('\n');
    assert_eq!(text.len(), len);
    text
}

/// The tenant's `stored_bytes` as the quota sees it: a submission larger than the quota is
/// refused whatever the usage, and the refusal reports the usage.
pub async fn stored_bytes(jobs: &Jobs, who: &Caller) -> u64 {
    let probe = padded_obj(RENDERED_QUOTA as usize + 1);
    match jobs.submit(who, obj(probe), spec(1), None).await {
        Err(JobError::QuotaExceeded {
            quota: "stored_bytes",
            limit,
            used: Some(used),
            ..
        }) => {
            assert_eq!(limit, RENDERED_QUOTA);
            used
        }
        other => panic!("expected the stored_bytes quota to refuse the probe, got {other:?}"),
    }
}

/// The bytes of a download, and whether it was streamed from storage.
pub async fn take(download: MeshDownload) -> (Vec<u8>, bool) {
    match download {
        MeshDownload::Whole(b) => (b.to_vec(), false),
        MeshDownload::Stored(mut r) => {
            let mut out = Vec::new();
            while let Some(chunk) = r.chunks.next().await {
                out.extend_from_slice(&chunk.expect("a stored chunk"));
            }
            assert_eq!(out.len() as u64, r.len);
            (out, true)
        }
    }
}

/// What a job stores besides its input, as its tenant's quota counts it (`jobs::stored`).
async fn planned(jobs: &Jobs, who: &Caller, id: &str) -> u64 {
    jobs.get(who, id).await.expect("get").planned_bytes
}

async fn succeeded(jobs: &Jobs, who: &Caller, text: String) -> String {
    let id = jobs
        .submit(who, obj(text), spec(1), None)
        .await
        .expect("within the quota")
        .id
        .to_string();
    let done = jobs
        .wait(who, &id, Duration::from_secs(120))
        .await
        .expect("wait");
    assert_eq!(done.state, JobState::Succeeded, "{:?}", done.error);
    id
}

/// The check, on a core started with `max_stored_bytes: RENDERED_QUOTA` and a result TTL of
/// `ttl` (the first job is left to expire; give the sweep a short interval).
pub async fn assert_rendered_downloads_count_in_stored_bytes(
    jobs: &Jobs,
    a: &Caller,
    ttl: Duration,
) {
    let id = succeeded(jobs, a, small_obj()).await;
    // The input and the frames, checkpoint and result its single step kept.
    let kept = planned(jobs, a, &id).await;
    assert!(kept > 0);
    let input = small_obj().len() as u64 + kept;
    assert_eq!(stored_bytes(jobs, a).await, input, "the job alone");
    // Rendered in memory (not stored): the bytes every download must be, and their sizes.
    let obj_bytes = jobs.result(a, &id, Format::Obj).await.expect("OBJ");
    let ply_bytes = jobs.result(a, &id, Format::Ply).await.expect("PLY");
    assert_eq!(
        stored_bytes(jobs, a).await,
        input,
        "an unstored render counts nothing"
    );

    // Stored: counted once, however often it is downloaded.
    for n in 0..2 {
        let download = jobs
            .result_download(a, &id, Format::Obj, None)
            .await
            .expect("OBJ");
        let (got, stored) = take(download).await;
        assert!(stored, "download {n} streams from storage");
        assert_eq!(got, obj_bytes);
        assert_eq!(
            stored_bytes(jobs, a).await,
            input + obj_bytes.len() as u64,
            "the input and the stored OBJ rendering, after download {n}"
        );
    }

    let used = input + obj_bytes.len() as u64;

    // A deleted job gives back its input and its stored renderings.
    let deleted = succeeded(jobs, a, small_obj()).await;
    let (got, stored) = take(
        jobs.result_download(a, &deleted, Format::Obj, None)
            .await
            .expect("OBJ"),
    )
    .await;
    assert!(stored);
    assert_eq!(stored_bytes(jobs, a).await, used + input + got.len() as u64);
    jobs.delete(a, &deleted).await.expect("delete");
    assert_eq!(
        stored_bytes(jobs, a).await,
        used,
        "the job and its rendering gone"
    );

    // Fill the quota to one byte short of the PLY rendering: its download is still served,
    // whole from memory, and counts nothing.
    // (The filler's mesh is the small sphere's: the same plan.)
    let filler_len = RENDERED_QUOTA - used - kept - (ply_bytes.len() as u64 - 1);
    let filler = succeeded(jobs, a, padded_obj(filler_len as usize)).await;
    let full = RENDERED_QUOTA - ply_bytes.len() as u64 + 1;
    assert_eq!(stored_bytes(jobs, a).await, full);
    let (got, stored) = take(
        jobs.result_download(a, &id, Format::Ply, None)
            .await
            .expect("PLY"),
    )
    .await;
    assert!(!stored, "no room under the quota: served from memory");
    assert_eq!(got, ply_bytes);
    assert_eq!(
        stored_bytes(jobs, a).await,
        full,
        "an unstored rendering counts nothing"
    );
    // The stored OBJ is still streamed at the quota.
    let (got, stored) = take(
        jobs.result_download(a, &id, Format::Obj, None)
            .await
            .expect("OBJ"),
    )
    .await;
    assert!(stored);
    assert_eq!(got, obj_bytes);
    jobs.delete(a, &filler).await.expect("delete the filler");
    assert_eq!(stored_bytes(jobs, a).await, used);

    // An expired job does too.
    let deadline = std::time::Instant::now() + ttl + Duration::from_secs(60);
    loop {
        let now = stored_bytes(jobs, a).await;
        if now == 0 {
            break;
        }
        assert_eq!(now, used, "nothing else changes the count");
        assert!(
            std::time::Instant::now() < deadline,
            "the expired job's bytes were never given back"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(matches!(
        jobs.result_download(a, &id, Format::Obj, None).await,
        Err(JobError::Gone(_))
    ));
}
