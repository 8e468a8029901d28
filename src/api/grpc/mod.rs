//! The gRPC transport: `willow.v1.Fairing`, `google.longrunning.Operations`, `grpc.health.v1`
//! and server reflection, all over the same [`Jobs`] handle the HTTP layer uses.
//!
//! The wire contract is `proto/willow/v1/fairing.proto`; `build.rs` generates [`pb`] from it.
//! This module only translates: wire request → validated [`JobSpec`](crate::jobs::JobSpec) /
//! [`UploadRef`](crate::jobs::UploadRef) → a call on [`Jobs`] → wire response. Every
//! [`JobError`](crate::jobs::JobError) becomes a [`tonic::Status`] in exactly one place,
//! `job_error`, with the google.rpc error details the proto documents.
//!
//! Entry point for the server: [`routes`] returns an axum router serving all of the above on
//! the `/{package}.{Service}/{Method}` paths, to merge into the HTTP router on one port.
//!
//! Health needs no drain hook: every `Check` and `Watch` reads [`Jobs::is_ready`], so
//! [`Jobs::begin_drain`] (or a stalled worker) turns gRPC health `NOT_SERVING` at once, exactly
//! when `/readyz` turns false.
//!
//! This file holds the router, reflection and health; the rest lives beside it:
//! - `fairing`: the `willow.v1.Fairing` service;
//! - `operations`: the `google.longrunning.Operations` service;
//! - `upload`: the assembly of an `UploadMesh` stream;
//! - `convert`: wire requests → the core's types, and the core's types → responses;
//! - `errors`: the error table, `JobError` → `tonic::Status`;
//! - [`fuzzing`]: entry points for the fuzz targets.

use std::pin::Pin;
use std::time::Duration;

use futures::{Stream, StreamExt};
use tonic::{Request, Response, Status};

use crate::jobs::Jobs;
use errors::clip;

mod convert;
mod errors;
mod fairing;
#[doc(hidden)]
pub mod fuzzing;
mod operations;
mod upload;

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

/// Largest message the Fairing service decodes. gRPC's default is 4 MiB; a little more lets a
/// client send 4 MiB upload chunks (plus framing) or a full 4 MiB inline mesh without tripping
/// over the envelope. Larger meshes go through `UploadMesh`, so this never needs to grow.
const MAX_DECODING_MESSAGE_BYTES: usize = (4 << 20) + (64 << 10);

/// Time kept back from the client's own deadline in `WaitOperation`, so the server answers with
/// the operation (not done yet) before the client gives up with DEADLINE_EXCEEDED.
const WAIT_DEADLINE_MARGIN: Duration = Duration::from_millis(100);

/// How often a health `Watch` stream re-reads readiness. Probes poll every few seconds; one
/// second keeps the reported status fresh at negligible cost.
const HEALTH_WATCH_PERIOD: Duration = Duration::from_secs(1);

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
    .layer(axum::middleware::map_response(client_faults))
}

/// tonic's own verdicts on a request's framing, in the codes the proto promises: a message
/// over the size limit is RESOURCE_EXHAUSTED with a QuotaFailure (tonic says OUT_OF_RANGE,
/// with no details), and a frame with an invalid compression flag or cut short is the
/// client's INVALID_ARGUMENT (tonic says INTERNAL, which invites a retry of the same bytes).
/// A compressed flag without `grpc-encoding` stays INTERNAL: the gRPC spec requires it. Only
/// trailers-only answers carry these (the call fails before any response message).
async fn client_faults(mut res: axum::response::Response) -> axum::response::Response {
    use tonic::Code;
    use tonic_types::{ErrorDetails, StatusExt};
    let Some(status) = Status::from_header_map(res.headers()) else {
        return res;
    };
    let message = status.message();
    let fixed = match status.code() {
        Code::OutOfRange if message.starts_with("Error, decoded message length too large") => {
            Status::with_error_details(
                Code::ResourceExhausted,
                format!("the request message is over the server's limit: {message}"),
                ErrorDetails::with_quota_failure_violation(
                    "request message bytes",
                    format!(
                        "a message may hold at most {MAX_DECODING_MESSAGE_BYTES} bytes; send \
                         larger meshes with UploadMesh"
                    ),
                ),
            )
        }
        Code::Internal
            if message
                .starts_with("protocol error: received message with invalid compression flag")
                || message == "Unexpected EOF decoding stream." =>
        {
            Status::with_error_details(
                Code::InvalidArgument,
                format!("the request is not well-framed gRPC: {message}"),
                ErrorDetails::with_bad_request_violation("request", message.to_string()),
            )
        }
        _ => return res,
    };
    let mut fresh = axum::http::HeaderMap::new();
    if fixed.add_header(&mut fresh).is_err() {
        tracing::warn!("could not write a gRPC status fix-up; the original status stands");
        return res;
    }
    let headers = res.headers_mut();
    for name in ["grpc-status", "grpc-message", "grpc-status-details-bin"] {
        headers.remove(name);
    }
    headers.extend(fresh);
    res
}

#[cfg(test)]
mod framing_tests {
    use super::*;
    use tonic::Code;
    use tonic_types::StatusExt;

    async fn fixed(status: Status) -> Status {
        let mut res = axum::response::Response::new(axum::body::Body::empty());
        status.add_header(res.headers_mut()).expect("headers");
        let res = client_faults(res).await;
        Status::from_header_map(res.headers()).expect("a status")
    }

    #[tokio::test]
    async fn framing_faults_get_the_codes_the_proto_promises() {
        let big = fixed(Status::out_of_range(
            "Error, decoded message length too large: found 9000000 bytes, the limit is: 4259840 bytes",
        ))
        .await;
        assert_eq!(big.code(), Code::ResourceExhausted);
        assert!(big.get_details_quota_failure().is_some(), "{big:?}");
        let flag = fixed(Status::internal(
            "protocol error: received message with invalid compression flag: 7 (valid flags are 0 and 1), while sending request",
        ))
        .await;
        assert_eq!(flag.code(), Code::InvalidArgument);
        assert!(flag.get_details_bad_request().is_some());
        let cut = fixed(Status::internal("Unexpected EOF decoding stream.")).await;
        assert_eq!(cut.code(), Code::InvalidArgument);
        // The spec's own INTERNAL and every other status pass as they are.
        let spec = "protocol error: received message with compressed-flag but no grpc-encoding was specified";
        assert_eq!(fixed(Status::internal(spec)).await.code(), Code::Internal);
        let other = fixed(Status::not_found("jobs/x")).await;
        assert_eq!((other.code(), other.message()), (Code::NotFound, "jobs/x"));
    }
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
