//! The gRPC transport: `willow.v1.Fairing`, `google.longrunning.Operations`, `grpc.health.v1`
//! and server reflection, all over the same [`Jobs`] handle the HTTP layer uses.
//!
//! The wire contract is `proto/willow/v1/fairing.proto`; `build.rs` generates [`pb`] from it.
//! This file only translates: wire request → validated [`JobSpec`] / [`UploadRef`] → a call on
//! [`Jobs`] → wire response. Every [`JobError`] becomes a [`tonic::Status`] in exactly one
//! place, `job_error`, with the google.rpc error details the proto documents.
//!
//! Entry point for the server: [`routes`] returns an axum router serving all of the above on
//! the `/{package}.{Service}/{Method}` paths, to merge into the HTTP router on one port.
//!
//! Health needs no drain hook: every `Check` and `Watch` reads [`Jobs::is_ready`], so
//! [`Jobs::begin_drain`] (or a stalled worker) turns gRPC health `NOT_SERVING` at once, exactly
//! when `/readyz` turns false.

use std::collections::HashMap;
use std::pin::Pin;
use std::time::Duration;

use bytes::Bytes;
use futures::{Stream, StreamExt};
use prost::Message as _;
use tonic::{Code, Request, Response, Status, Streaming};
use tonic_types::{ErrorDetails, StatusExt};

use super::problem::cap_detail;
use crate::jobs::curve::{CurveInput, CurveOutcome, CurveSpec};
use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
use crate::jobs::{
    Caller, Frame, JobError, JobEvent, JobSpec, JobState, JobStatus, Jobs, UploadRef,
};
use willow::flow::Method;
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

/// Code generated from `proto/` by `build.rs` (prost messages, tonic servers and clients).
///
/// Layout follows the proto packages: `pb::willow::v1`, `pb::google::longrunning`,
/// `pb::google::api`. `google.rpc` types are tonic-types' own ([`tonic_types::pb`]).
pub mod pb {
    #![allow(clippy::all, clippy::pedantic, missing_docs, rustdoc::all)]
    include!(concat!(env!("OUT_DIR"), "/willow_proto.rs"));

    /// Encoded `FileDescriptorSet` of `fairing.proto` and its imports, for reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/willow_descriptor.bin"));
}

use pb::google::longrunning as lro;
use pb::willow::v1;

/// `google.rpc.ErrorInfo.domain` of the errors this service produces.
const ERROR_DOMAIN: &str = "willow.v1";

/// `type_url` of a `willow.v1.Job` packed in `google.protobuf.Any` (Operation metadata and
/// response). The `type.googleapis.com/` prefix is what every protobuf runtime expects.
const JOB_TYPE_URL: &str = "type.googleapis.com/willow.v1.Job";

/// `type_url` of `google.rpc.ErrorInfo`, attached to a failed job's `google.rpc.Status`.
const ERROR_INFO_TYPE_URL: &str = "type.googleapis.com/google.rpc.ErrorInfo";

/// Largest message the Fairing service decodes. gRPC's default is 4 MiB; a little more lets a
/// client send 4 MiB upload chunks (plus framing) or a full 4 MiB inline mesh without tripping
/// over the envelope. Larger meshes go through `UploadMesh`, so this never needs to grow.
const MAX_DECODING_MESSAGE_BYTES: usize = (4 << 20) + (64 << 10);

/// Size of the chunks `DownloadResult` sends: well under every client's 4 MiB default, large
/// enough that per-message overhead is negligible.
const DOWNLOAD_CHUNK_BYTES: usize = 1 << 20;

/// Upper bound of one `WaitOperation` call. AIP-151 lets the server cap the wait; a bounded
/// long-poll keeps idle connections from piling up behind a load balancer's idle timeout.
const MAX_WAIT: Duration = Duration::from_secs(60);

/// Time kept back from the client's own deadline in `WaitOperation`, so the server answers with
/// the operation (not done yet) before the client gives up with DEADLINE_EXCEEDED.
const WAIT_DEADLINE_MARGIN: Duration = Duration::from_millis(100);

/// How often a health `Watch` stream re-reads readiness. Probes poll every few seconds; one
/// second keeps the reported status fresh at negligible cost.
const HEALTH_WATCH_PERIOD: Duration = Duration::from_secs(1);

/// Longest user-supplied text echoed back in an error message: a 1 MB bogus name must not
/// become a 1 MB status message (which would also exceed header size limits).
const MAX_ECHO_CHARS: usize = 80;

/// The gRPC services as an axum router, to merge into the HTTP router (the paths are
/// `/willow.v1.Fairing/*`, `/google.longrunning.Operations/*`, `/grpc.health.v1.Health/*` and
/// `/grpc.reflection.v1{,alpha}.ServerReflection/*`, so nothing collides with REST routes).
///
/// Health reflects [`Jobs::is_ready`] on every call: nothing to do on drain beyond
/// [`Jobs::begin_drain`].
pub fn routes(jobs: Jobs) -> axum::Router {
    let api = GrpcApi { jobs: jobs.clone() };
    tonic::service::Routes::new(
        v1::fairing_server::FairingServer::new(api.clone())
            .max_decoding_message_size(MAX_DECODING_MESSAGE_BYTES),
    )
    .add_service(lro::operations_server::OperationsServer::new(api))
    .add_service(tonic_health::pb::health_server::HealthServer::new(
        HealthService { jobs },
    ))
    .add_service(reflection_v1())
    .add_service(reflection_v1alpha())
    .prepare()
    .into_axum_router()
}

/// The fully qualified names of the services [`routes`] serves (health and reflection aside),
/// as health checks and reflection name them.
pub const SERVICE_NAMES: [&str; 2] = ["willow.v1.Fairing", "google.longrunning.Operations"];

fn reflection_builder() -> tonic_reflection::server::Builder<'static> {
    tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        // Health's descriptor too, or reflection clients (buf curl, grpcurl) cannot call it.
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
}

/// Reflection v1 (grpcurl, buf curl, grpcio-reflection).
fn reflection_v1() -> tonic_reflection::server::v1::ServerReflectionServer<
    impl tonic_reflection::server::v1::ServerReflection,
> {
    reflection_builder()
        .build_v1()
        // Both descriptor sets are compiled in (ours by build.rs, health's by tonic-health) and
        // decoded by the reflection tests, so this cannot fail at run time.
        .expect("compiled-in file descriptor sets decode")
}

/// Reflection v1alpha, still the only version some clients speak.
fn reflection_v1alpha() -> tonic_reflection::server::v1alpha::ServerReflectionServer<
    impl tonic_reflection::server::v1alpha::ServerReflection,
> {
    reflection_builder()
        .build_v1alpha()
        // Same descriptor sets as `reflection_v1`: see there.
        .expect("compiled-in file descriptor sets decode")
}

/// Implements both `willow.v1.Fairing` and `google.longrunning.Operations`: they are two views
/// of the same jobs (an Operation's name is its job's name).
#[derive(Clone)]
struct GrpcApi {
    jobs: Jobs,
}

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

#[tonic::async_trait]
impl v1::fairing_server::Fairing for GrpcApi {
    async fn upload_mesh(
        &self,
        request: Request<Streaming<v1::UploadMeshChunk>>,
    ) -> Result<Response<v1::Upload>, Status> {
        let caller = caller(&request)?;
        let mut chunks = request.into_inner();
        let limit = self.jobs.config().limits.max_upload_bytes;
        let mut upload = UploadAssembly::start(chunks.message().await?, limit)?;
        while let Some(chunk) = chunks.message().await? {
            upload.push(chunk)?;
        }
        let (data, format) = upload.finish()?;
        let size_bytes = data.len() as u64;
        let id = self
            .jobs
            .store_upload(&caller, Bytes::from(data), format)
            .await
            .map_err(|e| job_error(e, "data"))?;
        Ok(Response::new(v1::Upload {
            name: format!("uploads/{id}"),
            format: format_pb(format) as i32,
            size_bytes,
        }))
    }

    async fn create_job(
        &self,
        request: Request<v1::CreateJobRequest>,
    ) -> Result<Response<lro::Operation>, Status> {
        use v1::create_job_request::Mesh;
        let caller = caller(&request)?;
        let request = request.into_inner();
        let (upload, mesh_field) = match request.mesh {
            Some(Mesh::Upload(name)) => (
                UploadRef::Stored {
                    upload_id: parse_name("upload", "uploads/", &name)?,
                },
                "upload",
            ),
            Some(Mesh::InlineMesh(mesh)) => (
                UploadRef::Bytes {
                    data: mesh.data,
                    format: format_from_pb("inline_mesh.format", mesh.format)?,
                },
                "inline_mesh.data",
            ),
            None => {
                return Err(bad_request(
                    "mesh",
                    "set `upload` (a name from UploadMesh) or `inline_mesh`",
                ))
            }
        };
        let spec = spec_from_pb(request.params)?;
        let key = request_id(&request.request_id)?;
        let status = self
            .jobs
            .submit(&caller, upload, spec, key)
            .await
            .map_err(|e| job_error(e, mesh_field))?;
        Ok(Response::new(operation(&status)))
    }

    async fn get_job(
        &self,
        request: Request<v1::GetJobRequest>,
    ) -> Result<Response<v1::Job>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        let status = self
            .jobs
            .get(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(job_pb(&status)))
    }

    async fn list_jobs(
        &self,
        request: Request<v1::ListJobsRequest>,
    ) -> Result<Response<v1::ListJobsResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        let page_size = page_size(request.page_size)?;
        let state = match v1::job::State::try_from(request.state) {
            Ok(v1::job::State::Unspecified) => None,
            Ok(s) => Some(state_from_pb(s)),
            Err(_) => {
                return Err(bad_request(
                    "state",
                    format!("unknown job state {}", request.state),
                ))
            }
        };
        let token = Some(request.page_token).filter(|t| !t.is_empty());
        let (jobs, next) = self
            .jobs
            .list(&caller, state, page_size, token)
            .await
            .map_err(|e| job_error(e, "page_token"))?;
        Ok(Response::new(v1::ListJobsResponse {
            jobs: jobs.iter().map(job_pb).collect(),
            next_page_token: next.unwrap_or_default(),
        }))
    }

    async fn cancel_job(
        &self,
        request: Request<v1::CancelJobRequest>,
    ) -> Result<Response<v1::Job>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        let status = self
            .jobs
            .cancel(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(job_pb(&status)))
    }

    async fn delete_job(
        &self,
        request: Request<v1::DeleteJobRequest>,
    ) -> Result<Response<()>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        self.jobs
            .delete(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(()))
    }

    type StreamFramesStream = BoxStream<v1::StreamFramesResponse>;

    async fn stream_frames(
        &self,
        request: Request<v1::StreamFramesRequest>,
    ) -> Result<Response<Self::StreamFramesStream>, Status> {
        use v1::stream_frames_response::Event;
        let caller = caller(&request)?;
        let request = request.into_inner();
        let id = parse_name("name", "jobs/", &request.name)?;
        // No job has more steps than the server's limit, so a `from_step` beyond it could only
        // wait for the terminal message without a frame: it is a client bug, most often a
        // negative number (a client's int32 -1 arrives in this uint32 field as 4294967295).
        let max_steps = self.jobs.config().limits.max_steps;
        if request.from_step as usize > max_steps.saturating_add(1) {
            let shown = if request.from_step > i32::MAX as u32 {
                format!("{} (a negative number?)", request.from_step as i32)
            } else {
                request.from_step.to_string()
            };
            return Err(bad_request(
                "from_step",
                format!(
                    "must be between 0 and {} (the server's step limit + 1), got {shown}",
                    max_steps.saturating_add(1)
                ),
            ));
        }
        let events = self
            .jobs
            .watch(&caller, &id, request.from_step as usize)
            .await
            .map_err(|e| job_error(e, "name"))?;
        // End the stream right after `Done`, whatever the core does afterwards: the proto
        // promises the terminal job message is the last one.
        let responses = events
            .scan(false, |finished, event| {
                let item = if *finished {
                    None
                } else {
                    let event = match event {
                        JobEvent::State(s) => Event::Job(job_pb(&s)),
                        JobEvent::Frame(f) => Event::Frame(frame_pb(&f)),
                        JobEvent::Done(s) => {
                            *finished = true;
                            Event::Job(job_pb(&s))
                        }
                    };
                    Some(Ok(v1::StreamFramesResponse { event: Some(event) }))
                };
                futures::future::ready(item)
            })
            .boxed();
        Ok(Response::new(responses))
    }

    type DownloadResultStream = BoxStream<v1::DownloadResultChunk>;

    async fn download_result(
        &self,
        request: Request<v1::DownloadResultRequest>,
    ) -> Result<Response<Self::DownloadResultStream>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        let id = parse_name("name", "jobs/", &request.name)?;
        let format = match v1::MeshFormat::try_from(request.format) {
            Ok(v1::MeshFormat::Unspecified) => {
                self.jobs
                    .get(&caller, &id)
                    .await
                    .map_err(|e| job_error(e, "name"))?
                    .input_format
            }
            _ => format_from_pb("format", request.format)?,
        };
        let file = Bytes::from(
            self.jobs
                .result(&caller, &id, format)
                .await
                .map_err(|e| job_error(e, "name"))?,
        );
        // Slices of one `Bytes` share its buffer: chunking copies nothing.
        let chunks: Vec<Result<v1::DownloadResultChunk, Status>> = (0..file.len())
            .step_by(DOWNLOAD_CHUNK_BYTES)
            .enumerate()
            .map(|(i, start)| {
                let end = (start + DOWNLOAD_CHUNK_BYTES).min(file.len());
                Ok(v1::DownloadResultChunk {
                    format: if i == 0 { format_pb(format) as i32 } else { 0 },
                    data: file.slice(start..end),
                })
            })
            .collect();
        Ok(Response::new(futures::stream::iter(chunks).boxed()))
    }

    async fn fair_curve(
        &self,
        request: Request<v1::FairCurveRequest>,
    ) -> Result<Response<v1::FairCurveResponse>, Status> {
        // Answer a little before the client's own deadline, so it hears why.
        let client_deadline =
            grpc_timeout(&request).map(|d| d.saturating_sub(WAIT_DEADLINE_MARGIN));
        let request = request.into_inner();
        let curve = request
            .curve
            .ok_or_else(|| bad_request("curve", "required: the points to fair"))?;
        if curve.xy.len() % 2 != 0 {
            return Err(bad_request(
                "curve.xy",
                format!(
                    "must hold x, y pairs (an even count of numbers), got {}",
                    curve.xy.len()
                ),
            ));
        }
        let count = curve.xy.len() / 2;
        let limit = self.jobs.config().limits.max_curve_points;
        if count > limit {
            return Err(curve_error(JobError::TooLarge {
                what: "curve points",
                limit: limit as u64,
            }));
        }
        let mut points = Vec::new();
        points
            .try_reserve_exact(count)
            .map_err(|_| Status::resource_exhausted("not enough memory for the curve"))?;
        points.extend(curve.xy.chunks_exact(2).map(|c| [c[0], c[1]]));

        let mut spec = CurveSpec::default();
        if let Some(steps) = request.steps {
            spec.steps = steps as usize;
        }
        if let Some(tau) = request.tau {
            spec.tau = tau;
        }
        if request.frame_interval > 0 {
            spec.frame_interval = Some(request.frame_interval as usize);
        }
        if let Some(deadline) = request.deadline {
            let d = duration_from_pb("deadline", &deadline)?;
            if d.is_zero() {
                return Err(bad_request("deadline", "must be > 0 when set"));
            }
            spec.deadline_secs = Some(d.as_secs_f64());
        }
        let input = CurveInput::Points {
            points,
            closed: curve.closed,
        };
        let outcome = self
            .jobs
            .fair_curve(input, spec, client_deadline)
            .await
            .map_err(curve_error)?;
        Ok(Response::new(curve_response_pb(&outcome)))
    }
}

#[tonic::async_trait]
impl lro::operations_server::Operations for GrpcApi {
    async fn list_operations(
        &self,
        request: Request<lro::ListOperationsRequest>,
    ) -> Result<Response<lro::ListOperationsResponse>, Status> {
        let caller = caller(&request)?;
        let request = request.into_inner();
        // The collection's name: "jobs" (ours), "operations" (what generic LRO clients send)
        // or empty. Anything else names a collection this server does not have.
        if !matches!(request.name.as_str(), "" | "jobs" | "operations") {
            return Err(bad_request(
                "name",
                format!("must be `jobs` (or empty), got `{}`", clip(&request.name)),
            ));
        }
        let state = parse_operation_filter(&request.filter)?;
        let page_size = page_size(request.page_size)?;
        let token = Some(request.page_token).filter(|t| !t.is_empty());
        let (jobs, next) = self
            .jobs
            .list(&caller, state, page_size, token)
            .await
            .map_err(|e| job_error(e, "page_token"))?;
        Ok(Response::new(lro::ListOperationsResponse {
            operations: jobs.iter().map(operation).collect(),
            next_page_token: next.unwrap_or_default(),
            ..Default::default()
        }))
    }

    async fn get_operation(
        &self,
        request: Request<lro::GetOperationRequest>,
    ) -> Result<Response<lro::Operation>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        let status = self
            .jobs
            .get(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(operation(&status)))
    }

    async fn delete_operation(
        &self,
        request: Request<lro::DeleteOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        self.jobs
            .delete(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(()))
    }

    async fn cancel_operation(
        &self,
        request: Request<lro::CancelOperationRequest>,
    ) -> Result<Response<()>, Status> {
        let caller = caller(&request)?;
        let id = parse_name("name", "jobs/", &request.get_ref().name)?;
        self.jobs
            .cancel(&caller, &id)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(()))
    }

    async fn wait_operation(
        &self,
        request: Request<lro::WaitOperationRequest>,
    ) -> Result<Response<lro::Operation>, Status> {
        let client_deadline = grpc_timeout(&request);
        let caller = caller(&request)?;
        let request = request.into_inner();
        let id = parse_name("name", "jobs/", &request.name)?;
        let asked = match request.timeout {
            Some(t) => Some(duration_from_pb("timeout", &t)?),
            None => None,
        };
        // AIP-151: the shorter of the request's timeout and the RPC deadline, capped by the
        // server.
        let wait = [
            asked,
            client_deadline.map(|d| d.saturating_sub(WAIT_DEADLINE_MARGIN)),
            Some(MAX_WAIT),
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(MAX_WAIT);
        let status = self
            .jobs
            .wait(&caller, &id, wait)
            .await
            .map_err(|e| job_error(e, "name"))?;
        Ok(Response::new(operation(&status)))
    }
}

/// `grpc.health.v1.Health` answering from [`Jobs::is_ready`] on every call, so draining or a
/// stalled worker shows without anyone having to flip a flag.
struct HealthService {
    jobs: Jobs,
}

impl HealthService {
    /// The status of `service` ("" = the whole server), or `None` for a service we don't serve.
    fn status(
        &self,
        service: &str,
    ) -> Option<tonic_health::pb::health_check_response::ServingStatus> {
        use tonic_health::pb::health_check_response::ServingStatus;
        if !service.is_empty() && !SERVICE_NAMES.contains(&service) {
            return None;
        }
        Some(if self.jobs.is_ready() {
            ServingStatus::Serving
        } else {
            ServingStatus::NotServing
        })
    }
}

#[tonic::async_trait]
impl tonic_health::pb::health_server::Health for HealthService {
    async fn check(
        &self,
        request: Request<tonic_health::pb::HealthCheckRequest>,
    ) -> Result<Response<tonic_health::pb::HealthCheckResponse>, Status> {
        let service = &request.get_ref().service;
        match self.status(service) {
            Some(status) => Ok(Response::new(tonic_health::pb::HealthCheckResponse {
                status: status as i32,
            })),
            // The health protocol says: NOT_FOUND for a service the server does not know.
            None => Err(Status::not_found(format!(
                "unknown service `{}`",
                clip(service)
            ))),
        }
    }

    type WatchStream = BoxStream<tonic_health::pb::HealthCheckResponse>;

    async fn watch(
        &self,
        request: Request<tonic_health::pb::HealthCheckRequest>,
    ) -> Result<Response<Self::WatchStream>, Status> {
        use tonic_health::pb::health_check_response::ServingStatus;
        let service = request.into_inner().service;
        let jobs = self.jobs.clone();
        // Poll readiness and send only changes (the first reading always goes out), as the
        // protocol asks. An unknown service reports SERVICE_UNKNOWN rather than an error.
        let stream = futures::stream::unfold((None::<i32>, true), move |(last, first)| {
            let service = service.clone();
            let health = HealthService { jobs: jobs.clone() };
            async move {
                let mut first = first;
                loop {
                    if !first {
                        tokio::time::sleep(HEALTH_WATCH_PERIOD).await;
                    }
                    first = false;
                    let now = health
                        .status(&service)
                        .unwrap_or(ServingStatus::ServiceUnknown)
                        as i32;
                    if last != Some(now) {
                        let reply = tonic_health::pb::HealthCheckResponse { status: now };
                        return Some((Ok(reply), (Some(now), false)));
                    }
                }
            }
        });
        Ok(Response::new(stream.boxed()))
    }
}

// ---------------------------------------------------------------------------------------------
// Errors: the one place a JobError becomes a tonic::Status.

/// INVALID_ARGUMENT with a `google.rpc.BadRequest` naming `field` (a path in the request, as
/// AIP-193 asks: `params.tau`, `inline_mesh.data`, …).
/// The caller the authentication layer put on the request (HTTP extensions reach tonic's
/// request). None means the layer did not run for this route: refused, never served as anyone.
fn caller<T>(request: &Request<T>) -> Result<Caller, Status> {
    request
        .extensions()
        .get::<Caller>()
        .cloned()
        .ok_or_else(|| Status::unauthenticated("this call needs credentials and none were checked"))
}

fn bad_request(field: &str, description: impl Into<String>) -> Status {
    let description = cap_detail(description.into());
    Status::with_error_details(
        Code::InvalidArgument,
        cap_detail(format!("invalid `{field}`: {description}")),
        ErrorDetails::with_bad_request_violation(field, description),
    )
}

/// The request field a job-core parameter name corresponds to. The core names nested fields
/// by their JSON path (`filter.k`, `boundary.prescribed.axis.fixed`), which the proto mirrors
/// under `params`.
fn spec_field(core_field: &str) -> String {
    match core_field {
        "deadline_secs" => "params.deadline".into(),
        "idempotency_key" => "request_id".into(),
        "boundary.prescribed.angles.per_loop" => {
            "params.boundary.prescribed.angles.per_loop.values".into()
        }
        "method" | "steps" | "tau" | "iterations" | "frame_interval" | "include_positions"
        | "exactness" | "mobius_balancing" | "filter" | "boundary" | "safeguard" => {
            format!("params.{core_field}")
        }
        nested if nested.starts_with("filter.") || nested.starts_with("boundary.") => {
            format!("params.{nested}")
        }
        other => other.into(),
    }
}

/// Map a job-core error to its status. `mesh_field` is the request field that carried the mesh
/// (or the job name), so field violations point at what the client sent.
fn job_error(err: JobError, mesh_field: &str) -> Status {
    // The core's messages may echo user input (a parameter value, a parser's complaint about
    // the mesh): capped so the status stays small enough to travel in a header.
    let message = cap_detail(err.to_string());
    let mut details = ErrorDetails::new();
    let code = match &err {
        JobError::NotFound(id) => {
            details.set_resource_info(
                "willow.v1.Job",
                format!("jobs/{}", clip(id)),
                "",
                "no such job",
            );
            Code::NotFound
        }
        JobError::Gone(id) => {
            details.set_resource_info(
                "willow.v1.Job",
                format!("jobs/{}", clip(id)),
                "",
                "the job expired and its results were deleted",
            );
            details.set_error_info("EXPIRED", ERROR_DOMAIN, HashMap::new());
            Code::NotFound
        }
        JobError::UploadNotFound(id) => {
            details.set_resource_info(
                "willow.v1.Upload",
                format!("uploads/{}", clip(id)),
                "",
                "no such upload (uploads expire like jobs)",
            );
            Code::NotFound
        }
        JobError::FrameNotFound { id, step, detail } => {
            details.set_resource_info(
                "willow.v1.Frame",
                format!("jobs/{}/frames/{step}", clip(id)),
                "",
                detail.clone(),
            );
            Code::NotFound
        }
        JobError::QueueFull {
            retry_after_secs,
            capacity,
        } => {
            details.set_retry_info(Some(Duration::from_secs(*retry_after_secs)));
            details.set_error_info(
                "QUEUE_FULL",
                ERROR_DOMAIN,
                HashMap::from([("capacity".to_string(), capacity.to_string())]),
            );
            Code::ResourceExhausted
        }
        JobError::QuotaExceeded {
            quota,
            limit,
            used,
            retry_after_secs,
        } => {
            details.set_retry_info(Some(Duration::from_secs(*retry_after_secs)));
            details.add_quota_failure_violation(
                format!("tenant_quota:{quota}"),
                format!("tenant quota `{quota}` of {limit} is spent"),
            );
            let mut meta = HashMap::from([
                ("quota".to_string(), quota.to_string()),
                ("limit".to_string(), limit.to_string()),
            ]);
            if let Some(used) = used {
                meta.insert("used".to_string(), used.to_string());
            }
            details.set_error_info("QUOTA_EXCEEDED", ERROR_DOMAIN, meta);
            Code::ResourceExhausted
        }
        JobError::InvalidMesh(mesh) => {
            details.add_bad_request_violation(mesh_field, cap_detail(mesh.to_string()));
            details.set_error_info(
                mesh.code().to_ascii_uppercase(),
                ERROR_DOMAIN,
                HashMap::new(),
            );
            Code::InvalidArgument
        }
        JobError::InvalidSpec { field, reason } => {
            details.add_bad_request_violation(spec_field(field), cap_detail(reason.clone()));
            Code::InvalidArgument
        }
        // A step count over the limit is a parameter out of range, not a resource.
        JobError::TooLarge {
            what: "steps",
            limit,
        } => {
            details.add_bad_request_violation(
                "params.steps",
                format!("must be at most {limit} (the server's limit)"),
            );
            Code::InvalidArgument
        }
        // A mesh over a size limit: RESOURCE_EXHAUSTED as gRPC itself answers an oversized
        // message, with the limit named and no RetryInfo (retrying cannot help).
        JobError::TooLarge { what, limit } => {
            details
                .add_quota_failure_violation(*what, format!("{what} exceeds the limit of {limit}"));
            details.add_bad_request_violation(
                mesh_field,
                format!("{what} exceeds the limit of {limit}"),
            );
            Code::ResourceExhausted
        }
        JobError::Conflict(reason) => {
            details.add_precondition_failure_violation("STATE", mesh_field, reason.clone());
            Code::FailedPrecondition
        }
        JobError::IdempotencyMismatch(_) => {
            details.add_bad_request_violation(
                "request_id",
                "already used for a different request; use a new request_id",
            );
            details.set_error_info("REQUEST_ID_REUSED", ERROR_DOMAIN, HashMap::new());
            Code::AlreadyExists
        }
        JobError::ShuttingDown => {
            // Another replica (or this one, restarted) can take the job.
            details.set_retry_info(Some(Duration::from_secs(1)));
            Code::Unavailable
        }
        JobError::InvalidCurve(curve) => {
            details.add_bad_request_violation(mesh_field, cap_detail(curve.to_string()));
            details.set_error_info(
                crate::jobs::curve::curve_error_code(curve).to_ascii_uppercase(),
                ERROR_DOMAIN,
                HashMap::new(),
            );
            Code::InvalidArgument
        }
        JobError::Busy {
            retry_after_secs,
            slots,
        } => {
            details.set_retry_info(Some(Duration::from_secs(*retry_after_secs)));
            details.set_error_info(
                "BUSY",
                ERROR_DOMAIN,
                HashMap::from([("slots".to_string(), slots.to_string())]),
            );
            Code::ResourceExhausted
        }
        JobError::DeadlineExceeded { .. } => Code::DeadlineExceeded,
        JobError::Numerical { .. } => {
            // As a job's numerical failure: not the client's fault, not retryable (job_failure).
            details.set_error_info("NUMERICAL", ERROR_DOMAIN, HashMap::new());
            Code::Unknown
        }
        JobError::Unavailable(detail) => {
            tracing::warn!(error = %detail, "backend unavailable in a gRPC call");
            details.set_retry_info(Some(Duration::from_secs(2)));
            Code::Unavailable
        }
        JobError::Internal(detail) => {
            // The detail may name files and SQL: log it, don't send it.
            tracing::error!(error = %detail, "internal error in a gRPC call");
            return Status::internal("internal error");
        }
    };
    Status::with_error_details(code, message, details)
}

/// Map a [`Jobs::fair_curve`] error: its parameters are top-level fields of
/// `FairCurveRequest` (not `params.*` as for jobs), and the curve is `curve.xy`.
fn curve_error(err: JobError) -> Status {
    match err {
        JobError::InvalidSpec { field, reason } => {
            let field = match field {
                "deadline_secs" => "deadline",
                "curve" => "curve.xy",
                other => other,
            };
            bad_request(field, reason)
        }
        // A step count over the limit is a parameter out of range, as for jobs.
        JobError::TooLarge {
            what: "steps",
            limit,
        } => bad_request(
            "steps",
            format!("must be at most {limit} (the server's limit for curves)"),
        ),
        other => job_error(other, "curve.xy"),
    }
}

// ---------------------------------------------------------------------------------------------
// Requests → core types.

/// The id in `{prefix}{id}` (`jobs/…`, `uploads/…`), or INVALID_ARGUMENT naming `field`.
fn parse_name(field: &str, prefix: &str, name: &str) -> Result<String, Status> {
    match name.strip_prefix(prefix) {
        Some(id) if !id.is_empty() && !id.contains('/') => Ok(id.to_string()),
        _ => Err(bad_request(
            field,
            format!("must be `{prefix}{{id}}`, got `{}`", clip(name)),
        )),
    }
}

/// At most [`MAX_ECHO_CHARS`] characters of user input, for error messages.
fn clip(s: &str) -> String {
    if s.chars().count() <= MAX_ECHO_CHARS {
        s.to_string()
    } else {
        let mut out: String = s.chars().take(MAX_ECHO_CHARS).collect();
        out.push('…');
        out
    }
}

fn page_size(raw: i32) -> Result<usize, Status> {
    usize::try_from(raw).map_err(|_| bad_request("page_size", format!("must be >= 0, got {raw}")))
}

fn format_from_pb(field: &str, raw: i32) -> Result<Format, Status> {
    match v1::MeshFormat::try_from(raw) {
        Ok(v1::MeshFormat::Obj) => Ok(Format::Obj),
        Ok(v1::MeshFormat::Gltf) => Ok(Format::Gltf),
        Ok(v1::MeshFormat::Glb) => Ok(Format::Glb),
        Ok(v1::MeshFormat::Unspecified) => Err(bad_request(
            field,
            "required: MESH_FORMAT_OBJ, MESH_FORMAT_GLTF or MESH_FORMAT_GLB",
        )),
        Err(_) => Err(bad_request(field, format!("unknown mesh format {raw}"))),
    }
}

fn format_pb(format: Format) -> v1::MeshFormat {
    match format {
        Format::Obj => v1::MeshFormat::Obj,
        Format::Gltf => v1::MeshFormat::Gltf,
        Format::Glb => v1::MeshFormat::Glb,
    }
}

/// `METHOD_CONFORMAL` ↔ [`Method::Conformal`] by name: the proto value is `METHOD_` + the
/// method's serde name upper-cased. Matching by name (not an exhaustive `match`) means a flow
/// added to the library is refused cleanly until its proto value is added, and adding the
/// value is all it takes to expose it; no Rust change here.
fn method_from_pb(raw: i32) -> Result<Method, Status> {
    let value = match v1::Method::try_from(raw) {
        Ok(v1::Method::Unspecified) => return Ok(JobSpec::default().method),
        Ok(value) => value,
        Err(_) => {
            return Err(bad_request(
                "params.method",
                format!("unknown method {raw}"),
            ))
        }
    };
    Method::parse(value.as_str_name().trim_start_matches("METHOD_")).map_err(|_| {
        bad_request(
            "params.method",
            format!("{} is not supported by this server", value.as_str_name()),
        )
    })
}

/// The inverse of [`method_from_pb`]; a method without a proto value yet reports
/// `METHOD_UNSPECIFIED`.
fn method_pb(method: Method) -> v1::Method {
    v1::Method::from_str_name(&format!("METHOD_{}", method.name().to_ascii_uppercase()))
        .unwrap_or(v1::Method::Unspecified)
}

fn duration_from_pb(field: &str, d: &prost_types::Duration) -> Result<Duration, Status> {
    // prost-types checks sign consistency and nanos range for us.
    Duration::try_from(*d).map_err(|_| {
        bad_request(
            field,
            format!(
                "must be a non-negative duration, got {}s {}ns",
                d.seconds, d.nanos
            ),
        )
    })
}

/// Wire parameters → [`JobSpec`], unset fields taking the defaults. Range checks are the core's
/// ([`JobSpec::validate`], run by `submit`), so HTTP and gRPC refuse the same values.
fn spec_from_pb(params: Option<v1::JobParams>) -> Result<JobSpec, Status> {
    let mut spec = JobSpec::default();
    let Some(p) = params else {
        return Ok(spec);
    };
    spec.method = method_from_pb(p.method)?;
    if let Some(steps) = p.steps {
        spec.steps = steps as usize;
    }
    if let Some(tau) = p.tau {
        spec.tau = tau;
    }
    if let Some(iterations) = p.iterations {
        spec.iterations = iterations as usize;
    }
    if let Some(interval) = p.frame_interval {
        spec.frame_interval = interval as usize;
    }
    if let Some(include) = p.include_positions {
        spec.include_positions = include;
    }
    if let Some(deadline) = p.deadline {
        let d = duration_from_pb("params.deadline", &deadline)?;
        if d.is_zero() {
            return Err(bad_request("params.deadline", "must be > 0 when set"));
        }
        spec.deadline_secs = Some(d.as_secs_f64());
    }
    if let Some(exactness) = p.exactness {
        spec.exactness = exactness;
    }
    if let Some(mobius) = p.mobius_balancing {
        spec.mobius_balancing = mobius;
    }
    spec.filter = p.filter.map(|f| FilterSpec {
        sigma: f.sigma,
        k: f.k,
    });
    if let Some(boundary) = p.boundary {
        spec.boundary = boundary_from_pb(boundary);
    }
    if let Some(safeguard) = p.safeguard {
        spec.safeguard = safeguard;
    }
    Ok(spec)
}

/// Wire boundary → [`BoundarySpec`]. Unset oneofs take the defaults the proto documents
/// (free; tangent axis; uniform 0); the numbers are checked by [`JobSpec::validate`].
fn boundary_from_pb(boundary: v1::Boundary) -> BoundarySpec {
    use v1::boundary::Condition;
    match boundary.condition {
        None | Some(Condition::Free(())) => BoundarySpec::Free,
        Some(Condition::Fixed(())) => BoundarySpec::Fixed,
        Some(Condition::Cmc(())) => BoundarySpec::Cmc,
        Some(Condition::Prescribed(p)) => BoundarySpec::Prescribed(PrescribedSpec {
            frame_angle: p.frame_angle,
            axis: match p.axis.and_then(|a| a.axis) {
                None | Some(v1::rotation_axis::Axis::Tangent(())) => AxisSpec::Tangent,
                Some(v1::rotation_axis::Axis::Fixed(v)) => AxisSpec::Fixed([v.x, v.y, v.z]),
            },
            angles: match p.angles.and_then(|a| a.angles) {
                None => AnglesSpec::default(),
                Some(v1::boundary_angles::Angles::Uniform(a)) => AnglesSpec::Uniform(a),
                Some(v1::boundary_angles::Angles::PerLoop(list)) => {
                    AnglesSpec::PerLoop(list.values)
                }
            },
        }),
    }
}

/// [`BoundarySpec`] → wire, every oneof set (GetJob reports the effective condition).
fn boundary_pb(boundary: &BoundarySpec) -> v1::Boundary {
    use v1::boundary::Condition;
    let condition = match boundary {
        BoundarySpec::Free => Condition::Free(()),
        BoundarySpec::Fixed => Condition::Fixed(()),
        BoundarySpec::Cmc => Condition::Cmc(()),
        BoundarySpec::Prescribed(p) => Condition::Prescribed(v1::PrescribedVectors {
            frame_angle: p.frame_angle,
            axis: Some(v1::RotationAxis {
                axis: Some(match p.axis {
                    AxisSpec::Tangent => v1::rotation_axis::Axis::Tangent(()),
                    AxisSpec::Fixed([x, y, z]) => {
                        v1::rotation_axis::Axis::Fixed(v1::Vector3 { x, y, z })
                    }
                }),
            }),
            angles: Some(v1::BoundaryAngles {
                angles: Some(match &p.angles {
                    AnglesSpec::Uniform(a) => v1::boundary_angles::Angles::Uniform(*a),
                    AnglesSpec::PerLoop(values) => {
                        v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                            values: values.clone(),
                        })
                    }
                }),
            }),
        }),
    };
    v1::Boundary {
        condition: Some(condition),
    }
}

/// AIP-155: `request_id` is optional and, when set, a UUID (any version, any case).
fn request_id(raw: &str) -> Result<Option<String>, Status> {
    if raw.is_empty() {
        return Ok(None);
    }
    let bytes = raw.as_bytes();
    let is_uuid = bytes.len() == 36
        && bytes.iter().enumerate().all(|(i, b)| match i {
            8 | 13 | 18 | 23 => *b == b'-',
            _ => b.is_ascii_hexdigit(),
        });
    if !is_uuid {
        return Err(bad_request(
            "request_id",
            format!("must be a UUID (AIP-155), got `{}`", clip(raw)),
        ));
    }
    // Case-insensitive: the same UUID in upper case is the same request.
    Ok(Some(raw.to_ascii_lowercase()))
}

fn state_from_pb(state: v1::job::State) -> JobState {
    match state {
        v1::job::State::Unspecified | v1::job::State::Queued => JobState::Queued,
        v1::job::State::Running => JobState::Running,
        v1::job::State::Succeeded => JobState::Succeeded,
        v1::job::State::Failed => JobState::Failed,
        v1::job::State::Cancelled => JobState::Cancelled,
    }
}

/// `ListOperations.filter`: empty, `done=true|false` is not offered (a state says more), so we
/// accept `state=QUEUED|RUNNING|SUCCEEDED|FAILED|CANCELLED` (case-insensitive, spaces allowed).
fn parse_operation_filter(filter: &str) -> Result<Option<JobState>, Status> {
    let filter = filter.trim();
    if filter.is_empty() {
        return Ok(None);
    }
    let value = filter
        .split_once('=')
        .filter(|(key, _)| key.trim().eq_ignore_ascii_case("state"))
        .map(|(_, value)| value.trim().trim_matches('"').to_ascii_uppercase());
    match value.as_deref().and_then(v1::job::State::from_str_name) {
        Some(v1::job::State::Unspecified) | None => Err(bad_request(
            "filter",
            format!(
                "supported: `state=QUEUED|RUNNING|SUCCEEDED|FAILED|CANCELLED`, got `{}`",
                clip(filter)
            ),
        )),
        Some(state) => Ok(Some(state_from_pb(state))),
    }
}

/// The client's deadline from the `grpc-timeout` header (`<digits><unit>`, gRPC over HTTP/2
/// spec). tonic's own server reads it, but behind `axum::serve` nobody does, so we parse it.
fn grpc_timeout<T>(request: &Request<T>) -> Option<Duration> {
    let value = request.metadata().get("grpc-timeout")?.to_str().ok()?;
    let split = value.len().checked_sub(1)?;
    let (digits, unit) = value.split_at(split);
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

// ---------------------------------------------------------------------------------------------
// Core types → responses.

fn timestamp(ms: u64) -> prost_types::Timestamp {
    prost_types::Timestamp {
        seconds: (ms / 1000) as i64,
        // < 1e9 by construction.
        nanos: ((ms % 1000) * 1_000_000) as i32,
    }
}

/// Saturating `usize` → `u32` for counts on the wire (steps are limited far below u32::MAX).
fn count(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

fn state_pb(state: JobState) -> v1::job::State {
    match state {
        JobState::Queued => v1::job::State::Queued,
        JobState::Running => v1::job::State::Running,
        JobState::Succeeded => v1::job::State::Succeeded,
        JobState::Failed => v1::job::State::Failed,
        JobState::Cancelled => v1::job::State::Cancelled,
    }
}

fn params_pb(spec: &JobSpec) -> v1::JobParams {
    v1::JobParams {
        method: method_pb(spec.method) as i32,
        steps: Some(count(spec.steps)),
        tau: Some(spec.tau),
        iterations: Some(count(spec.iterations)),
        frame_interval: Some(count(spec.frame_interval)),
        include_positions: Some(spec.include_positions),
        deadline: spec
            .deadline_secs
            .and_then(|s| Duration::try_from_secs_f64(s).ok())
            .and_then(|d| prost_types::Duration::try_from(d).ok()),
        exactness: Some(spec.exactness),
        mobius_balancing: Some(spec.mobius_balancing),
        filter: spec.filter.map(|f| v1::SpectralFilter {
            sigma: f.sigma,
            k: f.k,
        }),
        boundary: Some(boundary_pb(&spec.boundary)),
        safeguard: Some(spec.safeguard),
    }
}

fn curve_pb(points: &[[f64; 2]], closed: bool) -> v1::Curve {
    v1::Curve {
        xy: points.iter().flat_map(|p| [p[0], p[1]]).collect(),
        closed,
    }
}

fn curve_response_pb(outcome: &CurveOutcome) -> v1::FairCurveResponse {
    let closed = outcome.curve.closed;
    v1::FairCurveResponse {
        curve: Some(curve_pb(&outcome.curve.points, closed)),
        metrics: outcome
            .metrics
            .iter()
            .map(|m| v1::CurveStepMetrics {
                step: count(m.step),
                energy: m.energy,
                curvature_std_over_mean: m.curvature_std_over_mean,
                max_edge_length_distortion: m.max_edge_length_distortion,
                closure_gap: m.closure_gap,
                poisson_residual: m.poisson_residual,
                total_length: m.total_length,
                total_curvature: m.total_curvature,
                step_ms: m.step_ms,
            })
            .collect(),
        frames: outcome
            .frames
            .iter()
            .map(|f| v1::CurveFrame {
                step: count(f.step),
                curve: Some(curve_pb(&f.points, closed)),
            })
            .collect(),
        steps: count(outcome.spec.steps),
        tau: outcome.spec.tau,
        frame_interval: outcome.spec.frame_interval.map_or(0, count),
        deadline: outcome
            .spec
            .deadline_secs
            .and_then(|s| Duration::try_from_secs_f64(s).ok())
            .and_then(|d| prost_types::Duration::try_from(d).ok()),
    }
}

fn metrics_pb(m: &StepMetrics) -> v1::StepMetrics {
    v1::StepMetrics {
        step: count(m.step),
        willmore_energy: m.willmore_energy,
        q_mean: m.q_mean,
        q_area_mean: m.q_area_mean,
        q_p95: m.q_p95,
        q_max: m.q_max,
        closure_residual: m.closure_residual,
        eigen_residual: m.eigen_residual,
        area: m.area,
        step_ms: m.step_ms,
        tau: m.tau,
        rejected: m.rejected,
    }
}

/// Positions as the proto documents them: packed little-endian f32 x, y, z per vertex.
fn positions_bytes(positions: &[[f32; 3]]) -> Bytes {
    let mut out = Vec::with_capacity(positions.len() * 12);
    for p in positions {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    Bytes::from(out)
}

fn frame_pb(frame: &Frame) -> v1::Frame {
    v1::Frame {
        step: count(frame.step),
        metrics: Some(metrics_pb(&frame.metrics)),
        positions: frame.positions.as_deref().map(|p| positions_bytes(p)),
    }
}

/// Why a job failed or was cancelled, as a `google.rpc.Status` (Job.error, Operation.error).
/// The core's machine-readable `error_code` picks the canonical code and rides along as
/// `ErrorInfo.reason`.
fn job_failure(status: &JobStatus) -> Option<tonic_types::pb::Status> {
    if !matches!(status.state, JobState::Failed | JobState::Cancelled) {
        return None;
    }
    let reason = status.error_code.as_deref().unwrap_or(match status.state {
        JobState::Cancelled => "cancelled",
        _ => "unknown",
    });
    let code = match (status.state, reason) {
        // google.longrunning: a cancelled operation's error has code CANCELLED.
        (JobState::Cancelled, _) | (_, "cancelled") => Code::Cancelled,
        (_, "deadline_exceeded") => Code::DeadlineExceeded,
        (_, "invalid_mesh" | "invalid_parameter") => Code::InvalidArgument,
        (_, "unsupported") => Code::Unimplemented,
        (_, "internal") => Code::Internal,
        // A numerical breakdown of the flow on this mesh: not the client's fault, not a server
        // bug, not retryable. UNKNOWN plus the reason says exactly that.
        _ => Code::Unknown,
    };
    let info = tonic_types::pb::ErrorInfo {
        reason: reason.to_ascii_uppercase(),
        domain: ERROR_DOMAIN.to_string(),
        metadata: HashMap::new(),
    };
    Some(tonic_types::pb::Status {
        code: code as i32,
        message: status.error.clone().unwrap_or_default(),
        details: vec![prost_types::Any {
            type_url: ERROR_INFO_TYPE_URL.to_string(),
            value: info.encode_to_vec(),
        }],
    })
}

/// Why a succeeded job stopped before its last step (Job.stopped_early): the core's note
/// (code `no_progress`) as a `google.rpc.Status` with code OK and the code as
/// `ErrorInfo.reason`.
fn job_stopped_early(status: &JobStatus) -> Option<tonic_types::pb::Status> {
    if status.state != JobState::Succeeded {
        return None;
    }
    let reason = status.error_code.as_deref()?;
    let info = tonic_types::pb::ErrorInfo {
        reason: reason.to_ascii_uppercase(),
        domain: ERROR_DOMAIN.to_string(),
        metadata: HashMap::new(),
    };
    Some(tonic_types::pb::Status {
        code: Code::Ok as i32,
        message: status.error.clone().unwrap_or_default(),
        details: vec![prost_types::Any {
            type_url: ERROR_INFO_TYPE_URL.to_string(),
            value: info.encode_to_vec(),
        }],
    })
}

fn job_pb(status: &JobStatus) -> v1::Job {
    v1::Job {
        name: format!("jobs/{}", status.id),
        state: state_pb(status.state) as i32,
        step: count(status.step),
        total_steps: count(status.total_steps),
        params: Some(params_pb(&status.spec)),
        input_format: format_pb(status.input_format) as i32,
        latest: status.latest.as_ref().map(metrics_pb),
        error: job_failure(status),
        create_time: Some(timestamp(status.created_at)),
        start_time: status.started_at.map(timestamp),
        end_time: status.finished_at.map(timestamp),
        expire_time: status.expires_at.map(timestamp),
        vertex_count: status.vertex_count as u64,
        face_count: status.face_count as u64,
        stopped_early: job_stopped_early(status),
    }
}

/// The job as a `google.longrunning.Operation`: metadata is always the Job; when done, the
/// result is the Job (SUCCEEDED) or its error (FAILED, CANCELLED).
fn operation(status: &JobStatus) -> lro::Operation {
    let job = job_pb(status);
    let packed = prost_types::Any {
        type_url: JOB_TYPE_URL.to_string(),
        value: job.encode_to_vec(),
    };
    let result = match status.state {
        JobState::Succeeded => Some(lro::operation::Result::Response(packed.clone())),
        JobState::Failed | JobState::Cancelled => job.error.map(lro::operation::Result::Error),
        JobState::Queued | JobState::Running => None,
    };
    lro::Operation {
        name: job.name,
        metadata: Some(packed),
        done: status.state.is_terminal(),
        result,
    }
}

// ---------------------------------------------------------------------------------------------
// UploadMesh: the chunks of the client stream assembled into one file, without the stream, so
// the logic is testable and fuzzable on its own (`fuzzing::upload_mesh`).

/// An `UploadMesh` stream being assembled: the header's format and announced size, the bytes
/// so far, and the server's upload limit.
struct UploadAssembly {
    format: Format,
    announced: u64,
    limit: u64,
    data: Vec<u8>,
}

impl UploadAssembly {
    /// Starts from the stream's first message (`None`: the stream was empty), which must carry
    /// the header.
    fn start(first: Option<v1::UploadMeshChunk>, limit: u64) -> Result<UploadAssembly, Status> {
        use v1::upload_mesh_chunk::Part;
        let header = match first {
            Some(v1::UploadMeshChunk {
                part: Some(Part::Header(h)),
            }) => h,
            Some(_) => {
                return Err(bad_request(
                    "header",
                    "the first message of the stream must carry `header`",
                ))
            }
            None => return Err(bad_request("header", "the upload stream was empty")),
        };
        let format = format_from_pb("header.format", header.format)?;
        if header.size_bytes > limit {
            return Err(job_error(
                JobError::TooLarge {
                    what: "upload bytes",
                    limit,
                },
                "header.size_bytes",
            ));
        }
        // Reserve what the client announced (already checked against the limit), fallibly:
        // a client lying about its size must get an error, not abort the server.
        let mut data: Vec<u8> = Vec::new();
        let announced = usize::try_from(header.size_bytes).unwrap_or(usize::MAX);
        data.try_reserve(announced)
            .map_err(|_| Status::resource_exhausted("not enough memory for the upload"))?;
        Ok(UploadAssembly {
            format,
            announced: header.size_bytes,
            limit,
            data,
        })
    }

    /// Appends one later message of the stream.
    fn push(&mut self, chunk: v1::UploadMeshChunk) -> Result<(), Status> {
        use v1::upload_mesh_chunk::Part;
        match chunk.part {
            Some(Part::Data(bytes)) => {
                if (self.data.len() as u64).saturating_add(bytes.len() as u64) > self.limit {
                    return Err(job_error(
                        JobError::TooLarge {
                            what: "upload bytes",
                            limit: self.limit,
                        },
                        "data",
                    ));
                }
                self.data
                    .try_reserve(bytes.len())
                    .map_err(|_| Status::resource_exhausted("not enough memory for the upload"))?;
                self.data.extend_from_slice(&bytes);
                Ok(())
            }
            Some(Part::Header(_)) => Err(bad_request(
                "header",
                "only the first message of the stream may carry `header`",
            )),
            // An empty message carries nothing; tolerate it like an empty chunk.
            None => Ok(()),
        }
    }

    /// The whole file, once the stream has ended: its size must be the announced one (when
    /// one was announced).
    fn finish(self) -> Result<(Vec<u8>, Format), Status> {
        if self.announced != 0 && self.data.len() as u64 != self.announced {
            return Err(bad_request(
                "header.size_bytes",
                format!(
                    "announced {} bytes but the stream carried {}",
                    self.announced,
                    self.data.len()
                ),
            ));
        }
        Ok((self.data, self.format))
    }
}

/// Entry points for the fuzz targets in `fuzz/` (not an API: hidden from the docs, may change
/// at any time). They run the same code the handlers run, minus the network and the job core.
#[doc(hidden)]
pub mod fuzzing {
    use super::{spec_from_pb, v1, JobSpec, UploadAssembly};
    use crate::api::codec;
    use crate::jobs::Config;
    use tonic::Status;
    use willow::mesh::io::Format;

    /// An `UploadMesh` stream whose messages arrive as the protobuf encodings in `messages`,
    /// decoded as the server's codec decodes them and assembled under an upload limit of
    /// `limit` bytes: the assembled file's size and format, or the status the client gets.
    pub fn upload_mesh(messages: &[&[u8]], limit: u64) -> Result<(usize, Format), Status> {
        let mut decoded = messages.iter().map(|m| decode::<v1::UploadMeshChunk>(m));
        let first = decoded.next().transpose()?;
        let mut upload = UploadAssembly::start(first, limit)?;
        for chunk in decoded {
            upload.push(chunk?)?;
        }
        let (data, format) = upload.finish()?;
        Ok((data.len(), format))
    }

    /// A `CreateJob` request's protobuf encoding, decoded as the server's codec decodes it,
    /// its parameters translated to a [`JobSpec`] and validated as `submit` validates them
    /// (default server configuration).
    pub fn create_job(bytes: &[u8]) -> Result<JobSpec, Status> {
        let request = decode::<v1::CreateJobRequest>(bytes)?;
        super::request_id(&request.request_id)?;
        if let Some(v1::create_job_request::Mesh::InlineMesh(mesh)) = &request.mesh {
            super::format_from_pb("inline_mesh.format", mesh.format)?;
        }
        let spec = spec_from_pb(request.params)?;
        spec.validate(default_config())
            .map_err(|e| super::job_error(e, "inline_mesh.data"))?;
        Ok(spec)
    }

    /// The default server configuration (built once: it asks the OS for the core count).
    pub(crate) fn default_config() -> &'static Config {
        static CONFIG: std::sync::OnceLock<Config> = std::sync::OnceLock::new();
        CONFIG.get_or_init(|| Config::new("willow-data"))
    }

    /// prost's decode, its error mapped as the codec maps it.
    fn decode<M: prost::Message + Default>(bytes: &[u8]) -> Result<M, Status> {
        M::decode(bytes)
            .map_err(|e| codec::malformed(&format!("failed to decode Protobuf message: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn methods_round_trip_through_their_proto_names() {
        for m in [
            Method::Conformal,
            Method::Mcf,
            Method::Cmcf,
            Method::Bilaplacian,
            Method::Taubin,
        ] {
            let wire = method_pb(m);
            assert_ne!(wire, v1::Method::Unspecified, "{m:?} has no proto value");
            assert_eq!(method_from_pb(wire as i32).ok(), Some(m));
        }
        assert_eq!(
            method_from_pb(0).ok(),
            Some(JobSpec::default().method),
            "unspecified takes the default"
        );
        assert_eq!(
            method_from_pb(999).map_err(|s| s.code()).err(),
            Some(Code::InvalidArgument)
        );
    }

    #[test]
    fn names_must_have_their_collection_prefix() {
        assert_eq!(
            parse_name("name", "jobs/", "jobs/abc").ok().as_deref(),
            Some("abc")
        );
        for bad in ["abc", "jobs/", "jobs/a/b", "uploads/abc", ""] {
            let status = parse_name("name", "jobs/", bad).err();
            let status = status.unwrap_or_else(|| panic!("`{bad}` was accepted"));
            assert_eq!(status.code(), Code::InvalidArgument);
            let violations = status
                .get_details_bad_request()
                .map(|b| b.field_violations)
                .unwrap_or_default();
            assert_eq!(violations.len(), 1);
            assert_eq!(violations[0].field, "name");
        }
    }

    #[test]
    fn request_ids_must_be_uuids() {
        assert_eq!(request_id("").ok(), Some(None));
        assert_eq!(
            request_id("3F2504E0-4F89-11D3-9A0C-0305E82C3301").ok(),
            Some(Some("3f2504e0-4f89-11d3-9a0c-0305e82c3301".to_string()))
        );
        for bad in [
            "retry-1",
            "3f2504e0-4f89-11d3-9a0c-0305e82c330",
            "3f2504e0x4f89-11d3-9a0c-0305e82c3301",
        ] {
            assert_eq!(
                request_id(bad).err().map(|s| s.code()),
                Some(Code::InvalidArgument)
            );
        }
    }

    #[test]
    fn grpc_timeout_header_units() {
        let mut r = Request::new(());
        assert_eq!(grpc_timeout(&r), None);
        for (text, want) in [
            ("5S", Duration::from_secs(5)),
            ("250m", Duration::from_millis(250)),
            ("2M", Duration::from_secs(120)),
            ("7u", Duration::from_micros(7)),
        ] {
            r.metadata_mut()
                .insert("grpc-timeout", text.parse().expect("ascii header value"));
            assert_eq!(grpc_timeout(&r), Some(want), "{text}");
        }
        r.metadata_mut()
            .insert("grpc-timeout", "5x".parse().expect("ascii"));
        assert_eq!(grpc_timeout(&r), None);
    }

    #[test]
    fn positions_are_packed_little_endian_xyz() {
        let bytes = positions_bytes(&[[1.0, -2.0, 0.5], [3.0, 4.0, 5.0]]);
        assert_eq!(bytes.len(), 24);
        assert_eq!(&bytes[0..4], &1.0f32.to_le_bytes());
        assert_eq!(&bytes[4..8], &(-2.0f32).to_le_bytes());
        assert_eq!(&bytes[20..24], &5.0f32.to_le_bytes());
    }

    #[test]
    fn operation_filter() {
        assert_eq!(parse_operation_filter("").ok(), Some(None));
        assert_eq!(
            parse_operation_filter(" state = running ").ok(),
            Some(Some(JobState::Running))
        );
        assert!(parse_operation_filter("done=true").is_err());
        assert!(parse_operation_filter("state=STATE_UNSPECIFIED").is_err());
    }

    #[test]
    fn queue_full_carries_retry_info() {
        let status = job_error(
            JobError::QueueFull {
                retry_after_secs: 7,
                capacity: 3,
            },
            "inline_mesh.data",
        );
        assert_eq!(status.code(), Code::ResourceExhausted);
        let retry = status.get_details_retry_info().and_then(|r| r.retry_delay);
        assert_eq!(retry, Some(Duration::from_secs(7)));
    }

    #[test]
    fn spec_fields_map_to_request_paths() {
        let status = job_error(
            JobError::InvalidSpec {
                field: "deadline_secs",
                reason: "too long".into(),
            },
            "upload",
        );
        assert_eq!(status.code(), Code::InvalidArgument);
        let fields: Vec<String> = status
            .get_details_bad_request()
            .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
            .unwrap_or_default();
        assert_eq!(fields, vec!["params.deadline".to_string()]);
        for (core, wire) in [
            ("filter.k", "params.filter.k"),
            ("exactness", "params.exactness"),
            (
                "boundary.prescribed.axis.fixed",
                "params.boundary.prescribed.axis.fixed",
            ),
            (
                "boundary.prescribed.angles.per_loop",
                "params.boundary.prescribed.angles.per_loop.values",
            ),
        ] {
            assert_eq!(spec_field(core), wire);
        }
    }

    #[test]
    fn boundaries_round_trip_through_the_wire() {
        for b in [
            BoundarySpec::Free,
            BoundarySpec::Fixed,
            BoundarySpec::Cmc,
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: -0.4,
                axis: AxisSpec::Fixed([1.0, 0.0, 0.5]),
                angles: AnglesSpec::PerLoop(vec![0.25, -0.5]),
            }),
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: 0.1,
                axis: AxisSpec::Tangent,
                angles: AnglesSpec::Uniform(0.3),
            }),
        ] {
            assert_eq!(boundary_from_pb(boundary_pb(&b)), b);
        }
        // Empty messages take the documented defaults.
        assert_eq!(
            boundary_from_pb(v1::Boundary::default()),
            BoundarySpec::Free
        );
        let bare = v1::Boundary {
            condition: Some(v1::boundary::Condition::Prescribed(
                v1::PrescribedVectors::default(),
            )),
        };
        assert_eq!(
            boundary_from_pb(bare),
            BoundarySpec::Prescribed(PrescribedSpec::default())
        );
    }
}
