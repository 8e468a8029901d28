//! The gRPC API end to end: a tonic client generated from `proto/` (the library's own
//! `willow_service::api::grpc::pb`) talks over a loopback socket to `willow_service::api::grpc::routes` served
//! by `axum::serve` on an ephemeral port, in front of a real job core (SQLite in a temp dir,
//! real flows on a blocking worker).
//!
//! Each test starts its own server with one worker, so queue and cancel behaviour is
//! deterministic.

use std::time::Duration;

use bytes::Bytes;
use prost::Message as _;
use tonic::transport::Channel;
use tonic::{Code, Status};
use tonic_types::StatusExt;

use willow_service::api::grpc::pb::google::longrunning as lro;
use willow_service::api::grpc::pb::willow::v1;
use willow_service::jobs::{Config, Jobs, Shutdown};
mod service_http_support;
use service_http_support::obj_text;
use willow::mesh::generate;
use willow::mesh::io::{Asset, Format};

use lro::operations_client::OperationsClient;
use v1::fairing_client::FairingClient;

/// Upper bound on anything a test waits for: generous for a loaded 2-core CI machine, finite
/// so a hang fails instead of blocking the suite.
const PATIENCE: Duration = Duration::from_secs(180);

// ---------------------------------------------------------------------------------------------
// Meshes

/// 162 vertices: a few flow steps take milliseconds.
fn small_obj() -> Vec<u8> {
    obj_text(&generate::bumpy_sphere(2, 0.1)).into_bytes()
}

/// 2562 vertices: many steps keep a worker busy long enough to act on a running job.
fn slow_obj() -> Vec<u8> {
    obj_text(&generate::bumpy_sphere(4, 0.1)).into_bytes()
}

/// An icosphere subdivided 7 times: 163 842 vertices, about 16 MiB of OBJ text, far above
/// gRPC's 4 MiB message limit, so it can only arrive through chunked UploadMesh.
fn large_obj() -> Vec<u8> {
    obj_text(&generate::icosphere(7)).into_bytes()
}

/// The small mesh as GLB, written by the library's own writer.
fn small_glb() -> Vec<u8> {
    let asset = Asset::read(&small_obj(), Format::Obj, &willow::mesh::Limits::default())
        .expect("generated OBJ parses");
    asset
        .write(&asset.surface().positions, Format::Glb)
        .expect("GLB writes")
}

// ---------------------------------------------------------------------------------------------
// Server and clients

struct Server {
    addr: String,
    jobs: Jobs,
    _core: Shutdown,
    _dir: tempfile::TempDir,
}

impl Server {
    async fn start(tweak: impl FnOnce(&mut Config)) -> Server {
        let dir = tempfile::tempdir().expect("temp dir");
        let mut config = Config::new(dir.path());
        config.workers = 1;
        config.queue_capacity = 8;
        tweak(&mut config);
        let (jobs, core) = Jobs::start(config).await.expect("job core starts");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind loopback");
        let addr = format!("http://{}", listener.local_addr().expect("local addr"));
        // The gRPC services alone, behind the server's authentication layer (`--auth none`:
        // every call is the anonymous caller's).
        let app = willow_service::api::auth::Auth::none()
            .wrap(willow_service::api::grpc::routes(jobs.clone()));
        tokio::spawn(async move { axum::serve(listener, app).await });
        Server {
            addr,
            jobs,
            _core: core,
            _dir: dir,
        }
    }

    async fn channel(&self) -> Channel {
        Channel::from_shared(self.addr.clone())
            .expect("valid uri")
            .connect()
            .await
            .expect("connect over h2c")
    }

    async fn fairing(&self) -> FairingClient<Channel> {
        FairingClient::new(self.channel().await)
    }

    async fn operations(&self) -> OperationsClient<Channel> {
        OperationsClient::new(self.channel().await)
    }
}

/// Stream `data` to UploadMesh in `chunk`-byte pieces.
async fn upload(
    client: &mut FairingClient<Channel>,
    format: v1::MeshFormat,
    data: &[u8],
    chunk: usize,
) -> Result<v1::Upload, Status> {
    use v1::upload_mesh_chunk::Part;
    let mut messages = vec![v1::UploadMeshChunk {
        part: Some(Part::Header(v1::UploadHeader {
            format: format as i32,
            size_bytes: data.len() as u64,
        })),
    }];
    messages.extend(data.chunks(chunk).map(|c| v1::UploadMeshChunk {
        part: Some(Part::Data(Bytes::copy_from_slice(c))),
    }));
    upload_raw(client, messages).await
}

async fn upload_raw(
    client: &mut FairingClient<Channel>,
    messages: Vec<v1::UploadMeshChunk>,
) -> Result<v1::Upload, Status> {
    client
        .upload_mesh(futures::stream::iter(messages))
        .await
        .map(|r| r.into_inner())
}

fn inline(format: v1::MeshFormat, data: Vec<u8>) -> Option<v1::create_job_request::Mesh> {
    Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
        format: format as i32,
        data: data.into(),
    }))
}

fn params(method: v1::Method, steps: u32) -> v1::JobParams {
    v1::JobParams {
        method: method as i32,
        steps: Some(steps),
        ..Default::default()
    }
}

/// A conformal job that runs all its steps (no stopping at convergence): one that is still
/// running when the test acts on it.
fn long_running(steps: u32) -> v1::JobParams {
    v1::JobParams {
        until_converged: Some(false),
        ..params(v1::Method::Conformal, steps)
    }
}

async fn create(
    client: &mut FairingClient<Channel>,
    mesh: Option<v1::create_job_request::Mesh>,
    params: v1::JobParams,
    request_id: &str,
) -> Result<lro::Operation, Status> {
    client
        .create_job(v1::CreateJobRequest {
            mesh,
            params: Some(params),
            request_id: request_id.to_string(),
        })
        .await
        .map(|r| r.into_inner())
}

/// The job's result as OBJ text, through the DownloadResult stream.
async fn download_obj(client: &mut FairingClient<Channel>, name: &str) -> String {
    let mut download = client
        .download_result(v1::DownloadResultRequest {
            name: name.to_string(),
            format: v1::MeshFormat::Obj as i32,
        })
        .await
        .expect("DownloadResult")
        .into_inner();
    let mut file = Vec::new();
    while let Some(chunk) = download.message().await.expect("download stream") {
        file.extend_from_slice(&chunk.data);
    }
    String::from_utf8(file).expect("OBJ text")
}

async fn get_job(client: &mut FairingClient<Channel>, name: &str) -> Result<v1::Job, Status> {
    client
        .get_job(v1::GetJobRequest {
            name: name.to_string(),
        })
        .await
        .map(|r| r.into_inner())
}

fn state(job: &v1::Job) -> v1::job::State {
    v1::job::State::try_from(job.state).expect("known state")
}

/// Poll GetJob until `done(job)` holds.
async fn poll_until(
    client: &mut FairingClient<Channel>,
    name: &str,
    done: impl Fn(&v1::Job) -> bool,
) -> v1::Job {
    let polling = async {
        loop {
            let job = get_job(client, name).await.expect("GetJob");
            if done(&job) {
                return job;
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    };
    tokio::time::timeout(PATIENCE, polling)
        .await
        .unwrap_or_else(|_| panic!("{name} did not reach the expected state"))
}

/// Everything StreamFrames sends for `name` from `from_step`, until the server closes it.
async fn stream_all(
    client: &mut FairingClient<Channel>,
    name: &str,
    from_step: u32,
) -> Vec<v1::stream_frames_response::Event> {
    let mut stream = client
        .stream_frames(v1::StreamFramesRequest {
            name: name.to_string(),
            from_step,
        })
        .await
        .expect("StreamFrames accepted")
        .into_inner();
    let collecting = async {
        let mut events = Vec::new();
        while let Some(msg) = stream.message().await.expect("stream stays healthy") {
            events.push(msg.event.expect("every message carries an event"));
        }
        events
    };
    tokio::time::timeout(PATIENCE, collecting)
        .await
        .expect("the frame stream ends")
}

fn job_from_any(any: &prost_types::Any) -> v1::Job {
    assert_eq!(any.type_url, "type.googleapis.com/willow.v1.Job");
    v1::Job::decode(any.value.as_slice()).expect("Any holds a Job")
}

fn violations(status: &Status) -> Vec<String> {
    status
        .get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default()
}

/// Assert INVALID_ARGUMENT whose BadRequest names exactly `field`.
fn assert_bad_field(result: Result<impl std::fmt::Debug, Status>, field: &str) {
    let status = result.expect_err("the request must be refused");
    assert_eq!(
        status.code(),
        Code::InvalidArgument,
        "{field}: {}",
        status.message()
    );
    assert_eq!(violations(&status), vec![field.to_string()], "{status:?}");
}

fn uuid() -> String {
    uuid::Uuid::new_v4().to_string()
}

// ---------------------------------------------------------------------------------------------
// Tests

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

/// Every bad input gets its canonical code and a detail naming what was wrong.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_input_gets_its_status_and_detail() {
    let server = Server::start(|c| c.limits.max_upload_bytes = 200_000).await;
    let mut client = server.fairing().await;
    let mut ops = server.operations().await;
    let obj = || inline(v1::MeshFormat::Obj, small_obj());
    let mcf = |steps| params(v1::Method::Mcf, steps);

    // Meshes.
    assert_bad_field(
        create(
            &mut client,
            inline(v1::MeshFormat::Obj, b"v 0 0 0\nf 1 2 3\n".to_vec()),
            mcf(1),
            "",
        )
        .await,
        "inline_mesh.data",
    );
    assert_bad_field(
        create(
            &mut client,
            inline(v1::MeshFormat::Unspecified, small_obj()),
            mcf(1),
            "",
        )
        .await,
        "inline_mesh.format",
    );
    assert_bad_field(create(&mut client, None, mcf(1), "").await, "mesh");
    // Two triangles sharing an edge with a third: non-manifold, refused with its rule named.
    let fin = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 -1 0\nv 0 0 1\nf 1 2 3\nf 2 1 4\nf 1 2 5\n".to_vec();
    let status = create(&mut client, inline(v1::MeshFormat::Obj, fin), mcf(1), "")
        .await
        .expect_err("non-manifold mesh");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(violations(&status), vec!["inline_mesh.data".to_string()]);
    let reason = status
        .get_details_error_info()
        .map(|e| e.reason)
        .unwrap_or_default();
    assert!(
        reason.starts_with("NON_MANIFOLD"),
        "{reason}: {}",
        status.message()
    );

    // Parameters.
    assert_bad_field(create(&mut client, obj(), mcf(0), "").await, "params.steps");
    assert_bad_field(
        create(&mut client, obj(), mcf(1_000_000), "").await,
        "params.steps",
    );
    let bad = |p: v1::JobParams| p;
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                tau: Some(-1.0),
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.tau",
    );
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                tau: Some(f64::NAN),
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.tau",
    );
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                method: 99,
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.method",
    );
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                iterations: Some(0),
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.iterations",
    );
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                frame_interval: Some(0),
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.frame_interval",
    );
    let negative = prost_types::Duration {
        seconds: -1,
        nanos: 0,
    };
    assert_bad_field(
        create(
            &mut client,
            obj(),
            bad(v1::JobParams {
                deadline: Some(negative),
                ..mcf(1)
            }),
            "",
        )
        .await,
        "params.deadline",
    );

    // Names.
    assert_bad_field(get_job(&mut client, "not-a-name").await, "name");
    assert_bad_field(get_job(&mut client, "jobs/a/b").await, "name");
    let missing = get_job(&mut client, "jobs/00000000-0000-4000-8000-000000000000")
        .await
        .expect_err("unknown job");
    assert_eq!(missing.code(), Code::NotFound);
    assert!(missing.get_details_resource_info().is_some());
    let no_upload = create(
        &mut client,
        Some(v1::create_job_request::Mesh::Upload("uploads/nope".into())),
        mcf(1),
        "",
    )
    .await
    .expect_err("unknown upload");
    assert_eq!(no_upload.code(), Code::NotFound, "{}", no_upload.message());
    assert_bad_field(
        create(
            &mut client,
            Some(v1::create_job_request::Mesh::Upload("nope".into())),
            mcf(1),
            "",
        )
        .await,
        "upload",
    );

    // Upload streams.
    use v1::upload_mesh_chunk::Part;
    let header = |format: v1::MeshFormat, size: u64| v1::UploadMeshChunk {
        part: Some(Part::Header(v1::UploadHeader {
            format: format as i32,
            size_bytes: size,
        })),
    };
    let data = |b: &[u8]| v1::UploadMeshChunk {
        part: Some(Part::Data(Bytes::copy_from_slice(b))),
    };
    assert_bad_field(upload_raw(&mut client, vec![]).await, "header");
    assert_bad_field(
        upload_raw(&mut client, vec![data(b"v 0 0 0\n")]).await,
        "header",
    );
    assert_bad_field(
        upload_raw(
            &mut client,
            vec![
                header(v1::MeshFormat::Obj, 0),
                header(v1::MeshFormat::Obj, 0),
            ],
        )
        .await,
        "header",
    );
    assert_bad_field(
        upload_raw(
            &mut client,
            vec![header(v1::MeshFormat::Unspecified, 0), data(b"v")],
        )
        .await,
        "header.format",
    );
    assert_bad_field(
        upload_raw(
            &mut client,
            vec![header(v1::MeshFormat::Obj, 100), data(b"v 0 0 0\n")],
        )
        .await,
        "header.size_bytes",
    );
    assert_bad_field(
        upload(&mut client, v1::MeshFormat::Glb, b"not a glb at all", 4).await,
        "data",
    );
    // Over the server's 200 000-byte limit: announced, and not announced.
    for (announce, field) in [(true, "header.size_bytes"), (false, "data")] {
        let big = vec![b'#'; 300_000];
        let size = if announce { big.len() as u64 } else { 0 };
        let msgs = vec![
            header(v1::MeshFormat::Obj, size),
            data(&big[..150_000]),
            data(&big[150_000..]),
        ];
        let status = upload_raw(&mut client, msgs)
            .await
            .expect_err("over the limit");
        assert_eq!(
            status.code(),
            Code::ResourceExhausted,
            "{}",
            status.message()
        );
        assert!(
            status.get_details_retry_info().is_none(),
            "retrying cannot help"
        );
        let quota = status.get_details_quota_failure().expect("QuotaFailure");
        assert!(
            quota.violations[0].description.contains("200000"),
            "{quota:?}"
        );
        assert_eq!(violations(&status), vec![field.to_string()]);
    }

    // Lists.
    assert_bad_field(
        client
            .list_jobs(v1::ListJobsRequest {
                page_size: -1,
                ..Default::default()
            })
            .await,
        "page_size",
    );
    assert_bad_field(
        ops.list_operations(lro::ListOperationsRequest {
            name: "jobs".into(),
            filter: "done=true".into(),
            ..Default::default()
        })
        .await,
        "filter",
    );

    // A result before the job has one.
    let op = create(&mut client, obj(), mcf(1), "")
        .await
        .expect("a good job");
    let early = client
        .download_result(v1::DownloadResultRequest {
            name: op.name.clone(),
            format: v1::MeshFormat::Obj as i32,
        })
        .await;
    if let Err(status) = early {
        assert_eq!(
            status.code(),
            Code::FailedPrecondition,
            "{}",
            status.message()
        );
    } // (the 1-step job may already have succeeded: then there is a result, which is fine)
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

/// grpc.health.v1 answers SERVING while the core is ready and NOT_SERVING once it drains;
/// reflection lists every service, health included, and serves their descriptors.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    use tonic_health::pb::HealthCheckRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let server = Server::start(|_| {}).await;
    let mut health = HealthClient::new(server.channel().await);
    let check = |service: &str| HealthCheckRequest {
        service: service.to_string(),
    };
    // Workers mark themselves alive just after start: allow them a moment.
    let mut status = 0;
    for _ in 0..100 {
        status = health
            .check(check(""))
            .await
            .expect("Check")
            .into_inner()
            .status;
        if status == ServingStatus::Serving as i32 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(status, ServingStatus::Serving as i32);
    for service in willow_service::api::grpc::SERVICE_NAMES {
        let s = health
            .check(check(service))
            .await
            .expect("Check")
            .into_inner();
        assert_eq!(s.status, ServingStatus::Serving as i32, "{service}");
    }
    let unknown = health
        .check(check("no.such.Service"))
        .await
        .expect_err("unknown");
    assert_eq!(unknown.code(), Code::NotFound);

    let mut reflection = ServerReflectionClient::new(server.channel().await);
    let ask = |m: MessageRequest| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(m),
    };
    let mut replies = reflection
        .server_reflection_info(futures::stream::iter(vec![
            ask(MessageRequest::ListServices(String::new())),
            ask(MessageRequest::FileContainingSymbol(
                "willow.v1.Fairing".into(),
            )),
        ]))
        .await
        .expect("reflection stream")
        .into_inner();
    let mut services = Vec::new();
    let mut files = 0;
    while let Some(reply) = replies.message().await.expect("reflection reply") {
        match reply.message_response {
            Some(MessageResponse::ListServicesResponse(list)) => {
                services.extend(list.service.into_iter().map(|s| s.name))
            }
            Some(MessageResponse::FileDescriptorResponse(fds)) => {
                files += fds.file_descriptor_proto.len()
            }
            other => panic!("unexpected reflection reply {other:?}"),
        }
    }
    for want in [
        "willow.v1.Fairing",
        "google.longrunning.Operations",
        "grpc.health.v1.Health",
        "grpc.reflection.v1.ServerReflection",
    ] {
        assert!(
            services.iter().any(|s| s == want),
            "{want} not in {services:?}"
        );
    }
    assert!(files >= 1, "fairing.proto's descriptor is served");

    // Draining flips health at once.
    server.jobs.begin_drain();
    let s = health.check(check("")).await.expect("Check").into_inner();
    assert_eq!(s.status, ServingStatus::NotServing as i32);
    let refused = create(
        &mut server.fairing().await,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Mcf, 1),
        "",
    )
    .await
    .expect_err("no new jobs while draining");
    assert_eq!(refused.code(), Code::Unavailable);
    assert!(refused.get_details_retry_info().is_some());
}

// ---------------------------------------------------------------------------------------------
// Issue 4: the rest of FlowParams as JobParams fields, and FairCurve.

fn prescribed(
    frame_angle: f64,
    axis: Option<v1::rotation_axis::Axis>,
    angles: Option<v1::boundary_angles::Angles>,
) -> Option<v1::Boundary> {
    Some(v1::Boundary {
        condition: Some(v1::boundary::Condition::Prescribed(v1::PrescribedVectors {
            frame_angle,
            axis: Some(v1::RotationAxis { axis }),
            angles: Some(v1::BoundaryAngles { angles }),
        })),
    })
}

fn condition(c: v1::boundary::Condition) -> Option<v1::Boundary> {
    Some(v1::Boundary { condition: Some(c) })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flow_options_are_reported_back_refused_by_field_and_run() {
    use v1::boundary::Condition;
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let sphere = || inline(v1::MeshFormat::Obj, small_obj());
    let cap = || {
        inline(
            v1::MeshFormat::Obj,
            obj_text(&generate::bumpy_cap(3, 0.06)).into_bytes(),
        )
    };

    // Every field set: accepted, reported by CreateJob's metadata and by GetJob, and run.
    let options = v1::JobParams {
        exactness: Some(false),
        mobius_balancing: Some(true),
        filter: Some(v1::SpectralFilter { sigma: 0.01, k: 2 }),
        boundary: prescribed(
            0.2,
            Some(v1::rotation_axis::Axis::Fixed(v1::Vector3 {
                x: 0.0,
                y: 0.0,
                z: 1.0,
            })),
            Some(v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                values: vec![0.15],
            })),
        ),
        ..params(v1::Method::Conformal, 2)
    };
    let op = create(&mut client, cap(), options.clone(), "")
        .await
        .expect("CreateJob with every option");
    let reported = job_from_any(op.metadata.as_ref().expect("metadata"))
        .params
        .expect("params");
    assert_eq!(reported.exactness, Some(false));
    assert_eq!(reported.mobius_balancing, Some(true));
    assert_eq!(reported.filter, options.filter);
    assert_eq!(reported.boundary, options.boundary);
    let done = poll_until(&mut client, &op.name, |j| {
        state(j) != v1::job::State::Queued && state(j) != v1::job::State::Running
    })
    .await;
    assert_eq!(state(&done), v1::job::State::Succeeded, "{:?}", done.error);
    assert_eq!(
        done.params.as_ref().map(|p| &p.boundary),
        Some(&options.boundary)
    );

    // Unset fields report their defaults; an empty Boundary is free.
    let op = create(
        &mut client,
        sphere(),
        v1::JobParams {
            boundary: Some(v1::Boundary::default()),
            ..params(v1::Method::Conformal, 1)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let p = get_job(&mut client, &op.name)
        .await
        .expect("GetJob")
        .params
        .expect("params");
    assert_eq!(p.exactness, Some(true));
    assert_eq!(p.mobius_balancing, Some(false));
    assert_eq!(p.filter, None);
    assert_eq!(p.boundary, condition(Condition::Free(())));

    // Taubin and a CMC boundary run to completion (CMC needs the prescribed-vectors solver).
    for (mesh, p) in [
        (
            sphere(),
            v1::JobParams {
                tau: Some(0.3),
                ..params(v1::Method::Taubin, 3)
            },
        ),
        (
            cap(),
            v1::JobParams {
                boundary: condition(Condition::Cmc(())),
                ..params(v1::Method::Conformal, 2)
            },
        ),
    ] {
        let op = create(&mut client, mesh, p.clone(), "")
            .await
            .expect("CreateJob");
        let done = poll_until(&mut client, &op.name, |j| {
            !matches!(state(j), v1::job::State::Queued | v1::job::State::Running)
        })
        .await;
        assert_eq!(
            state(&done),
            v1::job::State::Succeeded,
            "{p:?}: {:?}",
            done.error
        );
        assert_eq!(
            done.params.map(|q| q.boundary),
            Some(p.boundary.or(condition(Condition::Free(()))))
        );
    }

    // Each bad value: INVALID_ARGUMENT naming the field's path in the request.
    let conformal = || params(v1::Method::Conformal, 1);
    let filter = |sigma, k| Some(v1::SpectralFilter { sigma, k });
    let fixed = |x, y, z| Some(v1::rotation_axis::Axis::Fixed(v1::Vector3 { x, y, z }));
    let uniform = |a| Some(v1::boundary_angles::Angles::Uniform(a));
    let cases: Vec<(Option<v1::create_job_request::Mesh>, v1::JobParams, &str)> = vec![
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.1, 4),
                ..conformal()
            },
            "params.filter.k",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.0, 2),
                ..conformal()
            },
            "params.filter.sigma",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(f64::NAN, 2),
                ..conformal()
            },
            "params.filter.sigma",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(1.6, None, None),
                ..conformal()
            },
            "params.boundary.prescribed.frame_angle",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(-1.55, None, None),
                ..conformal()
            },
            "params.boundary.prescribed.frame_angle",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, fixed(0.0, 0.0, 0.0), None),
                ..conformal()
            },
            "params.boundary.prescribed.axis.fixed",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, fixed(f64::NAN, 0.0, 1.0), None),
                ..conformal()
            },
            "params.boundary.prescribed.axis.fixed",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, None, uniform(f64::INFINITY)),
                ..conformal()
            },
            "params.boundary.prescribed.angles.uniform",
        ),
        (
            sphere(),
            v1::JobParams {
                boundary: prescribed(
                    0.0,
                    None,
                    Some(v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                        values: vec![0.1],
                    })),
                ),
                ..conformal()
            },
            "params.boundary.prescribed.angles.per_loop.values",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.1, 1),
                ..params(v1::Method::Mcf, 1)
            },
            "params.filter",
        ),
        (
            sphere(),
            v1::JobParams {
                exactness: Some(false),
                ..params(v1::Method::Taubin, 1)
            },
            "params.exactness",
        ),
        (
            sphere(),
            v1::JobParams {
                mobius_balancing: Some(true),
                ..params(v1::Method::Mcf, 1)
            },
            "params.mobius_balancing",
        ),
        (
            sphere(),
            v1::JobParams {
                boundary: condition(Condition::Fixed(())),
                ..params(v1::Method::Bilaplacian, 1)
            },
            "params.boundary",
        ),
    ];
    for (mesh, p, field) in cases {
        assert_bad_field(create(&mut client, mesh, p, "").await, field);
    }
    // The defaults of conformal-only options are fine with any method.
    let op = create(
        &mut client,
        sphere(),
        v1::JobParams {
            exactness: Some(true),
            mobius_balancing: Some(false),
            boundary: condition(Condition::Free(())),
            tau: Some(0.1),
            ..params(v1::Method::Mcf, 1)
        },
        "",
    )
    .await;
    assert!(op.is_ok(), "{op:?}");
}

/// r = 1 + 0.2 sin 5t plus a deterministic jitter, as packed x, y.
fn noisy_closed_curve(n: usize) -> Vec<f64> {
    (0..n)
        .flat_map(|i| {
            let t = std::f64::consts::TAU * i as f64 / n as f64;
            let jitter = 0.01 * (((i * 7919) % 13) as f64 / 13.0 - 0.5);
            let r = 1.0 + 0.2 * (5.0 * t).sin() + jitter;
            [r * t.cos(), r * t.sin()]
        })
        .collect()
}

/// The library's measures of a closed curve: (σ(κ)/κ̄ with its own dual lengths, length).
fn curve_measures(xy: &[f64]) -> (f64, f64) {
    use willow::curve::{curvature_std_over_mean, dual_lengths, Curve};
    let points: Vec<[f64; 2]> = xy.chunks_exact(2).map(|c| [c[0], c[1]]).collect();
    let curve = Curve::new(points, true).expect("valid curve");
    let mut dual = vec![0.0; curve.points.len()];
    dual_lengths(&curve.edge_lengths(), true, &mut dual);
    (
        curvature_std_over_mean(&curve.curvature(), &dual),
        curve.length(),
    )
}

fn curve_request(xy: Vec<f64>, closed: bool) -> v1::FairCurveRequest {
    v1::FairCurveRequest {
        curve: Some(v1::Curve { xy, closed }),
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fair_curve_rounds_a_noisy_curve_and_refuses_hostile_input() {
    let server = Server::start(|c| {
        c.limits.max_curve_points = 60_000;
        c.limits.max_curve_frame_points = 5_000;
    })
    .await;
    let mut client = server.fairing().await;
    let input = noisy_closed_curve(256);
    let (before, length) = curve_measures(&input);
    assert!(before > 0.5, "noisy: σ/κ̄ = {before}");

    let out = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(6),
            ..curve_request(input.clone(), true)
        })
        .await
        .expect("FairCurve")
        .into_inner();
    let curve = out.curve.expect("curve");
    assert!(curve.closed);
    assert_eq!(curve.xy.len(), input.len());
    let (after, new_length) = curve_measures(&curve.xy);
    assert!(after < 1e-2 * before, "σ/κ̄ from {before} to {after}");
    assert!(
        (new_length / length - 1.0).abs() < 1e-3,
        "{length} → {new_length}"
    );
    assert_eq!(out.metrics.len(), 7);
    assert_eq!(out.metrics.last().map(|m| m.step), Some(6));
    assert!((out.metrics[6].curvature_std_over_mean - after).abs() < 1e-3);
    assert_eq!((out.steps, out.tau, out.frame_interval), (6, 0.5, 0));
    assert_eq!(
        out.deadline.map(|d| d.seconds),
        Some(10),
        "the server default"
    );
    assert!(out.frames.is_empty());

    let out = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(5),
            frame_interval: 2,
            ..curve_request(input.clone(), true)
        })
        .await
        .expect("FairCurve with frames")
        .into_inner();
    let steps: Vec<u32> = out.frames.iter().map(|f| f.step).collect();
    assert_eq!(steps, vec![0, 2, 4, 5]);
    assert_eq!(
        out.frames[0].curve.as_ref().map(|c| &c.xy),
        Some(&input),
        "frame 0 is the input, bit for bit"
    );
    assert_eq!(out.frames[3].curve, out.curve);

    // Hostile input: each refused with the field (and for curves, the reason) named.
    let reason = |s: &Status| {
        s.get_details_error_info()
            .map(|e| e.reason)
            .unwrap_or_default()
    };
    let mut repeated = input.clone();
    repeated.extend_from_slice(&input[..2]);
    let mut nan = input.clone();
    nan[7] = f64::NAN;
    for (request, field, why) in [
        (curve_request(input[..5].to_vec(), true), "curve.xy", ""),
        (curve_request(nan, true), "curve.xy", "NON_FINITE"),
        (
            curve_request(repeated, true),
            "curve.xy",
            "ZERO_LENGTH_EDGE",
        ),
        (
            curve_request(vec![0.0, 0.0, 1.0, 0.0], true),
            "curve.xy",
            "TOO_FEW_POINTS",
        ),
        (
            curve_request(Vec::new(), false),
            "curve.xy",
            "TOO_FEW_POINTS",
        ),
        (
            curve_request(vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0], false),
            "curve.xy",
            "CUSP",
        ),
        (v1::FairCurveRequest::default(), "curve", ""),
        (
            v1::FairCurveRequest {
                steps: Some(0),
                ..curve_request(input.clone(), true)
            },
            "steps",
            "",
        ),
        (
            v1::FairCurveRequest {
                steps: Some(5000),
                ..curve_request(input.clone(), true)
            },
            "steps",
            "",
        ),
        (
            v1::FairCurveRequest {
                tau: Some(1.0),
                ..curve_request(input.clone(), true)
            },
            "tau",
            "",
        ),
        (
            v1::FairCurveRequest {
                tau: Some(f64::NAN),
                ..curve_request(input.clone(), true)
            },
            "tau",
            "",
        ),
        (
            v1::FairCurveRequest {
                deadline: Some(prost_types::Duration {
                    seconds: 0,
                    nanos: 0,
                }),
                ..curve_request(input.clone(), true)
            },
            "deadline",
            "",
        ),
        (
            v1::FairCurveRequest {
                deadline: Some(prost_types::Duration {
                    seconds: 1000,
                    nanos: 0,
                }),
                ..curve_request(input.clone(), true)
            },
            "deadline",
            "",
        ),
        // 256 points × 101 frames is over this server's 5000 frame points.
        (
            v1::FairCurveRequest {
                steps: Some(100),
                frame_interval: 1,
                ..curve_request(input.clone(), true)
            },
            "frame_interval",
            "",
        ),
    ] {
        let status = client.fair_curve(request).await.expect_err("refused");
        assert_eq!(
            status.code(),
            Code::InvalidArgument,
            "{field}: {}",
            status.message()
        );
        assert_eq!(violations(&status), vec![field.to_string()], "{status:?}");
        if !why.is_empty() {
            assert_eq!(reason(&status), why, "{}", status.message());
        }
    }
    // Too many points: a named quota, like an oversized mesh.
    let status = client
        .fair_curve(curve_request(noisy_closed_curve(60_001), true))
        .await
        .expect_err("too many points");
    assert_eq!(status.code(), Code::ResourceExhausted);
    let quota = status
        .get_details_quota_failure()
        .map(|q| {
            q.violations
                .into_iter()
                .map(|v| v.subject)
                .collect::<Vec<_>>()
        })
        .unwrap_or_default();
    assert_eq!(quota, vec!["curve points".to_string()]);
    // The request's deadline ends a long run (50k points, 1000 steps) with DEADLINE_EXCEEDED.
    let status = client
        .fair_curve(v1::FairCurveRequest {
            steps: Some(1000),
            deadline: Some(prost_types::Duration {
                seconds: 0,
                nanos: 300_000_000,
            }),
            ..curve_request(noisy_closed_curve(50_000), true)
        })
        .await
        .expect_err("over its deadline");
    assert_eq!(
        status.code(),
        Code::DeadlineExceeded,
        "{}",
        status.message()
    );
    assert!(
        status.message().contains("deadline of 0.3 s"),
        "{}",
        status.message()
    );
}

// ---------------------------------------------------------------------------------------------
// Issue 10: safeguarded steps.

/// The frames StreamFrames sent, in order.
fn frames_of(events: &[v1::stream_frames_response::Event]) -> Vec<v1::Frame> {
    use v1::stream_frames_response::Event;
    events
        .iter()
        .filter_map(|e| match e {
            Event::Frame(f) => Some(f.clone()),
            Event::Job(_) => None,
        })
        .collect()
}

/// `safeguard` is reported back by CreateJob and GetJob; frames carry the τ each step used
/// and its rejected tries; and a job whose flow can make no acceptable step (implicit MCF at
/// τ = 1000 on `bumpy_sphere(2, 0.4)`: steps 1 and 2 are kept, step 3 raises W even at
/// τ/1024) ends SUCCEEDED after step 2 with Job.stopped_early (reason NO_PROGRESS), and
/// DownloadResult gives the surface of the last frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safeguard_option_frame_tau_and_no_progress_keeps_the_last_good_mesh() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let bumpy = obj_text(&generate::bumpy_sphere(2, 0.4)).into_bytes();

    for (safeguard, reported) in [(None, true), (Some(false), false), (Some(true), true)] {
        let op = create(
            &mut client,
            inline(v1::MeshFormat::Obj, bumpy.clone()),
            v1::JobParams {
                tau: Some(0.5),
                safeguard,
                ..params(v1::Method::Conformal, 3)
            },
            "",
        )
        .await
        .expect("CreateJob");
        let created = job_from_any(op.metadata.as_ref().expect("metadata"));
        assert_eq!(
            created.params.as_ref().and_then(|p| p.safeguard),
            Some(reported),
            "{safeguard:?}"
        );
        let frames = frames_of(&stream_all(&mut client, &op.name, 0).await);
        assert_eq!(frames.len(), 4, "{safeguard:?}");
        let metrics: Vec<(f64, u32)> = frames
            .iter()
            .map(|f| {
                let m = f.metrics.as_ref().expect("metrics");
                (m.tau, m.rejected)
            })
            .collect();
        assert_eq!(metrics, vec![(0.0, 0), (0.5, 0), (0.5, 0), (0.5, 0)]);
        let done = get_job(&mut client, &op.name).await.expect("GetJob");
        assert_eq!(state(&done), v1::job::State::Succeeded);
        assert_eq!(done.params.and_then(|p| p.safeguard), Some(reported));
        assert_eq!(done.latest.map(|m| m.tau), Some(0.5));
        assert_eq!(done.stopped_early, None);
    }

    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, bumpy.clone()),
        v1::JobParams {
            tau: Some(1000.0),
            ..params(v1::Method::Mcf, 6)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let frames = frames_of(&stream_all(&mut client, &op.name, 0).await);
    assert_eq!(
        frames.iter().map(|f| f.step).collect::<Vec<_>>(),
        vec![0, 1, 2],
        "steps 1 and 2 kept"
    );
    let last = frames.last().expect("a frame");
    assert_eq!(last.metrics.as_ref().map(|m| m.tau), Some(1000.0));
    let done = get_job(&mut client, &op.name).await.expect("GetJob");
    assert_eq!(state(&done), v1::job::State::Succeeded, "{:?}", done.error);
    assert_eq!(done.error, None, "not a failure");
    assert_eq!((done.step, done.total_steps), (2, 6));
    let note = done.stopped_early.expect("Job.stopped_early");
    assert_eq!(note.code, Code::Ok as i32);
    assert!(
        note.message.contains("no progress at step 3")
            && note.message.contains("Willmore energy would rise"),
        "{}",
        note.message
    );
    let info = note
        .details
        .iter()
        .find(|d| d.type_url == "type.googleapis.com/google.rpc.ErrorInfo")
        .map(|d| tonic_types::pb::ErrorInfo::decode(d.value.as_ref()).expect("ErrorInfo"))
        .expect("ErrorInfo detail");
    assert_eq!(info.reason, "NO_PROGRESS");

    let text = download_obj(&mut client, &op.name).await;
    let frame = service_http_support::f32_triples(
        last.positions
            .as_ref()
            .expect("the last frame carries positions"),
    );
    service_http_support::assert_obj_result_is_frame(&text, &frame, 162);
}

// ---------------------------------------------------------------------------------------------
// Issue 12, part 4: one error contract.

/// A unary call with hand-made request bytes over h2c; returns `grpc-status` and
/// `grpc-message` (a request refused before the handler runs is a trailers-only response:
/// both are headers).
async fn raw_unary(addr: &str, method: &str, message: &[u8]) -> (String, String) {
    let client = reqwest::Client::builder()
        .http2_prior_knowledge()
        .build()
        .expect("h2c client");
    let mut body = vec![0u8];
    body.extend_from_slice(&(message.len() as u32).to_be_bytes());
    body.extend_from_slice(message);
    let res = client
        .post(format!("{addr}/willow.v1.Fairing/{method}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(body)
        .send()
        .await
        .expect("raw gRPC call");
    let header = |name: &str| {
        res.headers()
            .get(name)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string()
    };
    (header("grpc-status"), header("grpc-message"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_protobuf_and_invalid_utf8_are_invalid_argument() {
    let server = Server::start(|_| {}).await;
    // GetJobRequest.name (field 1, length-delimited) claims 5 bytes and has 1: truncated.
    let (status, message) = raw_unary(&server.addr, "GetJob", &[0x0a, 0x05, b'a']).await;
    assert_eq!(status, "3", "truncated message: {message}");
    // The same field holding bytes that are not UTF-8.
    let (status, message) = raw_unary(&server.addr, "GetJob", &[0x0a, 0x02, 0xff, 0xfe]).await;
    assert_eq!(status, "3", "invalid UTF-8: {message}");
    // A well-formed request still reaches the handler (NOT_FOUND for an unknown job).
    let ok = v1::GetJobRequest {
        name: format!("jobs/{}", uuid()),
    }
    .encode_to_vec();
    let (status, _) = raw_unary(&server.addr, "GetJob", &ok).await;
    assert_eq!(status, "5");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn negative_from_step_is_refused_not_waited_on() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, small_obj()),
        params(v1::Method::Conformal, 2),
        &uuid(),
    )
    .await
    .expect("CreateJob");
    // A client's int32 -1 arrives in the uint32 field as u32::MAX.
    for from_step in [u32::MAX, i32::MAX as u32 + 1, 1_000_000] {
        let result = tokio::time::timeout(
            PATIENCE,
            client.stream_frames(v1::StreamFramesRequest {
                name: op.name.clone(),
                from_step,
            }),
        )
        .await
        .expect("answered, not left waiting");
        assert_bad_field(result.map(|_| ()), "from_step");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_user_text_is_capped_in_status_messages() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let long = "x".repeat(1 << 20);
    let status = client
        .get_job(v1::GetJobRequest {
            name: format!("jobs/{long}"),
        })
        .await
        .expect_err("no such job");
    assert_eq!(status.code(), Code::NotFound, "{}", &status.message()[..80]);
    assert!(
        status.message().chars().count() <= 1025,
        "{} chars",
        status.message().len()
    );
    let status = client
        .create_job(v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::Upload(format!(
                "uploads/{long}"
            ))),
            params: Some(params(v1::Method::Conformal, 2)),
            request_id: uuid(),
        })
        .await
        .expect_err("no such upload");
    assert!(
        status.message().chars().count() <= 1025,
        "{} chars",
        status.message().len()
    );
}
