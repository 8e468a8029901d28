//! `willow.v1.Fairing`: uploads, jobs, frame streams, downloads and curves.

use bytes::Bytes;
use futures::StreamExt;
use tonic::{Request, Response, Status, Streaming};

use super::convert::{
    curve_response_pb, duration_from_pb, format_from_pb, format_pb, frame_pb, grpc_timeout, job_pb,
    operation, page_size, parse_name, request_id, spec_from_pb, state_from_pb,
};
use super::errors::{bad_request, caller, curve_error, job_error};
use super::pb::google::longrunning as lro;
use super::pb::willow::v1;
use super::upload::UploadAssembly;
use super::{BoxStream, GrpcApi, WAIT_DEADLINE_MARGIN};
use crate::api::download::{self, Busy, DownloadBudget, DownloadError, BUSY_RETRY_SECS};
use crate::jobs::curve::{CurveInput, CurveSpec};
use crate::jobs::{JobError, JobEvent, UploadRef};
use std::time::Duration;
use tonic::Code;
use tonic_types::{ErrorDetails, StatusExt};

/// UNAVAILABLE with RetryInfo: too many downloads are waiting to be read.
fn downloads_busy(b: Busy) -> Status {
    let mut details = ErrorDetails::new();
    details.set_retry_info(Some(Duration::from_secs(BUSY_RETRY_SECS)));
    Status::with_error_details(Code::Unavailable, b.detail(), details)
}

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
        let floor = request
            .extensions()
            .get::<DownloadBudget>()
            .map(DownloadBudget::watch_floor)
            .unwrap_or_default();
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
            .watch_with_floor(&caller, &id, request.from_step as usize, floor)
            .await
            .map_err(|e| job_error(e, "name"))?;
        // A client slower than the floor is cut off: its stream ends with DEADLINE_EXCEEDED.
        let cut = events.cut();
        let tail = futures::stream::once(async move {
            cut.is_cut().then(|| {
                Err(Status::deadline_exceeded(
                    "the client did not take the stream's events in time (write deadline and \
                     minimum rate); watch again from the next step",
                ))
            })
        })
        .filter_map(futures::future::ready);
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
            .chain(tail)
            .boxed();
        Ok(Response::new(responses))
    }

    type DownloadResultStream = BoxStream<v1::DownloadResultChunk>;

    async fn download_result(
        &self,
        request: Request<v1::DownloadResultRequest>,
    ) -> Result<Response<Self::DownloadResultStream>, Status> {
        let caller = caller(&request)?;
        let budget = request.extensions().get::<DownloadBudget>().cloned();
        if let Some(b) = &budget {
            b.check().map_err(downloads_busy)?;
        }
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
        let bytes = self
            .jobs
            .result_download(
                &caller,
                &id,
                format,
                budget.as_ref().map(DownloadBudget::memory),
            )
            .await
            .map_err(|e| job_error(e, "name"))?;
        let download = download::start(budget.as_ref(), bytes)
            .await
            .map_err(downloads_busy)?;
        // Chunks are handed out as the client takes them, and the download's deadline drops
        // the buffer of a client that does not (see api::download).
        let chunks = futures::stream::unfold((download, true), move |(mut d, first)| async move {
            let chunk = d.next_chunk().await?;
            let item = chunk
                .map(|data| v1::DownloadResultChunk {
                    format: if first { format_pb(format) as i32 } else { 0 },
                    data,
                })
                .map_err(|e| match e {
                    DownloadError::TooSlow => Status::deadline_exceeded(e.to_string()),
                    DownloadError::Storage(_) => Status::unavailable(e.to_string()),
                });
            Some((item, (d, false)))
        });
        Ok(Response::new(chunks.boxed()))
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
