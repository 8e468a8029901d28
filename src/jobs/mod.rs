//! The job core: fairing jobs accepted, queued, run, streamed and kept, for every transport.
//!
//! HTTP (`api::http`), gRPC (`api::grpc`) and the CLI all call the same [`Jobs`] handle; nothing
//! in here knows about axum, tonic or any wire type. What crosses the border in is a
//! [`UploadRef`] plus a validated [`JobSpec`]; what crosses out is a [`JobStatus`], a stream of
//! [`JobEvent`]s (each step's [`Frame`]) and result bytes. Errors are one enum, [`JobError`],
//! which each transport maps once to its own status codes.
//!
//! The pieces, one file each:
//! - [`ports`]: the five seams to a backend (`JobStore`, `BlobStore`, `WorkQueue`, `EventBus`,
//!   `CancelBus`); admission (here), [`worker`] and [`watch`] are written once over them.
//! - [`embedded`]: the default backend (SQLite, files, in-process queue and broadcast).
//! - [`nats`]: the NATS JetStream backend, for many API and worker nodes.
//! - [`codec`]: the byte forms the backends share (metrics, positions, checkpoints, hashes).
//! - [`watch`]: state, replayed and live frames for any number of watchers on any node.
//! - [`worker`]: the bounded pool that runs flows step by step on blocking threads, checking
//!   cancellation, deadline and shutdown between steps, heartbeating its lease and
//!   checkpointing.
//! - [`telemetry`]: the Prometheus metrics of the core (queue depth, running, outcomes, durations).
//! - [`spec`]: the filter and boundary options of a [`JobSpec`], as the network may send them.
//! - [`curve`]: synchronous curve fairing ([`Jobs::fair_curve`]) on its own bounded slots.
//!
//! Times in [`JobStatus`] are **unix milliseconds** (`u64`): cheap to compare and to turn into a
//! protobuf `Timestamp` or an RFC 3339 string at the edge ([`rfc3339`] does the latter).
//!
//! Restart semantics: every accepted job is in the store before `submit` returns. On start,
//! finished jobs keep their results, queued jobs are queued again in their original order, and
//! jobs that were running are re-queued and **resume from their last checkpoint** (step 0 if
//! they had none): the frames after it are taken again, and watchers see each step once.

pub mod codec;
pub mod curve;
pub mod embedded;
pub mod nats;
pub mod ports;
pub mod spec;
pub mod telemetry;
pub mod watch;
pub mod worker;

use crate::flow::curve::CurveError;
use crate::flow::{FlowParams, Method};
use crate::mesh::io::{Asset, Format};
use crate::mesh::{Limits, MeshError};
use crate::metrics::StepMetrics;
use futures::Stream;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio_util::sync::CancellationToken;

use ports::{Backend, BlobKey, Inserted, NewJob};

/// A job's identifier: a UUID v4 in its hyphenated lower-case text form.
pub type JobId = String;

/// What to run on an uploaded mesh. Transports turn their wire parameters into this and call
/// [`JobSpec::validate`] (which [`Jobs::submit`] calls again, so no transport can skip it).
///
/// Stored as JSON with the job: a field added later must have a default (`#[serde(default)]`
/// fills it in for rows written before it existed) and is appended at the end (see
/// `codec::request_hash`). Every field of [`FlowParams`] has one here.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobSpec {
    /// Which flow: `conformal` (the paper), `mcf` (the yardstick), `cmcf`, `bilaplacian` or
    /// `taubin`.
    pub method: Method,
    /// Number of flow steps to take (step 0 is the input).
    pub steps: usize,
    /// Time step τ (see [`FlowParams::tau`]).
    pub tau: f64,
    /// Inverse power iterations per step (conformal flow).
    pub iterations: usize,
    /// Every `frame_interval`-th step (and step 0 and the last step) keeps its vertex positions,
    /// so `frames/{step}` can serve that mesh and watchers get `positions`.
    pub frame_interval: usize,
    /// Whether live and replayed frames carry positions at all (metrics are always sent).
    pub include_positions: bool,
    /// Wall-clock budget from submission, in seconds; `None` takes the server default.
    pub deadline_secs: Option<f64>,
    /// Exactness constraints on surfaces of genus > 0 (§6.2, App. C); conformal flow only.
    pub exactness: bool,
    /// Möbius balancing toward the input's area distribution (App. E.1); conformal flow only.
    pub mobius_balancing: bool,
    /// Spectral filter of the flow direction (§4); `None` is the paper's plain flow. Conformal
    /// flow only.
    pub filter: Option<spec::FilterSpec>,
    /// Boundary condition (§6.3); anything but `free` is for the conformal flow only.
    pub boundary: spec::BoundarySpec,
    /// Safeguarded steps (see [`crate::flow::safeguard`]): a step that raises W or damages the
    /// mesh is retried at a smaller τ. Every method; default on.
    pub safeguard: bool,
}

impl Default for JobSpec {
    fn default() -> Self {
        let flow = FlowParams::default();
        JobSpec {
            method: flow.method,
            steps: 20,
            tau: flow.tau,
            iterations: flow.iterations,
            frame_interval: 1,
            include_positions: true,
            deadline_secs: None,
            exactness: flow.exactness,
            mobius_balancing: flow.mobius_balancing,
            filter: None,
            boundary: spec::BoundarySpec::Free,
            safeguard: flow.safeguard,
        }
    }
}

impl JobSpec {
    /// Check every field against the server's limits; the error names the field.
    pub fn validate(&self, config: &Config) -> Result<(), JobError> {
        self.validate_with(config.limits.max_steps, config.max_deadline.as_secs_f64())
    }

    /// [`JobSpec::validate`] with explicit limits (the CLI has none of a server's).
    pub fn validate_with(&self, max_steps: usize, max_deadline_secs: f64) -> Result<(), JobError> {
        let bad =
            |field: &'static str, reason: String| Err(JobError::InvalidSpec { field, reason });
        if self.steps == 0 {
            return bad("steps", "must be at least 1".into());
        }
        if self.steps > max_steps {
            return Err(JobError::TooLarge {
                what: "steps",
                limit: max_steps as u64,
            });
        }
        if !self.tau.is_finite() || self.tau <= 0.0 {
            return bad(
                "tau",
                format!("must be a finite number > 0, got {}", self.tau),
            );
        }
        if self.method == Method::Conformal && self.tau >= 1.0 {
            // Paper §4: the curvature update u ← (1 − 2τ)u is only stable for τ < 1.
            return bad(
                "tau",
                format!(
                    "must be < 1 for the conformal flow (paper §4), got {}",
                    self.tau
                ),
            );
        }
        if self.iterations == 0 || self.iterations > MAX_ITERATIONS {
            return bad(
                "iterations",
                format!(
                    "must be between 1 and {MAX_ITERATIONS}, got {}",
                    self.iterations
                ),
            );
        }
        if self.frame_interval == 0 {
            return bad("frame_interval", "must be at least 1".into());
        }
        if let Some(d) = self.deadline_secs {
            if !d.is_finite() || d <= 0.0 {
                return bad(
                    "deadline_secs",
                    format!("must be a finite number > 0, got {d}"),
                );
            }
            if d > max_deadline_secs {
                return bad(
                    "deadline_secs",
                    format!("must be at most {max_deadline_secs} (the server's maximum), got {d}"),
                );
            }
        }
        if let Some(filter) = &self.filter {
            if let Err((field, reason)) = spec::check_filter(filter) {
                return bad(field, reason);
            }
        }
        if let Err((field, reason)) = spec::check_boundary(&self.boundary) {
            return bad(field, reason);
        }
        if self.method != Method::Conformal {
            // The other flows would run and silently ignore these (the library only reads them
            // in the conformal flow); a client that asks for them should hear so.
            let ignored = [
                ("exactness", !self.exactness),
                ("mobius_balancing", self.mobius_balancing),
                ("filter", self.filter.is_some()),
                ("boundary", !self.boundary.is_free()),
            ];
            if let Some((field, _)) = ignored.iter().find(|(_, set)| *set) {
                return bad(
                    field,
                    format!(
                        "applies only to method `conformal`, got `{}`",
                        self.method.name()
                    ),
                );
            }
        }
        Ok(())
    }

    /// Checks that need the uploaded surface: one per-loop boundary angle per boundary loop.
    pub fn validate_for_mesh(&self, mesh: &crate::mesh::Mesh) -> Result<(), JobError> {
        if let spec::BoundarySpec::Prescribed(p) = &self.boundary {
            if matches!(p.angles, spec::AnglesSpec::PerLoop(_)) {
                let loops = crate::mesh::topology::Topology::new(mesh)
                    .boundary_loops
                    .len();
                spec::check_loop_count(&self.boundary, loops)
                    .map_err(|(field, reason)| JobError::InvalidSpec { field, reason })?;
            }
        }
        Ok(())
    }

    /// The flow parameters this spec asks for: every field of [`FlowParams`].
    pub fn flow_params(&self) -> FlowParams {
        FlowParams {
            method: self.method,
            tau: self.tau,
            iterations: self.iterations,
            exactness: self.exactness,
            mobius_balancing: self.mobius_balancing,
            filter: self.filter.map(spec::FilterSpec::to_flow),
            boundary: self.boundary.to_flow(),
            safeguard: self.safeguard,
            // Not the client's to choose: the worker pool sets it (`worker::thread_budget`).
            threads: 1,
            precision: crate::flow::Precision::Auto,
        }
    }

    /// Whether `step` keeps positions (step 0, every `frame_interval`-th, and the last).
    pub fn keeps_positions(&self, step: usize) -> bool {
        self.include_positions
            && (step.is_multiple_of(self.frame_interval.max(1)) || step == self.steps)
    }
}

pub use crate::flow::MAX_ITERATIONS;

/// Where a job is in its life. Terminal states: succeeded, failed, cancelled.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<JobState> {
        Some(match s {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "succeeded" => JobState::Succeeded,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            _ => return None,
        })
    }
}

/// A snapshot of one job, as every transport reports it. Times are unix milliseconds.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: JobId,
    pub state: JobState,
    /// Steps completed so far (0 while queued).
    pub step: usize,
    pub total_steps: usize,
    pub spec: JobSpec,
    #[serde(
        serialize_with = "serialize_format",
        deserialize_with = "deserialize_format"
    )]
    pub input_format: Format,
    /// Vertices in the uploaded file's order: a frame's positions are this many xyz triples.
    pub vertex_count: usize,
    /// Triangles of the welded surface.
    pub face_count: usize,
    /// Metrics of the latest completed step (step 0 = the input) once the job has started.
    pub latest: Option<StepMetrics>,
    /// Why the job failed or was cancelled, for people; on a succeeded job, why it stopped
    /// before `total_steps` (code `no_progress`).
    pub error: Option<String>,
    /// The same, for programs: `deadline_exceeded`, `cancelled`, `numerical`, `invalid_mesh`,
    /// `unsupported`, `invalid_parameter`, `internal`; and `no_progress` on a **succeeded** job
    /// the safeguard stopped early (no acceptable step, even at τ/1024): its result is the
    /// last accepted surface, the one after step `step`.
    pub error_code: Option<String>,
    pub created_at: u64,
    pub started_at: Option<u64>,
    pub finished_at: Option<u64>,
    /// When a finished job's results are deleted (then every call answers [`JobError::Gone`]).
    pub expires_at: Option<u64>,
}

fn serialize_format<S: serde::Serializer>(f: &Format, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(format_name(*f))
}

fn deserialize_format<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Format, D::Error> {
    let name = String::deserialize(d)?;
    parse_format(&name)
        .ok_or_else(|| serde::de::Error::custom(format!("unknown mesh format `{name}`")))
}

/// One step of a running job, as watchers receive it.
#[derive(Clone, Debug)]
pub struct Frame {
    pub step: usize,
    pub metrics: StepMetrics,
    /// Vertex positions after the step, in the uploaded file's vertex order, when this step
    /// keeps positions ([`JobSpec::keeps_positions`]). Shared, so fan-out copies no vertices.
    pub positions: Option<Arc<Vec<[f32; 3]>>>,
}

/// What a watcher sees: state changes, one frame per step, then the final status.
#[derive(Clone, Debug)]
pub enum JobEvent {
    State(JobStatus),
    Frame(Frame),
    Done(JobStatus),
}

/// The mesh a job runs on: the bytes themselves, or an upload stored earlier by
/// [`Jobs::store_upload`] (chunked gRPC uploads).
pub enum UploadRef {
    Bytes { data: bytes::Bytes, format: Format },
    Stored { upload_id: String },
}

/// Everything that can go wrong, typed so each transport maps it once to its own codes.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("job `{0}` not found")]
    NotFound(JobId),
    #[error("job `{0}` has expired and its results were deleted")]
    Gone(JobId),
    #[error("the queue is full ({capacity} jobs waiting); retry in about {retry_after_secs} s")]
    QueueFull {
        retry_after_secs: u64,
        capacity: usize,
    },
    #[error("invalid mesh: {0}")]
    InvalidMesh(MeshError),
    #[error("invalid parameter `{field}`: {reason}")]
    InvalidSpec { field: &'static str, reason: String },
    #[error("{what} exceeds the limit of {limit}")]
    TooLarge { what: &'static str, limit: u64 },
    #[error("{0}")]
    Conflict(String),
    #[error("idempotency key reused with a different request: {0}")]
    IdempotencyMismatch(String),
    #[error("the server is shutting down and accepts no new jobs")]
    ShuttingDown,
    #[error("internal error: {0}")]
    Internal(String),
    /// The backend's server did not answer in time (NATS restarting, a network partition):
    /// retry shortly. A running job that meets it is left to be delivered again and resumes
    /// from its checkpoint; it is never failed for it.
    #[error("the job backend is unavailable: {0}")]
    Unavailable(String),
    /// A step that exists but kept no positions, or a step past the job's progress.
    #[error("job `{id}` has no mesh for step {step}: {detail}")]
    FrameNotFound {
        id: JobId,
        step: usize,
        detail: String,
    },
    /// An upload id that [`Jobs::store_upload`] never returned (or that expired).
    #[error("upload `{0}` not found")]
    UploadNotFound(String),
    /// A curve the curve flow refuses (see [`CurveError`]).
    #[error("invalid curve: {0}")]
    InvalidCurve(CurveError),
    /// Every slot for synchronous work is taken (curve fairing); retry shortly.
    #[error("all {slots} curve slots are busy; retry in about {retry_after_secs} s")]
    Busy { retry_after_secs: u64, slots: usize },
    /// A synchronous request ran out of its time budget.
    #[error("deadline of {secs} s exceeded after step {step} of {steps}")]
    DeadlineExceeded {
        secs: f64,
        step: usize,
        steps: usize,
    },
    /// The flow broke down on this input (non-finite positions).
    #[error("numerical failure at step {step}: {reason}")]
    Numerical { step: usize, reason: String },
}

impl JobError {
    /// A stable machine-readable code, shared by every transport.
    pub fn code(&self) -> &'static str {
        match self {
            JobError::NotFound(_) => "not_found",
            JobError::Gone(_) => "gone",
            JobError::QueueFull { .. } => "queue_full",
            JobError::InvalidMesh(e) => e.code(),
            JobError::InvalidSpec { .. } => "invalid_parameter",
            JobError::TooLarge { .. } => "too_large",
            JobError::Conflict(_) => "conflict",
            JobError::IdempotencyMismatch(_) => "idempotency_mismatch",
            JobError::ShuttingDown => "shutting_down",
            JobError::Internal(_) => "internal",
            JobError::Unavailable(_) => "unavailable",
            JobError::FrameNotFound { .. } => "frame_not_found",
            JobError::UploadNotFound(_) => "upload_not_found",
            JobError::InvalidCurve(e) => curve::curve_error_code(e),
            JobError::Busy { .. } => "busy",
            JobError::DeadlineExceeded { .. } => "deadline_exceeded",
            JobError::Numerical { .. } => "numerical",
        }
    }
}

impl From<rusqlite::Error> for JobError {
    fn from(e: rusqlite::Error) -> Self {
        JobError::Internal(format!("store: {e}"))
    }
}

impl From<std::io::Error> for JobError {
    fn from(e: std::io::Error) -> Self {
        JobError::Internal(format!("file: {e}"))
    }
}

/// Size limits, all named in the errors that enforce them.
#[derive(Clone, Debug)]
pub struct JobLimits {
    /// Largest accepted upload in bytes.
    pub max_upload_bytes: u64,
    /// Most vertices of the welded surface.
    pub max_vertices: usize,
    /// Most triangles.
    pub max_faces: usize,
    /// Most steps one job may ask for.
    pub max_steps: usize,
    /// Most points of a curve sent to [`Jobs::fair_curve`].
    pub max_curve_points: usize,
    /// Most steps one curve request may ask for.
    pub max_curve_steps: usize,
    /// Largest curve file (JSON or OBJ) in bytes.
    pub max_curve_bytes: u64,
    /// Most points a curve response may carry in its frames, all frames together.
    pub max_curve_frame_points: usize,
}

impl Default for JobLimits {
    fn default() -> Self {
        JobLimits {
            // 64 MiB: a 1M-triangle GLB is about 40 MiB; above that one job would hold a
            // worker for hours on this class of machine anyway.
            max_upload_bytes: 64 << 20,
            max_vertices: 1_000_000,
            max_faces: 2_000_000,
            max_steps: 10_000,
            // A curve step costs ~0.1 ms per 2k points and a flow holds ~15 f64 per point, so
            // 100k points are ~5 ms a step and ~12 MB a request: a synchronous answer stays
            // well inside the deadline even at a few hundred steps.
            max_curve_points: 100_000,
            // The flow reaches its minimum in about six steps at τ = 0.5 (§5); a thousand is
            // room for small τ without letting one request hold a slot for long.
            max_curve_steps: 1_000,
            // 100k points as JSON or OBJ text are ~5 MB.
            max_curve_bytes: 8 << 20,
            // ~45 MB of JSON at most: a few hundred frames of a detailed curve.
            max_curve_frame_points: 1_000_000,
        }
    }
}

impl JobLimits {
    /// The same limits in the mesh reader's terms.
    pub fn mesh_limits(&self) -> Limits {
        Limits {
            max_bytes: usize::try_from(self.max_upload_bytes).unwrap_or(usize::MAX),
            max_vertices: self.max_vertices,
            max_faces: self.max_faces,
        }
    }
}

/// How the job core runs. `Config::new(dir)` gives defaults that work on a fresh machine.
#[derive(Clone, Debug)]
pub struct Config {
    /// Holds `willow.sqlite3` and the blob folders; created if missing.
    pub data_dir: PathBuf,
    /// Blocking workers, each running one single-threaded flow (default: the core count, since
    /// a flow step is CPU-bound and more workers than cores only interleave them).
    pub workers: usize,
    /// Jobs that may wait (not counting running ones) before `submit` answers `QueueFull`.
    pub queue_capacity: usize,
    pub limits: JobLimits,
    /// How long a finished job (and an unused upload) is kept before it answers `Gone`.
    pub result_ttl: Duration,
    /// Deadline of jobs whose spec names none.
    pub default_deadline: Duration,
    /// Largest deadline a spec may ask for.
    pub max_deadline: Duration,
    /// How often expired jobs are swept from disk.
    pub sweep_interval: Duration,
    /// Readiness turns false when a job is running and no step finished for this long: a
    /// wedged worker must not keep a pod in the load balancer.
    pub stall_after: Duration,
    /// Curve requests that may run at once, each on one blocking thread (default: `workers`).
    /// Separate from the job workers, whose jobs may hold them for hours; see [`curve`].
    pub curve_slots: usize,
    /// Time budget of a curve request that names none.
    pub curve_default_deadline: Duration,
    /// Largest time budget a curve request may ask for: the answer is synchronous, and common
    /// proxies cut idle requests after 60 s.
    pub curve_max_deadline: Duration,
    /// What this node does: take requests, run jobs, or both.
    pub role: Role,
    /// A running job checkpoints after this many steps…
    pub checkpoint_steps: usize,
    /// …or this long after its last checkpoint, whichever comes first.
    pub checkpoint_interval: Duration,
    /// How often a running job's lease is renewed (well inside the queue's `ack_wait`).
    pub heartbeat_interval: Duration,
    /// A job delivered more often than this (its workers kept dying on it) fails with code
    /// `redelivered` instead of taking down one more worker.
    pub max_deliveries: u32,
}

/// What a node of the service does. One process of the embedded backend is both; with NATS,
/// API nodes and worker nodes scale separately.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Role {
    /// Admission, status, streams, results: no worker loops.
    Api,
    /// Worker loops only (the transports then serve probes and metrics).
    Worker,
    All,
}

impl Role {
    pub fn parse(s: &str) -> Option<Role> {
        Some(match s {
            "api" => Role::Api,
            "worker" => Role::Worker,
            "all" => Role::All,
            _ => return None,
        })
    }

    pub fn runs_workers(self) -> bool {
        self != Role::Api
    }

    pub fn serves_api(self) -> bool {
        self != Role::Worker
    }
}

impl Config {
    pub fn new(data_dir: impl Into<PathBuf>) -> Config {
        Config {
            data_dir: data_dir.into(),
            workers: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            queue_capacity: 64,
            limits: JobLimits::default(),
            result_ttl: Duration::from_secs(24 * 3600),
            default_deadline: Duration::from_secs(3600),
            max_deadline: Duration::from_secs(24 * 3600),
            sweep_interval: Duration::from_secs(60),
            stall_after: Duration::from_secs(600),
            curve_slots: std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1),
            curve_default_deadline: Duration::from_secs(10),
            curve_max_deadline: Duration::from_secs(60),
            role: Role::All,
            // A checkpoint is one blob of 24 bytes per vertex: ~1 ms for a 100k-triangle mesh
            // whose step takes ~0.5 s, so ten steps or half a minute lose little on a crash
            // and cost well under 1% (`cargo bench --bench service_load` measures it).
            checkpoint_steps: 10,
            checkpoint_interval: Duration::from_secs(30),
            heartbeat_interval: Duration::from_secs(5),
            max_deliveries: 3,
        }
    }
}

/// Unix milliseconds now.
pub fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

/// RFC 3339 UTC text (`2026-11-22T12:52:02.123Z`) of unix milliseconds.
pub fn rfc3339(ms: u64) -> String {
    let secs = ms / 1000;
    let (days, rem) = (secs / 86_400, secs % 86_400);
    // Civil-from-days (Howard Hinnant's algorithm), valid for all dates after 1970.
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        (rem % 3600) / 60,
        rem % 60,
        ms % 1000
    )
}

/// The lower-case name of a mesh format, as stored and as in `?format=`.
pub fn format_name(f: Format) -> &'static str {
    match f {
        Format::Obj => "obj",
        Format::Glb => "glb",
        Format::Gltf => "gltf",
    }
}

/// The inverse of [`format_name`].
pub fn parse_format(s: &str) -> Option<Format> {
    Some(match s.to_ascii_lowercase().as_str() {
        "obj" => Format::Obj,
        "glb" => Format::Glb,
        "gltf" => Format::Gltf,
        _ => return None,
    })
}

/// The media type of a mesh format (for downloads).
pub fn format_media_type(f: Format) -> &'static str {
    match f {
        Format::Obj => "model/obj",
        Format::Glb => "model/gltf-binary",
        Format::Gltf => "model/gltf+json",
    }
}

/// Shared state behind the [`Jobs`] handle.
pub(crate) struct Inner {
    pub config: Config,
    pub backend: Backend,
    /// Serialises this node's admission decisions (idempotency lookup, capacity, insert,
    /// enqueue) so two of its submissions cannot both take the last slot. Across nodes the
    /// backend's own atomic operations decide (see [`ports::JobStore::insert`]).
    pub admission: tokio::sync::Mutex<()>,
    pub draining: AtomicBool,
    /// Cancelled when draining begins, for transports that must react (gRPC health).
    pub drain_signal: CancellationToken,
    /// Cancelled on shutdown after the grace period: running jobs stop at the next step,
    /// checkpoint and are re-queued.
    pub shutdown: CancellationToken,
    pub telemetry: telemetry::Telemetry,
    /// Unix ms of the latest worker progress (a finished step or an idle poll).
    pub last_progress_ms: AtomicU64,
    pub running: AtomicUsize,
    pub workers_alive: AtomicUsize,
    /// Exponential moving average of job wall time in ms, for `Retry-After` estimates.
    pub avg_job_ms: AtomicU64,
    /// Permits for curve requests ([`Config::curve_slots`]).
    pub curve_slots: Arc<tokio::sync::Semaphore>,
}

/// The cheap, cloneable handle every transport holds.
#[derive(Clone)]
pub struct Jobs {
    pub(crate) inner: Arc<Inner>,
}

/// Returned by [`Jobs::start`]: owns the workers. Call [`Shutdown::shutdown`] to drain; dropping
/// it without that stops the workers at their next step (jobs are then re-queued on restart).
pub struct Shutdown {
    jobs: Jobs,
    tracker: tokio_util::task::TaskTracker,
    stop_polling: CancellationToken,
}

impl Jobs {
    /// The embedded backend under `config.data_dir`: see [`Jobs::start_with`].
    pub async fn start(config: Config) -> Result<(Jobs, Shutdown), JobError> {
        let (dir, capacity) = (config.data_dir.clone(), config.queue_capacity);
        let backend = tokio::task::spawn_blocking(move || embedded::open(&dir, capacity))
            .await
            .map_err(join_err)??;
        Jobs::start_with(config, backend).await
    }

    /// Recover jobs the backend's queue does not hold (the embedded backend after a restart),
    /// then spawn the workers (if `config.role` runs any) and the expiry sweeper (if it serves
    /// the API). Must be called inside a tokio runtime.
    pub async fn start_with(
        config: Config,
        backend: Backend,
    ) -> Result<(Jobs, Shutdown), JobError> {
        let positive = [
            ("workers", config.workers),
            ("queue_capacity", config.queue_capacity),
            ("curve_slots", config.curve_slots),
            ("checkpoint_steps", config.checkpoint_steps),
            ("max_deliveries", config.max_deliveries as usize),
        ];
        if let Some((field, _)) = positive.iter().find(|(_, v)| *v == 0) {
            return Err(JobError::InvalidSpec {
                field,
                reason: "must be at least 1".into(),
            });
        }
        let recovered = backend.store.recover().await?;
        for id in &recovered {
            // Recovered jobs bypass the capacity check: they were admitted before.
            backend.queue.push_recovered(id).await?;
        }
        if !recovered.is_empty() {
            tracing::info!(count = recovered.len(), "re-queued jobs from the store");
        }
        let inner = Arc::new(Inner {
            config: config.clone(),
            backend,
            admission: tokio::sync::Mutex::new(()),
            draining: AtomicBool::new(false),
            drain_signal: CancellationToken::new(),
            shutdown: CancellationToken::new(),
            telemetry: telemetry::Telemetry::new(),
            last_progress_ms: AtomicU64::new(now_ms()),
            running: AtomicUsize::new(0),
            workers_alive: AtomicUsize::new(0),
            avg_job_ms: AtomicU64::new(5_000),
            curve_slots: Arc::new(tokio::sync::Semaphore::new(config.curve_slots)),
        });
        let jobs = Jobs { inner };
        jobs.inner
            .telemetry
            .queue_depth
            .set(jobs.inner.backend.queue.depth() as i64);

        let tracker = tokio_util::task::TaskTracker::new();
        let stop_polling = CancellationToken::new();
        if config.role.runs_workers() {
            for n in 0..config.workers {
                tracker.spawn(worker::worker_loop(jobs.clone(), n, stop_polling.clone()));
            }
        }
        if config.role.serves_api() {
            let sweeper = jobs.clone();
            let stop = stop_polling.clone();
            tokio::spawn(async move { sweeper.sweep_loop(stop).await });
        }
        tracker.close();
        Ok((
            jobs.clone(),
            Shutdown {
                jobs,
                tracker,
                stop_polling,
            },
        ))
    }

    pub fn config(&self) -> &Config {
        &self.inner.config
    }

    /// `embedded` or the NATS URL: for logs and probes.
    pub fn backend_name(&self) -> &str {
        &self.inner.backend.name
    }

    /// Parse and validate the mesh (on a blocking thread), then store and enqueue the job.
    ///
    /// With an idempotency key, a repeat of the same request returns the job it created (even
    /// when the queue has since filled up, and on any node); the same key with a different
    /// mesh or spec is [`JobError::IdempotencyMismatch`].
    pub async fn submit(
        &self,
        upload: UploadRef,
        spec: JobSpec,
        idempotency_key: Option<String>,
    ) -> Result<JobStatus, JobError> {
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        spec.validate(&self.inner.config)?;
        let backend = &self.inner.backend;
        let (data, format) = match upload {
            UploadRef::Bytes { data, format } => (data, format),
            UploadRef::Stored { upload_id } => {
                let format = backend.store.upload(&upload_id).await?;
                let key = BlobKey::Upload {
                    id: upload_id.clone(),
                    format,
                };
                let data = backend
                    .blobs
                    .get(key)
                    .await?
                    .ok_or(JobError::UploadNotFound(upload_id))?;
                (data, format)
            }
        };
        let limit = self.inner.config.limits.max_upload_bytes;
        if data.len() as u64 > limit {
            return Err(JobError::TooLarge {
                what: "upload bytes",
                limit,
            });
        }
        let key = match idempotency_key {
            Some(k) if k.is_empty() || k.len() > 255 => {
                return Err(JobError::InvalidSpec {
                    field: "idempotency_key",
                    reason: "must be 1 to 255 characters".into(),
                })
            }
            other => other,
        };
        let request_hash = key
            .as_ref()
            .map(|_| codec::request_hash(&data, format, &spec));
        if let (Some(k), Some(h)) = (&key, &request_hash) {
            if let Some(status) = backend.store.idempotent(k, h).await? {
                return Ok(status);
            }
        }

        // Parse and validate off the runtime: a large OBJ takes a while and the async threads
        // must keep serving status polls and streams meanwhile.
        let limits = self.inner.config.limits.clone();
        let parse_data = data.clone();
        let parse_spec = spec.clone();
        let (vertex_count, face_count) = tokio::task::spawn_blocking(move || {
            let asset =
                Asset::read(&parse_data, format, &limits.mesh_limits()).map_err(mesh_error)?;
            let surface = asset.surface();
            parse_spec.validate_for_mesh(surface)?;
            if surface.vertex_count() > limits.max_vertices {
                return Err(JobError::TooLarge {
                    what: "vertices",
                    limit: limits.max_vertices as u64,
                });
            }
            if surface.face_count() > limits.max_faces {
                return Err(JobError::TooLarge {
                    what: "faces",
                    limit: limits.max_faces as u64,
                });
            }
            Ok((asset.file_vertex_count(), surface.face_count()))
        })
        .await
        .map_err(join_err)??;

        let id: JobId = uuid::Uuid::new_v4().to_string();
        // Write the blob before taking the admission lock: fsync is slow and need not be
        // serialised. A refused job's blob is removed again below.
        backend
            .blobs
            .put(
                BlobKey::Input {
                    id: id.clone(),
                    format,
                },
                data,
            )
            .await?;
        let job = NewJob {
            id: id.clone(),
            spec: spec.clone(),
            format,
            vertex_count,
            face_count,
            created_at: now_ms(),
            idempotency: key.zip(request_hash),
        };
        match self.admit(job).await {
            Ok(Inserted::New(status)) => {
                tracing::info!(job_id = %status.id, vertex_count, face_count, steps = spec.steps, "job accepted");
                Ok(status)
            }
            Ok(Inserted::Existing(status)) => {
                let _ = backend.blobs.delete_job(&id).await;
                Ok(status)
            }
            Err(e) => {
                let _ = backend.blobs.delete_job(&id).await;
                Err(e)
            }
        }
    }

    async fn admit(&self, job: NewJob) -> Result<Inserted, JobError> {
        let backend = &self.inner.backend;
        let _guard = self.inner.admission.lock().await;
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        // A quick local refusal; the queue's own `push` is the cluster-wide decision.
        if backend.queue.depth() >= backend.queue.capacity() {
            return Err(self.queue_full());
        }
        let id = job.id.clone();
        let inserted = backend.store.insert(job).await?;
        if let Inserted::Existing(_) = inserted {
            return Ok(inserted);
        }
        if let Err(e) = backend.queue.push(&id).await {
            // Lost the race for the last slot to another node (or the queue is away): the
            // record goes again, key and all, so a retry can succeed.
            let now = now_ms();
            let withdrawn = Some(("queue_full".to_string(), e.to_string()));
            let _ = backend
                .store
                .finish(&id, JobState::Failed, withdrawn, now, now)
                .await;
            let _ = backend.store.delete(&id).await;
            return Err(match e {
                JobError::QueueFull { .. } => self.queue_full(),
                other => other,
            });
        }
        self.inner.telemetry.submitted.inc();
        self.inner
            .telemetry
            .queue_depth
            .set(backend.queue.depth() as i64);
        Ok(inserted)
    }

    fn queue_full(&self) -> JobError {
        self.inner.telemetry.rejected.inc();
        JobError::QueueFull {
            retry_after_secs: self.retry_after_secs(),
            capacity: self.inner.backend.queue.capacity(),
        }
    }

    /// `Retry-After` estimate: the time for the workers to drain the queue once, from the
    /// moving average of job durations, clamped to 1..=300 s.
    fn retry_after_secs(&self) -> u64 {
        let avg_ms = self.inner.avg_job_ms.load(Ordering::Relaxed);
        let workers = self.inner.config.workers.max(1) as u64;
        let depth = self.inner.backend.queue.depth().max(1) as u64;
        (avg_ms * depth / workers / 1000).clamp(1, 300)
    }

    /// Store an upload for later use by [`UploadRef::Stored`]. The mesh is validated now, so a
    /// bad upload fails here and not at job creation.
    pub async fn store_upload(
        &self,
        data: bytes::Bytes,
        format: Format,
    ) -> Result<String, JobError> {
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        let limit = self.inner.config.limits.max_upload_bytes;
        if data.len() as u64 > limit {
            return Err(JobError::TooLarge {
                what: "upload bytes",
                limit,
            });
        }
        let limits = self.inner.config.limits.mesh_limits();
        let check = data.clone();
        tokio::task::spawn_blocking(move || Asset::read(&check, format, &limits).map(|_| ()))
            .await
            .map_err(join_err)?
            .map_err(mesh_error)?;
        let id = uuid::Uuid::new_v4().to_string();
        let expires = now_ms() + self.inner.config.result_ttl.as_millis() as u64;
        let size = data.len() as u64;
        let backend = &self.inner.backend;
        let key = BlobKey::Upload {
            id: id.clone(),
            format,
        };
        backend.blobs.put(key, data).await?;
        backend.store.put_upload(&id, format, size, expires).await?;
        Ok(id)
    }

    /// The job's current status; `Gone` once it expired.
    pub async fn get(&self, id: &str) -> Result<JobStatus, JobError> {
        self.inner.backend.store.status(id).await
    }

    /// Jobs newest first, optionally of one state. `page_token` is the opaque
    /// `next_page_token` of the previous page; `page_size` 0 means 50, at most 1000.
    pub async fn list(
        &self,
        state: Option<JobState>,
        page_size: usize,
        page_token: Option<String>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError> {
        let size = match page_size {
            0 => 50,
            n => n.min(1000),
        };
        self.inner.backend.store.list(state, size, page_token).await
    }

    /// Cancel a job. Queued: removed from the queue and cancelled now. Running (on any node):
    /// it stops at the next step boundary (the returned status may still say `running`; watch
    /// or poll for `cancelled`). Terminal: [`JobError::Conflict`].
    pub async fn cancel(&self, id: &str) -> Result<JobStatus, JobError> {
        let status = self.get(id).await?;
        if status.state.is_terminal() {
            return Err(JobError::Conflict(format!(
                "job `{id}` is already {} and cannot be cancelled",
                status.state.as_str()
            )));
        }
        let backend = &self.inner.backend;
        // Either we take the job out of the queue (then no worker will run it: `start` refuses
        // a terminal job), or a worker has it (then the cancel bus tells it to stop).
        if status.state == JobState::Queued && backend.queue.withdraw(id).await? {
            self.inner
                .telemetry
                .queue_depth
                .set(backend.queue.depth() as i64);
            return worker::finish(
                &self.inner,
                id,
                JobState::Cancelled,
                Some(("cancelled", "cancelled while queued".to_string())),
            )
            .await;
        }
        backend.cancels.cancel(id).await?;
        tracing::info!(job_id = %id, "cancellation requested");
        self.get(id).await
    }

    /// Remove a terminal job, its frames and its files. Queued or running: `Conflict`.
    pub async fn delete(&self, id: &str) -> Result<(), JobError> {
        let backend = &self.inner.backend;
        backend.store.delete(id).await?;
        backend.blobs.delete_job(id).await
    }

    /// Events of a job from `from_step` on: its current state, the stored frames (replay),
    /// then live frames, ending with `Done`. A watcher that falls behind the live channel
    /// resumes from the store, so it sees every step once and in order, and never slows the
    /// worker down.
    pub async fn watch(
        &self,
        id: &str,
        from_step: usize,
    ) -> Result<impl Stream<Item = JobEvent> + Send + 'static, JobError> {
        watch::watch(self.clone(), id.to_string(), from_step).await
    }

    /// Metrics of steps `from_step..` (at most `page_size`, 0 = 100, max 10 000) and the step
    /// to ask for next, if any.
    pub async fn frames(
        &self,
        id: &str,
        from_step: usize,
        page_size: usize,
    ) -> Result<(Vec<StepMetrics>, Option<usize>), JobError> {
        let size = match page_size {
            0 => 100,
            n => n.min(10_000),
        };
        let store = &self.inner.backend.store;
        store.status(id).await?;
        let rows = store.frame_rows(id, from_step, size + 1).await?;
        let mut metrics: Vec<StepMetrics> = rows.into_iter().map(|(m, _)| m).collect();
        let next = if metrics.len() > size {
            metrics.truncate(size);
            metrics.last().map(|m| m.step + 1)
        } else {
            None
        };
        Ok((metrics, next))
    }

    /// The mesh after `step` in `format`, for steps that kept positions.
    pub async fn frame_mesh(
        &self,
        id: &str,
        step: usize,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let status = self.get(id).await?;
        let kept = if step <= status.step {
            let rows = self.inner.backend.store.frame_rows(id, step, 1).await?;
            rows.first().is_some_and(|(m, p)| m.step == step && *p)
        } else {
            false
        };
        let key = BlobKey::Frame {
            id: id.to_string(),
            step,
            welded: true,
        };
        let bytes = if kept {
            self.inner.backend.blobs.get(key).await?
        } else {
            None
        };
        let Some(bytes) = bytes else {
            let detail = if step > status.step
                || (step == status.step && !status.state.is_terminal() && status.latest.is_none())
            {
                format!(
                    "the job has completed {} of {} steps",
                    status.step, status.total_steps
                )
            } else if !status.spec.include_positions {
                "the job was submitted with include_positions=false".to_string()
            } else {
                format!(
                    "positions are kept at step 0, every {} steps and the last step",
                    status.spec.frame_interval
                )
            };
            return Err(JobError::FrameNotFound {
                id: id.to_string(),
                step,
                detail,
            });
        };
        self.render(&status, codec::bytes_to_f64s(&bytes)?, format)
            .await
    }

    /// The faired mesh in `format` (input UVs, materials and textures kept). `Conflict` until
    /// the job succeeded.
    pub async fn result(&self, id: &str, format: Format) -> Result<Vec<u8>, JobError> {
        let status = self.get(id).await?;
        if status.state != JobState::Succeeded {
            return Err(JobError::Conflict(format!(
                "job `{id}` is {}: only a succeeded job has a result",
                status.state.as_str()
            )));
        }
        let key = BlobKey::Result { id: id.to_string() };
        let bytes =
            self.inner.backend.blobs.get(key).await?.ok_or_else(|| {
                JobError::Internal(format!("the result of job `{id}` is missing"))
            })?;
        self.render(&status, codec::bytes_to_f64s(&bytes)?, format)
            .await
    }

    /// Write `positions` (welded, f64) over the job's input asset in `format`.
    async fn render(
        &self,
        status: &JobStatus,
        positions: Vec<[f64; 3]>,
        format: Format,
    ) -> Result<Vec<u8>, JobError> {
        let key = BlobKey::Input {
            id: status.id.clone(),
            format: status.input_format,
        };
        let input = self.inner.backend.blobs.get(key).await?.ok_or_else(|| {
            JobError::Internal(format!("the input of job `{}` is missing", status.id))
        })?;
        let (input_format, limits) = (status.input_format, self.inner.config.limits.mesh_limits());
        tokio::task::spawn_blocking(move || {
            let asset =
                Asset::read(&input, input_format, &limits).map_err(JobError::InvalidMesh)?;
            asset
                .write(&positions, format)
                .map_err(|e| JobError::Internal(format!("writing {}: {e}", format_name(format))))
        })
        .await
        .map_err(join_err)?
    }

    /// Wait until the job is terminal or `timeout` passed; returns the status either way.
    pub async fn wait(
        &self,
        id: &str,
        timeout: std::time::Duration,
    ) -> Result<JobStatus, JobError> {
        use futures::StreamExt;
        let status = self.get(id).await?;
        if status.state.is_terminal() {
            return Ok(status);
        }
        let mut events = Box::pin(self.watch(id, usize::MAX).await?);
        let waited = tokio::time::timeout(timeout, async {
            while let Some(ev) = events.next().await {
                if let JobEvent::Done(s) = ev {
                    return Some(s);
                }
            }
            None
        })
        .await;
        match waited {
            Ok(Some(s)) => Ok(s),
            _ => self.get(id).await,
        }
    }

    /// Stop admitting jobs: `submit` answers `ShuttingDown` and readiness turns false. Running
    /// and queued jobs go on until [`Shutdown::shutdown`].
    pub fn begin_drain(&self) {
        if !self.inner.draining.swap(true, Ordering::SeqCst) {
            tracing::info!("draining: no new jobs are admitted");
        }
        self.inner.drain_signal.cancel();
    }

    /// Resolves once draining has begun: the hook for a transport that must announce it
    /// (gRPC health flips to NOT_SERVING), e.g. `tokio::spawn(async move { jobs.drained().await; … })`.
    pub async fn drained(&self) {
        self.inner.drain_signal.cancelled().await
    }

    pub fn is_draining(&self) -> bool {
        self.inner.draining.load(Ordering::SeqCst)
    }

    /// Ready to take traffic: not draining, the backend reachable, every worker loop alive,
    /// and, when a job is running, a step finished within `stall_after`.
    pub fn is_ready(&self) -> bool {
        let inner = &self.inner;
        if inner.draining.load(Ordering::SeqCst) || !inner.backend.queue.connected() {
            return false;
        }
        let workers = if inner.config.role.runs_workers() {
            inner.config.workers
        } else {
            0
        };
        if inner.workers_alive.load(Ordering::SeqCst) < workers {
            return false;
        }
        let idle = inner.running.load(Ordering::SeqCst) == 0;
        let since = now_ms().saturating_sub(inner.last_progress_ms.load(Ordering::SeqCst));
        idle || since <= inner.config.stall_after.as_millis() as u64
    }

    /// Whether the backend's server is reachable (always, embedded).
    pub fn backend_connected(&self) -> bool {
        self.inner.backend.queue.connected()
    }

    /// Jobs waiting in the queue now (a cluster's count may lag by a moment).
    pub fn queue_depth(&self) -> usize {
        self.inner.backend.queue.depth()
    }

    /// Jobs running now on this node.
    pub fn running(&self) -> usize {
        self.inner.running.load(Ordering::SeqCst)
    }

    /// The Prometheus text exposition of the core's metrics.
    pub fn metrics_text(&self) -> String {
        self.inner
            .telemetry
            .queue_depth
            .set(self.inner.backend.queue.depth() as i64);
        self.inner
            .telemetry
            .running
            .set(self.inner.running.load(Ordering::SeqCst) as i64);
        self.inner.telemetry.render()
    }

    async fn sweep_loop(self, stop: CancellationToken) {
        let period = self.inner.config.sweep_interval;
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = tokio::time::sleep(period) => {}
            }
            match self.sweep().await {
                Ok(n) if n > 0 => tracing::info!(count = n, "expired jobs swept"),
                Err(e) => tracing::warn!(error = %e, "expiry sweep failed"),
                _ => {}
            }
        }
    }

    async fn sweep(&self) -> Result<usize, JobError> {
        let backend = &self.inner.backend;
        let swept = backend.store.sweep_expired(now_ms()).await?;
        for id in &swept.jobs {
            backend.blobs.delete_job(id).await?;
        }
        for (id, format) in swept.uploads {
            backend.blobs.delete(BlobKey::Upload { id, format }).await?;
        }
        Ok(swept.jobs.len())
    }
}

impl Shutdown {
    /// Graceful shutdown: stop admitting, let running jobs finish for up to `grace`, then stop
    /// them at their next step, checkpoint them and re-queue them (they resume on the next
    /// start, or on another worker). Queued jobs simply stay queued in the store.
    pub async fn shutdown(self, grace: Duration) {
        self.jobs.begin_drain();
        // Workers take no new job from now on; the ones running keep going.
        self.stop_polling.cancel();
        if tokio::time::timeout(grace, self.tracker.wait())
            .await
            .is_err()
        {
            tracing::warn!(
                grace_secs = grace.as_secs_f64(),
                "jobs still running after the grace period: stopping them at the next step, they will be re-queued"
            );
            self.jobs.inner.shutdown.cancel();
            self.tracker.wait().await;
        }
        tracing::info!("job core stopped");
    }

    /// The handle the shutdown belongs to.
    pub fn jobs(&self) -> &Jobs {
        &self.jobs
    }
}

impl Drop for Shutdown {
    fn drop(&mut self) {
        // Without a graceful shutdown, running jobs must still stop at their next step so the
        // process can exit; they are re-queued (in the store) when they stop or on restart.
        self.stop_polling.cancel();
        self.jobs.inner.shutdown.cancel();
    }
}

/// A mesh refused for its size is a `TooLarge` (HTTP 413), any other refusal an `InvalidMesh`.
pub(crate) fn mesh_error(e: MeshError) -> JobError {
    match e {
        MeshError::TooLarge { what, limit, .. } => JobError::TooLarge {
            what,
            limit: limit as u64,
        },
        other => JobError::InvalidMesh(other),
    }
}

pub(crate) fn join_err(e: tokio::task::JoinError) -> JobError {
    JobError::Internal(format!("blocking task failed: {e}"))
}

pub(crate) fn poisoned<T>(_: std::sync::PoisonError<T>) -> JobError {
    JobError::Internal("a lock was poisoned by a panicking thread".into())
}
