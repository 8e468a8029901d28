//! The job core's vocabulary: what a job asks for ([`JobSpec`], in `job_spec.rs`), where it is
//! ([`JobState`], [`JobStatus`]), what watchers get ([`Frame`], [`JobEvent`]), what can go
//! wrong ([`JobError`](super::JobError)) and how the core runs ([`Config`], [`JobLimits`], [`Role`]). Plain data: no
//! transport, no backend.

use super::error::FailureCode;
use super::ids::JobId;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use willow::mesh::io::Format;
use willow::mesh::Limits;
use willow::metrics::StepMetrics;

pub use super::job_spec::JobSpec;

pub use willow::flow::MAX_ITERATIONS;

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

/// Who is asking: every job, upload, idempotency key and operation belongs to one tenant, and a
/// caller sees only its own tenant's. The api layer's authentication makes it (an API key or a
/// JWT names the tenant); with `--auth none` every caller is [`Caller::anonymous`].
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Caller {
    /// The tenant: 1–64 of `A-Z a-z 0-9 . _ -` (it names NATS subjects and keys).
    pub tenant: String,
    /// The key's name or the token's subject, for audit lines; never a secret.
    pub subject: String,
}

/// The tenant of [`Caller::anonymous`].
pub const DEFAULT_TENANT: &str = "default";

impl Caller {
    /// A caller of `tenant`; `Err` names what is wrong with the tenant id.
    pub fn new(tenant: &str, subject: &str) -> Result<Caller, String> {
        if !valid_tenant(tenant) {
            return Err(format!(
                "tenant id must be 1-64 characters of A-Z a-z 0-9 . _ -, got {:?}",
                tenant.chars().take(80).collect::<String>()
            ));
        }
        Ok(Caller {
            tenant: tenant.to_string(),
            subject: subject.chars().take(128).collect(),
        })
    }

    /// Everyone, when authentication is off (`--auth none`, loopback only).
    pub fn anonymous() -> Caller {
        Caller {
            tenant: DEFAULT_TENANT.to_string(),
            subject: "anonymous".to_string(),
        }
    }
}

/// Whether `t` may name a tenant.
pub fn valid_tenant(t: &str) -> bool {
    (1..=64).contains(&t.len())
        && t.bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// A snapshot of one job, as every transport reports it. Times are unix milliseconds.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: JobId,
    /// The tenant that owns the job ([`Caller::tenant`]); records from before tenants belong
    /// to [`DEFAULT_TENANT`].
    #[serde(default = "default_tenant")]
    pub tenant: String,
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
    /// Size of the uploaded file: counted against its tenant's storage quota.
    #[serde(default)]
    pub input_bytes: u64,
    /// What the job may store besides its input (kept frames, checkpoint, result, a metrics
    /// row per step: [`super::stored`]), counted against its tenant's storage quota from
    /// submission; brought down to what it kept when it stops early, to 0 when it ends
    /// without starting. 0 in records from before it.
    #[serde(default)]
    pub planned_bytes: u64,
    /// Metrics of the latest completed step (step 0 = the input) once the job has started.
    pub latest: Option<StepMetrics>,
    /// Why the job failed or was cancelled, for people; on a succeeded job, why it stopped
    /// before `total_steps` (see [`JobStatus::outcome`]).
    pub error: Option<String>,
    /// The same, for programs: `deadline_exceeded`, `cancelled`, `numerical`, `invalid_mesh`,
    /// `unsupported`, `invalid_parameter`, `internal`; and on a **succeeded** job that stopped
    /// before `total_steps` the outcome of its run: `converged`, `target_reached`,
    /// `max_deviation`, or `no_progress` (the safeguard found no acceptable step, even at
    /// τ/1024). Its result is then the surface after step `step`.
    /// Stored as text, so a code this version does not know still reads;
    /// [`JobStatus::failure`] is the typed view.
    pub error_code: Option<String>,
    pub created_at: u64,
    pub started_at: Option<u64>,
    pub finished_at: Option<u64>,
    /// When a finished job's results are deleted (then every call answers [`JobError::Gone`](super::JobError::Gone)).
    pub expires_at: Option<u64>,
    /// What `repair` changed in the upload, in the file's numbering (`None` when nothing
    /// was repaired, or without `repair`). Stored with the job, so every read reports it; records from before it was
    /// stored read as `None`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repairs: Option<willow::mesh::io::Repairs>,
    /// What the result cannot keep of the upload as it was, for people
    /// ([`willow::mesh::io::Asset::notes`]: e.g. a compressed glTF written back as plain
    /// floats, morph targets dropped). Stored with the job; empty for older records.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

impl JobStatus {
    /// How a succeeded job's run ended, by the name of [`willow::flow::stopping::Outcome`]
    /// (`completed`, `converged`, `target_reached`, `max_deviation`, `no_progress`, …), and
    /// why, for people. A run that ended before its steps keeps the two as its note
    /// (`error_code`, `error`); one that ran them all has none. A method with an end of its
    /// own (`denoise`: its filtering settled) completes before its steps, with no note either.
    /// `None` unless succeeded.
    pub fn outcome(&self) -> Option<(String, String)> {
        let completed = || {
            if self.step < self.total_steps {
                format!(
                    "the method ended on its own after {} of its {} steps",
                    self.step, self.total_steps
                )
            } else {
                format!("ran its {} steps", self.total_steps)
            }
        };
        (self.state == JobState::Succeeded).then(|| match &self.error_code {
            Some(code) => (code.clone(), self.error.clone().unwrap_or_default()),
            None => (
                willow::flow::stopping::Outcome::Completed
                    .name()
                    .to_string(),
                completed(),
            ),
        })
    }

    /// Progress in percent: `step / total_steps × 100`, and 100 once succeeded (a run that
    /// converged early ends before its last step).
    pub fn percent_complete(&self) -> f64 {
        if self.state == JobState::Succeeded {
            return 100.0;
        }
        if self.total_steps == 0 {
            return 0.0;
        }
        (self.step as f64 / self.total_steps as f64 * 100.0).clamp(0.0, 100.0)
    }

    /// The typed view of [`JobStatus::error_code`]: `None` when there is none, or when it is a
    /// code this version does not know.
    pub fn failure(&self) -> Option<FailureCode> {
        self.error_code.as_deref().and_then(FailureCode::parse)
    }
}

fn default_tenant() -> String {
    DEFAULT_TENANT.to_string()
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
    pub positions: Option<Arc<FramePositions>>,
    /// Step 0 of a job with `refine` or `fill_holes`: the mesh is not the upload (its faces
    /// from `GET /v1/jobs/{id}/frames/0`; its vertices the file's own, then the new ones). Set
    /// by the watcher ([`Jobs::watch`](super::Jobs::watch)) from the job's spec.
    pub connectivity_changed: bool,
}

/// A frame's vertex positions: f32 offsets from an f64 origin, so a model far from the
/// origin (map-grid coordinates) streams with ~1e-7 of its size instead of snapping to the
/// f32 grid of its distance (issue 27, item 4). The origin is the job's
/// [`willow::mesh::io::Asset::frame_origin`]: the same in every frame of a job, and exactly
/// zero for a model around the origin, where `relative` are the coordinates themselves.
#[derive(Clone, Debug, PartialEq)]
pub struct FramePositions {
    pub origin: [f64; 3],
    pub relative: Vec<[f32; 3]>,
}

impl FramePositions {
    /// Is the origin zero (then clients that ignore it read the frame right)?
    pub fn at_zero(&self) -> bool {
        self.origin == [0.0; 3]
    }

    /// The positions in f64: origin + offset.
    pub fn absolute(&self) -> Vec<[f64; 3]> {
        self.relative
            .iter()
            .map(|p| [0, 1, 2].map(|k| self.origin[k] + f64::from(p[k])))
            .collect()
    }
}

/// What a watcher sees: state changes, one frame per step, then the final status.
#[derive(Clone, Debug)]
pub enum JobEvent {
    State(JobStatus),
    Frame(Frame),
    Done(JobStatus),
}

/// The mesh a job runs on: the bytes themselves, or an upload stored earlier by
/// [`Jobs::store_upload`](super::Jobs::store_upload) (chunked gRPC uploads).
pub enum UploadRef {
    Bytes { data: bytes::Bytes, format: Format },
    Stored { upload_id: String },
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
    /// Most points of a curve sent to [`Jobs::fair_curve`](super::Jobs::fair_curve).
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
    /// Separate from the job workers, whose jobs may hold them for hours; see
    /// [`curve`](super::curve).
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
    /// What one tenant may hold at once.
    pub quotas: TenantQuotas,
    /// Callbacks may use `http` and reach loopback, private and link-local addresses (tests
    /// and closed networks only: otherwise a client could make the server probe its own
    /// network).
    pub allow_insecure_callbacks: bool,
    /// The server's webhook secret; each tenant signs with HMAC-SHA256(secret, tenant)
    /// ([`super::webhooks::tenant_key`]). `None`: a random secret per process, so signatures
    /// cannot be checked across a restart — set one in production.
    pub webhook_secret: Option<Vec<u8>>,
    /// Tries of one callback before it is given up (the first, then retries after 1 s, 2 s,
    /// 4 s, … capped at [`super::webhooks::MAX_BACKOFF`]).
    pub webhook_max_attempts: u32,
}

/// Per-tenant quotas: each refusal names its quota (`QuotaExceeded`, 429 /
/// RESOURCE_EXHAUSTED). The same for every tenant; 0 turns a quota off.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TenantQuotas {
    /// Queued plus running jobs.
    pub max_live_jobs: usize,
    /// Bytes kept: stored uploads, and unexpired jobs' inputs, what they may store besides
    /// ([`super::stored`]: kept frames, checkpoint, result, metrics) and stored renderings.
    pub max_stored_bytes: u64,
    /// Meshes received (job submissions and stored uploads) in any 60 s.
    pub uploads_per_minute: usize,
    /// Not per tenant: the server's disk budget, every tenant's stored bytes together (as
    /// `max_stored_bytes` counts them). Past it every tenant is refused with 507
    /// `quota_exceeded`, quota `server_stored_bytes`, so one tenant within its own quota
    /// cannot fill the disk the others share. 0: no budget.
    pub server_max_stored_bytes: u64,
}

impl Default for TenantQuotas {
    fn default() -> Self {
        TenantQuotas {
            // Off: the operator knows the disk (`--disk-budget-mib`).
            server_max_stored_bytes: 0,
            // Half the default queue: one tenant's burst leaves room for the others (the
            // queue's fair order does the rest).
            max_live_jobs: 32,
            // Sixteen uploads at the 64 MiB limit.
            max_stored_bytes: 1 << 30,
            // Two a second on average: far more than people upload, and bounded for scripts.
            uploads_per_minute: 120,
        }
    }
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
            // A checkpoint is one blob of 24 bytes per vertex: ~10 ms (fsync'ed file or object
            // store) for a 100k-triangle mesh whose step takes ~1 s, i.e. 1% of a step, 0.1%
            // at one checkpoint in ten steps; ten steps or half a minute lose little on a
            // crash (`cargo bench --bench service_load`, part 5, measures it).
            checkpoint_steps: 10,
            checkpoint_interval: Duration::from_secs(30),
            heartbeat_interval: Duration::from_secs(5),
            max_deliveries: 3,
            quotas: TenantQuotas::default(),
            allow_insecure_callbacks: false,
            webhook_secret: None,
            // 1 + 2 + … + 256 s plus the cap: about an hour of a receiver being down.
            webhook_max_attempts: 12,
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

/// The lower-case name of a mesh format, as stored and as in `?format=`: its usual extension.
pub fn format_name(f: Format) -> &'static str {
    f.extension()
}

/// The inverse of [`format_name`] (case-insensitive).
pub fn parse_format(s: &str) -> Option<Format> {
    Format::from_extension(s)
}

/// The media type of a mesh format (for downloads): the registered one where there is one
/// (`model/stl`), `model/x-ply` and `model/x-off` for the unregistered PLY and OFF.
pub fn format_media_type(f: Format) -> &'static str {
    f.mime()
}
