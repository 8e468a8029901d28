//! Jobs end to end: chunked and inline uploads, streamed frames, resumption, the queue
//! limit, cancellation, idempotent creation, deadlines, and the Operations views.

use super::*;

/// Chunked GLB upload → job → every frame by StreamFrames (complete, ordered, positions on the
/// frame interval, decodable) → resume from a later step → poll and Operations views agree →
/// result download.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn glb_upload_job_streams_every_frame_and_resumes() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;

    let glb = small_glb();
    let up = upload(&mut client, v1::MeshFormat::Glb, &glb, 4096)
        .await
        .expect("GLB upload");
    assert!(up.name.starts_with("uploads/"), "{}", up.name);
    assert_eq!(up.size_bytes, glb.len() as u64);
    assert_eq!(up.format, v1::MeshFormat::Glb as i32);

    let steps = 6;
    let op = create(
        &mut client,
        Some(v1::create_job_request::Mesh::Upload(up.name.clone())),
        v1::JobParams {
            frame_interval: Some(2),
            include_positions: Some(true),
            tau: Some(0.1),
            ..params(v1::Method::Mcf, steps)
        },
        &uuid(),
    )
    .await
    .expect("CreateJob");
    assert!(op.name.starts_with("jobs/"), "{}", op.name);
    let meta = job_from_any(op.metadata.as_ref().expect("metadata"));
    assert_eq!(meta.name, op.name);
    assert_eq!(meta.total_steps, steps);
    assert_eq!(meta.input_format, v1::MeshFormat::Glb as i32);

    use v1::stream_frames_response::Event;
    let events = stream_all(&mut client, &op.name, 0).await;
    assert!(
        matches!(events.first(), Some(Event::Job(_))),
        "the stream opens with the job's state"
    );
    let last = match events.last() {
        Some(Event::Job(job)) => job.clone(),
        other => panic!("the stream must end with the terminal job, got {other:?}"),
    };
    assert_eq!(state(&last), v1::job::State::Succeeded, "{:?}", last.error);
    let frames: Vec<&v1::Frame> = events
        .iter()
        .filter_map(|e| match e {
            Event::Frame(f) => Some(f),
            Event::Job(_) => None,
        })
        .collect();
    let seen: Vec<u32> = frames.iter().map(|f| f.step).collect();
    assert_eq!(
        seen,
        (0..=steps).collect::<Vec<_>>(),
        "every step once, in order"
    );
    let vertex_bytes = last.vertex_count as usize * 12;
    assert!(last.vertex_count > 0);
    for f in &frames {
        let m = f.metrics.as_ref().expect("metrics on every frame");
        assert_eq!(m.step, f.step);
        assert!(m.area > 0.0 && m.willmore_energy.is_finite());
        // Positions at step 0, every 2nd step and the last.
        let keyframe = f.step % 2 == 0 || f.step == steps;
        match &f.positions {
            Some(p) if keyframe => {
                assert_eq!(p.len(), vertex_bytes, "12 bytes per vertex");
                let floats: Vec<f32> = p
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                assert!(floats.iter().all(|x| x.is_finite() && x.abs() < 10.0));
            }
            None if !keyframe => {}
            other => panic!(
                "step {}: positions {:?}",
                f.step,
                other.as_ref().map(|p| p.len())
            ),
        }
    }
    // The input frame's positions are the uploaded vertices, in file order.
    let input = Asset::read(&glb, Format::Glb, &willow::mesh::Limits::default()).expect("GLB");
    let expected = input.file_positions(&input.surface().positions);
    let p0 = frames[0].positions.as_ref().expect("step 0 positions");
    let first = [
        f32::from_le_bytes([p0[0], p0[1], p0[2], p0[3]]),
        f32::from_le_bytes([p0[4], p0[5], p0[6], p0[7]]),
        f32::from_le_bytes([p0[8], p0[9], p0[10], p0[11]]),
    ];
    assert_eq!(first, expected[0]);

    // Reconnect from a later step: only the rest is replayed.
    let resumed = stream_all(&mut client, &op.name, 4).await;
    let resumed_steps: Vec<u32> = resumed
        .iter()
        .filter_map(|e| match e {
            Event::Frame(f) => Some(f.step),
            Event::Job(_) => None,
        })
        .collect();
    assert_eq!(resumed_steps, vec![4, 5, 6]);
    assert!(matches!(resumed.last(), Some(Event::Job(j)) if state(j) == v1::job::State::Succeeded));

    // Polling and the Operations view agree.
    let job = get_job(&mut client, &op.name).await.expect("GetJob");
    assert_eq!(state(&job), v1::job::State::Succeeded);
    assert_eq!(job.step, steps);
    assert_eq!(job.latest.as_ref().map(|m| m.step), Some(steps));
    assert!(job.end_time.is_some() && job.start_time.is_some());
    let op2 = ops
        .get_operation(lro::GetOperationRequest {
            name: op.name.clone(),
        })
        .await
        .expect("Operations.GetOperation")
        .into_inner();
    assert!(op2.done);
    match op2.result {
        Some(lro::operation::Result::Response(any)) => {
            assert_eq!(job_from_any(&any).name, op.name)
        }
        other => panic!("a succeeded operation carries the Job as response, got {other:?}"),
    }

    // The faired mesh, in chunks, in the input's format.
    let mut download = client
        .download_result(v1::DownloadResultRequest {
            name: op.name.clone(),
            format: v1::MeshFormat::Unspecified as i32,
        })
        .await
        .expect("DownloadResult")
        .into_inner();
    let mut file = Vec::new();
    let mut first_format = None;
    while let Some(chunk) = download.message().await.expect("download stream") {
        first_format.get_or_insert(chunk.format);
        file.extend_from_slice(&chunk.data);
    }
    assert_eq!(first_format, Some(v1::MeshFormat::Glb as i32));
    let result = Asset::read(&file, Format::Glb, &willow::mesh::Limits::default())
        .expect("the result is a valid GLB");
    assert_eq!(result.file_vertex_count(), last.vertex_count as usize);
}

/// A client applies the last streamed positions to the `v` lines of the OBJ it uploaded
/// (shuffled vertex order, unused vertices) and gets the downloaded result.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_positions_applied_to_the_upload_give_the_obj_result() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let upload = service_http_support::shuffled_obj();
    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, upload.clone().into_bytes()),
        v1::JobParams {
            frame_interval: Some(1),
            include_positions: Some(true),
            tau: Some(0.1),
            ..params(v1::Method::Mcf, 3)
        },
        &uuid(),
    )
    .await
    .expect("CreateJob");
    use v1::stream_frames_response::Event;
    let events = stream_all(&mut client, &op.name, 0).await;
    let job = match events.last() {
        Some(Event::Job(job)) => job.clone(),
        other => panic!("the stream must end with the terminal job, got {other:?}"),
    };
    assert_eq!(state(&job), v1::job::State::Succeeded, "{:?}", job.error);
    let v_lines = upload.lines().filter(|l| l.starts_with("v ")).count();
    assert_eq!(job.vertex_count, v_lines as u64);
    let last = events
        .iter()
        .rev()
        .find_map(|e| match e {
            Event::Frame(f) => f.positions.clone(),
            Event::Job(_) => None,
        })
        .expect("a frame with positions");
    let frame = service_http_support::f32_triples(&last);

    let result = download_obj(&mut client, &op.name).await;
    service_http_support::assert_frame_applies_to_upload(&upload, &frame, &result);
    assert_ne!(result, upload, "the result is faired, not the upload");
}

/// A 16 MiB OBJ (4x gRPC's message limit) arrives through chunked UploadMesh and is usable by
/// CreateJob; inline OBJ works for small meshes; a full queue answers RESOURCE_EXHAUSTED with
/// RetryInfo; cancelling queued and running jobs; cancel of a finished job and delete of an
/// unfinished one are FAILED_PRECONDITION.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_upload_queue_full_and_cancel() {
    let server = Server::start(|c| c.queue_capacity = 1).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;

    let large = large_obj();
    assert!(large.len() > 12 << 20, "{} bytes", large.len());
    let big = upload(&mut client, v1::MeshFormat::Obj, &large, 1 << 20)
        .await
        .expect("16 MiB upload in 1 MiB chunks");
    assert_eq!(big.size_bytes, large.len() as u64);

    // A: long-running, on the one worker.
    let running = create(
        &mut client,
        inline(v1::MeshFormat::Obj, slow_obj()),
        long_running(5000),
        "",
    )
    .await
    .expect("CreateJob A");
    poll_until(&mut client, &running.name, |j| {
        state(j) == v1::job::State::Running && j.step >= 1
    })
    .await;

    // B: the large upload, queued behind A (fills the queue of capacity 1).
    let queued = create(
        &mut client,
        Some(v1::create_job_request::Mesh::Upload(big.name.clone())),
        params(v1::Method::Mcf, 1),
        "",
    )
    .await
    .expect("CreateJob B from the large upload");
    let queued_job = job_from_any(queued.metadata.as_ref().expect("metadata"));
    assert_eq!(state(&queued_job), v1::job::State::Queued);
    assert_eq!(queued_job.vertex_count, 163_842);

    // C: no room.
    let full = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 1),
        "",
    )
    .await
    .expect_err("the queue is full");
    assert_eq!(full.code(), Code::ResourceExhausted, "{}", full.message());
    let retry = full
        .get_details_retry_info()
        .and_then(|r| r.retry_delay)
        .expect("RetryInfo with a delay");
    assert!(retry >= Duration::from_secs(1), "{retry:?}");
    assert_eq!(
        full.get_details_error_info().map(|e| e.reason),
        Some("QUEUE_FULL".to_string())
    );

    // Deleting an unfinished job is refused.
    let del = client
        .delete_job(v1::DeleteJobRequest {
            name: running.name.clone(),
        })
        .await
        .expect_err("delete of a running job");
    assert_eq!(del.code(), Code::FailedPrecondition, "{}", del.message());

    // Cancel the queued job (through the Operations service): cancelled at once.
    ops.cancel_operation(lro::CancelOperationRequest {
        name: queued.name.clone(),
    })
    .await
    .expect("CancelOperation of a queued job");
    let b = get_job(&mut client, &queued.name).await.expect("GetJob B");
    assert_eq!(state(&b), v1::job::State::Cancelled);
    assert_eq!(
        b.error.as_ref().map(|e| e.code),
        Some(Code::Cancelled as i32)
    );

    // Cancel the running job: it stops at its next step, well before its 5000.
    let a = client
        .cancel_job(v1::CancelJobRequest {
            name: running.name.clone(),
        })
        .await
        .expect("CancelJob of a running job")
        .into_inner();
    assert!(
        matches!(
            state(&a),
            v1::job::State::Running | v1::job::State::Cancelled
        ),
        "{a:?}"
    );
    let waited = ops
        .wait_operation(lro::WaitOperationRequest {
            name: running.name.clone(),
            timeout: Some(prost_types::Duration {
                seconds: 60,
                nanos: 0,
            }),
        })
        .await
        .expect("WaitOperation")
        .into_inner();
    assert!(waited.done, "cancelled within a step");
    match &waited.result {
        Some(lro::operation::Result::Error(e)) => assert_eq!(e.code, Code::Cancelled as i32),
        other => panic!("a cancelled operation carries error CANCELLED, got {other:?}"),
    }
    let a = get_job(&mut client, &running.name).await.expect("GetJob A");
    assert!(a.step < 5000, "stopped early at step {}", a.step);

    // Cancelling again: it already finished.
    let again = client
        .cancel_job(v1::CancelJobRequest {
            name: running.name.clone(),
        })
        .await
        .expect_err("cancel of a finished job");
    assert_eq!(
        again.code(),
        Code::FailedPrecondition,
        "{}",
        again.message()
    );
    assert!(again
        .get_details_precondition_failure()
        .is_some_and(|p| !p.violations.is_empty()));

    // Now the queue has room again, and the finished job can be deleted.
    create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 1),
        "",
    )
    .await
    .expect("room in the queue again");
    ops.delete_operation(lro::DeleteOperationRequest {
        name: running.name.clone(),
    })
    .await
    .expect("DeleteOperation of a finished job");
    let gone = get_job(&mut client, &running.name)
        .await
        .expect_err("deleted");
    assert_eq!(gone.code(), Code::NotFound);
    assert_eq!(
        gone.get_details_resource_info().map(|r| r.resource_name),
        Some(running.name.clone())
    );
}

/// AIP-155: a retried CreateJob with the same request_id returns the original operation; the
/// same id with a different request is ALREADY_EXISTS; a malformed id is INVALID_ARGUMENT.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn request_id_makes_create_job_idempotent() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let id = uuid();

    let first = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 2),
        &id,
    )
    .await
    .expect("first CreateJob");
    let retry = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 2),
        &id.to_uppercase(),
    )
    .await
    .expect("retried CreateJob");
    assert_eq!(retry.name, first.name, "the retry returns the original job");

    let list = client
        .list_jobs(v1::ListJobsRequest::default())
        .await
        .expect("ListJobs")
        .into_inner();
    assert_eq!(list.jobs.len(), 1, "one job despite two calls");

    let other = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 3),
        &id,
    )
    .await
    .expect_err("same request_id, different request");
    assert_eq!(other.code(), Code::AlreadyExists, "{}", other.message());
    assert_eq!(violations(&other), vec!["request_id".to_string()]);
    assert_eq!(
        other.get_details_error_info().map(|e| e.reason),
        Some("REQUEST_ID_REUSED".to_string())
    );

    assert_bad_field(
        create(
            &mut client,
            inline(v1::MeshFormat::Obj, small_obj()),
            params(v1::Method::Mcf, 2),
            "retry-1",
        )
        .await,
        "request_id",
    );
}

/// A job over its deadline finishes FAILED with DEADLINE_EXCEEDED in Job.error and
/// Operation.error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn job_deadline_gives_deadline_exceeded() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;
    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, slow_obj()),
        v1::JobParams {
            deadline: Some(prost_types::Duration {
                seconds: 0,
                nanos: 300_000_000,
            }),
            ..long_running(5000)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let done = poll_until(&mut client, &op.name, |j| {
        state(j) != v1::job::State::Queued && state(j) != v1::job::State::Running
    })
    .await;
    assert_eq!(state(&done), v1::job::State::Failed);
    let error = done.error.expect("Job.error");
    assert_eq!(
        error.code,
        Code::DeadlineExceeded as i32,
        "{}",
        error.message
    );
    let op = ops
        .get_operation(lro::GetOperationRequest { name: op.name })
        .await
        .expect("GetOperation")
        .into_inner();
    assert!(op.done);
    assert!(
        matches!(op.result, Some(lro::operation::Result::Error(e)) if e.code == Code::DeadlineExceeded as i32)
    );
}

/// Operations.List pages over the jobs, filters by state, and WaitOperation returns a
/// not-done operation when its timeout passes first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operations_list_pages_and_wait_times_out() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;
    let slow = create(
        &mut client,
        inline(v1::MeshFormat::Obj, slow_obj()),
        long_running(5000),
        "",
    )
    .await
    .expect("slow job");
    let mut names = vec![slow.name.clone()];
    for _ in 0..2 {
        let op = create(
            &mut client,
            inline(v1::MeshFormat::Obj, small_obj()),
            params(v1::Method::Mcf, 1),
            "",
        )
        .await
        .expect("job");
        names.push(op.name);
    }

    let mut seen = Vec::new();
    let mut token = String::new();
    loop {
        let page = ops
            .list_operations(lro::ListOperationsRequest {
                name: "jobs".into(),
                page_size: 2,
                page_token: token.clone(),
                ..Default::default()
            })
            .await
            .expect("ListOperations")
            .into_inner();
        assert!(page.operations.len() <= 2);
        seen.extend(page.operations.into_iter().map(|o| o.name));
        if page.next_page_token.is_empty() {
            break;
        }
        token = page.next_page_token;
    }
    seen.sort();
    names.sort();
    assert_eq!(seen, names, "paging visits every job once");

    let queued = ops
        .list_operations(lro::ListOperationsRequest {
            filter: "state=QUEUED".into(),
            ..Default::default()
        })
        .await
        .expect("filtered list")
        .into_inner();
    assert!(queued.operations.iter().all(|o| !o.done));

    let started = std::time::Instant::now();
    let op = ops
        .wait_operation(lro::WaitOperationRequest {
            name: slow.name.clone(),
            timeout: Some(prost_types::Duration {
                seconds: 0,
                nanos: 300_000_000,
            }),
        })
        .await
        .expect("WaitOperation")
        .into_inner();
    assert!(!op.done, "a 5000-step job is not done in 0.3 s");
    assert!(started.elapsed() >= Duration::from_millis(250));
    let meta = job_from_any(op.metadata.as_ref().expect("metadata"));
    assert!(matches!(
        state(&meta),
        v1::job::State::Queued | v1::job::State::Running
    ));
    client
        .cancel_job(v1::CancelJobRequest { name: slow.name })
        .await
        .expect("cancel the slow job");
}
