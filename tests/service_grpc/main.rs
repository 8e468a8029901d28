//! The gRPC API end to end: a tonic client generated from `proto/` (the library's own
//! `willow_service::api::grpc::pb`) talks over a loopback socket to `willow_service::api::grpc::routes` served
//! by `axum::serve` on an ephemeral port, in front of a real job core (SQLite in a temp dir,
//! real flows on a blocking worker).
//!
//! Each test starts its own server with one worker, so queue and cancel behaviour is
//! deterministic. One file a theme: `jobs`, `errors`, `service`, `options`, `curves`; this one
//! holds the meshes, the server and the client helpers they share.

use std::time::Duration;

use bytes::Bytes;
use prost::Message as _;
use tonic::transport::Channel;
use tonic::{Code, Status};
use tonic_types::StatusExt;

use willow_service::api::grpc::pb::google::longrunning as lro;
use willow_service::api::grpc::pb::willow::v1;
use willow_service::jobs::{Config, Jobs, Shutdown};
#[path = "../service_http_support/mod.rs"]
mod service_http_support;
#[path = "../webhook_support/mod.rs"]
mod webhook_support;

mod curves;
mod errors;
mod far;
mod jobs;
mod options;
mod service;
mod webhooks;

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
