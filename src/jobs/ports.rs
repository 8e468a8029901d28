//! The seams of the job core: five ports, and nothing else the core needs from a backend.
//!
//! Admission, the worker and the watchers ([`super::Jobs`], [`super::worker`],
//! [`super::watch`]) are written once against these traits. Two backends implement them:
//! - [`super::embedded`] (the default): SQLite for records, files for blobs, an in-process
//!   queue and broadcast channels, one process;
//! - [`super::nats`]: a JetStream work queue, KV records, the Object Store and per-job frame
//!   subjects, for many API and worker nodes on one NATS.
//!
//! The traits are async and object-safe (`async_trait`), so a backend is chosen at start-up and
//! the core holds `Arc<dyn …>`. A backend that blocks (SQLite, files) does so on tokio's
//! blocking pool inside its own methods; callers never need to know.
//!
//! What each port promises is written on it. The ones the core relies on for correctness:
//! - every frame is in the [`JobStore`] (and its positions in the [`BlobStore`]) before it is
//!   published on the [`EventBus`], so a watcher that subscribes first and then replays misses
//!   nothing;
//! - [`JobStore::start`] refuses a terminal job, so a job cancelled while its queue entry was
//!   in flight is not run;
//! - a [`Lease`] that is neither acked nor heartbeaten is delivered again (NATS: after
//!   `ack_wait`; embedded: on the next start of the process).

use super::{FailureCode, JobError, JobEvent, JobId, JobSpec, JobState, JobStatus, TenantQuotas};
use async_trait::async_trait;
use futures::stream::BoxStream;
use futures::StreamExt;
use tokio_util::sync::CancellationToken;
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

/// A job about to be admitted.
#[derive(Clone, Debug)]
pub struct NewJob {
    pub id: JobId,
    /// The owner: every read by a caller is scoped to it.
    pub tenant: String,
    pub spec: JobSpec,
    pub format: Format,
    pub vertex_count: usize,
    pub face_count: usize,
    /// What `repair` changed ([`JobStatus::repairs`](super::JobStatus::repairs)).
    pub repairs: Option<willow::mesh::io::Repairs>,
    /// What the result cannot keep ([`JobStatus::notes`](super::JobStatus::notes)).
    pub notes: Vec<String>,
    /// Size of the uploaded file (the tenant's storage quota counts it).
    pub input_bytes: u64,
    /// What the job may store besides its input ([`super::stored::planned_bytes`]): the
    /// quota counts it too, from the insert on.
    pub planned_bytes: u64,
    /// Whether the mesh came with this request. A job made from a stored upload receives no
    /// mesh: its upload was counted toward `uploads_per_minute` when it arrived, so the job
    /// neither counts there again nor is refused by that quota.
    pub received: bool,
    pub created_at: u64,
    /// The tenant's quotas: [`JobStore::insert`] refuses the job when its tenant's usage
    /// leaves no room ([`Inserted::OverQuota`]).
    pub quotas: TenantQuotas,
    /// (key, request hash), the key scoped to `tenant`: see [`super::codec::request_hash`].
    pub idempotency: Option<(String, String)>,
}

/// What [`JobStore::insert`] did.
#[derive(Debug)]
pub enum Inserted {
    /// The job is stored, queued.
    New(JobStatus),
    /// Its idempotency key already named this job (the same request sent again): nothing was
    /// stored, the caller answers with the existing job.
    Existing(JobStatus),
    /// Nothing was stored: the tenant's usage leaves no room under this quota.
    OverQuota(OverQuota),
}

/// Which quota a job or upload would break, and by how much.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OverQuota {
    /// `live_jobs`, `uploads_per_minute` or `stored_bytes`.
    pub quota: &'static str,
    pub limit: u64,
    pub used: u64,
}

/// What asks [`over_quota`] for room.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admitting {
    /// An upload stored for later jobs.
    Upload,
    /// A job; `received`: its mesh came with it ([`NewJob::received`]).
    Job { received: bool },
    /// A download rendered and about to be stored ([`JobStore::charge_rendered`]): only
    /// `stored_bytes` counts it.
    Rendered,
}

/// The quota `usage` plus what is `admitting` would break, if any: one more stored mesh of
/// `bytes`, one more mesh received in the minute (uploads, and jobs that bring their mesh)
/// and, for a job, one more live job. A limit of 0 is no limit.
pub fn over_quota(
    q: &TenantQuotas,
    usage: &Usage,
    bytes: u64,
    admitting: Admitting,
) -> Option<OverQuota> {
    let over = |quota, limit: u64, used: u64| Some(OverQuota { quota, limit, used });
    let (job, received) = match admitting {
        Admitting::Upload => (false, true),
        Admitting::Job { received } => (true, received),
        Admitting::Rendered => (false, false),
    };
    if job && q.max_live_jobs > 0 && usage.live_jobs >= q.max_live_jobs {
        return over("live_jobs", q.max_live_jobs as u64, usage.live_jobs as u64);
    }
    if received && q.uploads_per_minute > 0 && usage.uploads_last_minute >= q.uploads_per_minute {
        return over(
            "uploads_per_minute",
            q.uploads_per_minute as u64,
            usage.uploads_last_minute as u64,
        );
    }
    if q.max_stored_bytes > 0 && usage.stored_bytes.saturating_add(bytes) > q.max_stored_bytes {
        return over("stored_bytes", q.max_stored_bytes, usage.stored_bytes);
    }
    if q.server_max_stored_bytes > 0
        && usage.server_stored_bytes.saturating_add(bytes) > q.server_max_stored_bytes
    {
        return over(
            "server_stored_bytes",
            q.server_max_stored_bytes,
            usage.server_stored_bytes,
        );
    }
    None
}

impl TenantQuotas {
    /// Whether any quota is on (else usage need not be counted).
    pub fn any(&self) -> bool {
        self.max_live_jobs > 0
            || self.max_stored_bytes > 0
            || self.uploads_per_minute > 0
            || self.server_max_stored_bytes > 0
    }
}

/// Jobs and uploads that [`JobStore::sweep_expired`] retired: their blobs are the caller's to
/// delete.
#[derive(Debug, Default)]
pub struct Swept {
    pub jobs: Vec<JobId>,
    pub uploads: Vec<(String, Format)>,
}

/// What one tenant holds, for its quotas ([`super::TenantQuotas`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Usage {
    /// Queued and running jobs.
    pub live_jobs: usize,
    /// Bytes kept: inputs of unexpired jobs, unexpired uploads, and the downloads rendered
    /// and stored for unexpired jobs ([`JobStore::charge_rendered`]).
    pub stored_bytes: u64,
    /// Meshes received (uploads, and jobs that brought theirs) in the minute before the `now` of
    /// [`JobStore::usage`] (the SQLite store estimates the sliding minute from two fixed ones).
    pub uploads_last_minute: usize,
    /// Every tenant's `stored_bytes` together (for [`super::TenantQuotas::server_max_stored_bytes`];
    /// 0 when that is off, and not counted then).
    pub server_stored_bytes: u64,
}

/// A minute, in unix ms.
pub const MINUTE_MS: u64 = 60_000;

/// The meshes a tenant sent (uploads, and jobs that brought theirs), counted in fixed minutes: O(1) to keep and to
/// read, for the `uploads_per_minute` quota. [`MinuteWindows::last_minute`] is the usual
/// sliding-window estimate of rate limiters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct MinuteWindows {
    /// Start (unix ms, a whole minute) of the minute `current` counts.
    pub start: u64,
    pub current: u64,
    /// The count of the minute before `start`.
    pub previous: u64,
}

impl MinuteWindows {
    /// Count a mesh received at `at`: the windows move on to its minute (the current count
    /// becomes the previous one when the next minute starts; both reset after a quiet
    /// minute), and a mesh stamped in the previous minute but counted late counts there.
    pub fn receive(&mut self, at: u64) {
        let minute = at - at % MINUTE_MS;
        if minute == self.start {
            self.current += 1;
        } else if minute + MINUTE_MS == self.start {
            self.previous += 1;
        } else if minute > self.start {
            self.previous = if minute == self.start + MINUTE_MS {
                self.current
            } else {
                0
            };
            self.current = 1;
            self.start = minute;
        }
    }

    /// Meshes received in the minute before `now`: the part of the previous minute still
    /// inside the sliding one taken as evenly filled, rounded up so that a burst just before
    /// a minute boundary still counts in full right after it. Exact while all the counted
    /// meshes are in one fixed minute; otherwise off by less than the previous minute's count
    /// times the fraction of this minute elapsed.
    pub fn last_minute(&self, now: u64) -> usize {
        let this_minute = now - now % MINUTE_MS;
        let elapsed = (now - this_minute) as f64 / MINUTE_MS as f64;
        let weighted = |count: u64| (count as f64 * (1.0 - elapsed)).ceil() as u64;
        let count = if self.start > this_minute {
            // Windows ahead of `now` (the clock stepped back): all of it is recent.
            self.current + self.previous
        } else if self.start == this_minute {
            weighted(self.previous) + self.current
        } else if self.start + MINUTE_MS == this_minute {
            weighted(self.current)
        } else {
            0
        };
        usize::try_from(count).unwrap_or(usize::MAX)
    }
}

/// A job found queued or running at start ([`JobStore::recover`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Recovered {
    pub id: JobId,
    pub tenant: String,
    /// Deliveries so far (a job found running died with its process: that counts).
    pub delivered: u32,
}

/// Job records: state, spec, progress, per-step metrics, idempotency keys and upload records.
///
/// Tenancy is in the signatures: what a caller reaches (a status, a listing, an idempotency
/// key, an upload, a delete) takes the caller's tenant, and another tenant's job answers
/// exactly as an unknown one (`NotFound`, never `Gone` or `Conflict`). Calls without a tenant
/// (`status(id, None)`, `start`, `finish`, …) are the core's own, by job id.
#[async_trait]
pub trait JobStore: Send + Sync + 'static {
    /// Store an admitted job, queued, with its idempotency key, atomically: of two requests
    /// with one key (on any node), one inserts and the other gets [`Inserted::Existing`], or
    /// [`JobError::IdempotencyMismatch`] when its hash differs. A job its tenant's quotas have
    /// no room for is [`Inserted::OverQuota`] (a repeat with a known key is `Existing` first);
    /// where the backend has transactions the count and the insert are one, so concurrent
    /// submissions cannot overshoot (NATS: the count is a scan just before the insert, so
    /// concurrent submissions of one tenant may overshoot by their number).
    async fn insert(&self, job: NewJob) -> Result<Inserted, JobError>;
    /// The job `tenant`'s key created, when the key is known and bound to `hash`. Keys are
    /// per tenant: two tenants' equal keys are unrelated.
    async fn idempotent(
        &self,
        tenant: &str,
        key: &str,
        hash: &str,
    ) -> Result<Option<JobStatus>, JobError>;
    /// `NotFound` if unknown (or, with `Some(tenant)`, another tenant's), `Gone` once expired.
    async fn status(&self, id: &str, tenant: Option<&str>) -> Result<JobStatus, JobError>;
    /// `tenant`'s jobs, newest first; `token` is the opaque `next_page_token` of the previous
    /// page.
    async fn list(
        &self,
        tenant: &str,
        state: Option<JobState>,
        size: usize,
        token: Option<String>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError>;
    /// A worker takes the job under `fence`: queued → running, or running → running when it
    /// is delivered again after its worker died. [`Started::Gone`] when the job is terminal,
    /// deleted or unknown; [`Started::Held`] when another worker's fence holds it and has not
    /// lapsed (the job is not to be run: its holder is alive, or may be).
    async fn start(&self, id: &str, fence: &Fence, at: u64) -> Result<Started, JobError>;
    /// Keep `fence`'s hold on the running job (from the heartbeat). A hold that another
    /// worker took cancels [`Fence::lost`] and is [`JobError::Conflict`].
    async fn renew(&self, id: &str, fence: &Fence) -> Result<(), JobError>;
    /// A step's metrics; advances the job's progress to `metrics.step`. Refused (and
    /// [`Fence::lost`] cancelled) when `fence` no longer holds the job.
    async fn record_frame(
        &self,
        id: &str,
        metrics: StepMetrics,
        has_positions: bool,
        fence: &Fence,
    ) -> Result<(), JobError>;
    /// Forget the frames after `step` and set the progress back to it (a job resumed from its
    /// checkpoint at `step` takes the later steps again). Fenced as `record_frame`.
    async fn rewind(&self, id: &str, step: usize, fence: &Fence) -> Result<(), JobError>;
    /// Stored frames of steps `from..` in step order (at most `limit`), with whether each kept
    /// positions.
    async fn frame_rows(
        &self,
        id: &str,
        from: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError>;
    /// Move a queued or running job to a terminal state; `None` if it already was terminal.
    /// A worker passes its fence (refused, as `record_frame`, once the fence lost the job);
    /// `None` is the API's own transition (a job withdrawn from the queue).
    async fn finish(
        &self,
        id: &str,
        state: JobState,
        error: Option<(FailureCode, String)>,
        at: u64,
        expires_at: u64,
        fence: Option<&Fence>,
    ) -> Result<Option<JobStatus>, JobError>;
    /// A running job goes back to queued (shutdown) and its fence lets go; its frames and
    /// checkpoint stay. Nothing happens if `fence` no longer holds it. A hand-back in order
    /// starts the job's count of deliveries without progress afresh ([`JobStore::delivered`]).
    async fn requeue(&self, id: &str, fence: &Fence) -> Result<(), JobError>;
    /// The job's checkpoint now holds `step` (the worker under `fence` wrote it): progress
    /// that survives the worker, for [`JobStore::delivered`]. Fenced as `record_frame`.
    async fn checkpointed(&self, id: &str, step: usize, fence: &Fence) -> Result<(), JobError>;
    /// The running job (held by `fence`) stored at most `bytes` besides its input: its
    /// [`JobStatus::planned_bytes`](super::JobStatus::planned_bytes), and its tenant's
    /// `stored_bytes` with it, come down to that (never up: the plan is the bound the quota
    /// admitted). Called as a job that stopped before its last step ends.
    async fn settle_planned(&self, id: &str, bytes: u64, fence: &Fence) -> Result<(), JobError>;
    /// A delivery of the job to the worker under `fence` (just started): how many
    /// deliveries in a row, this one included, found no checkpoint newer than the delivery
    /// before them saw. 1 when the job is new, was handed back in order, or its last run got
    /// past a checkpoint; `n + 1` after `n` runs that each died (killed, out of memory, node
    /// lost) before writing a new checkpoint. `Config::max_deliveries` bounds it, so a job
    /// that keeps killing its workers fails `redelivered`, while one whose workers die after
    /// progress goes on (issue 25 item 4).
    async fn delivered(&self, id: &str, fence: &Fence) -> Result<u32, JobError>;
    /// Count `bytes` of a download of job `id`, rendered and about to be stored as `name`
    /// ([`BlobKey::Rendered`]), in its tenant's `stored_bytes`, unless `quotas` leave no room
    /// for them: then nothing is counted and the quota is named (the caller serves the
    /// rendering from memory without storing it). A name counted already is not counted
    /// again (two nodes rendering one download store one blob). `Gone`/`NotFound` when the
    /// job is retired or unknown. The count goes when the job is deleted or expires, with
    /// its blobs.
    async fn charge_rendered(
        &self,
        id: &str,
        name: &str,
        bytes: u64,
        quotas: &TenantQuotas,
    ) -> Result<Option<OverQuota>, JobError>;
    /// Take back [`JobStore::charge_rendered`]'s count of `name`, whose blob could not be
    /// stored.
    async fn refund_rendered(&self, id: &str, name: &str) -> Result<(), JobError>;
    /// Remove `tenant`'s terminal (or expired) job's record and frames; `Conflict` if it is
    /// live. Its blobs are the caller's to delete.
    async fn delete(&self, tenant: &str, id: &str) -> Result<(), JobError>;
    /// Retire jobs and uploads past their expiry (jobs keep a tombstone, so they answer
    /// `Gone`).
    async fn sweep_expired(&self, now: u64) -> Result<Swept, JobError>;
    /// After a restart: the jobs a durable queue does not hold, in queue order, for the core
    /// to queue again (the embedded backend: queued and running jobs; NATS: none).
    async fn recover(&self) -> Result<Vec<Recovered>, JobError>;
    /// Record `tenant`'s upload stored ahead of its job (chunked gRPC).
    async fn put_upload(
        &self,
        tenant: &str,
        id: &str,
        format: Format,
        size: u64,
        expires_at: u64,
    ) -> Result<(), JobError>;
    /// `tenant`'s upload's format; `UploadNotFound` if unknown, expired or another tenant's.
    async fn upload(&self, tenant: &str, id: &str) -> Result<Format, JobError>;
    /// What `tenant` holds at `now` (unix ms), with the meshes it sent in the minute before.
    async fn usage(&self, tenant: &str, now: u64) -> Result<Usage, JobError>;
    /// Every tenant's stored bytes together (the server's disk budget,
    /// [`super::TenantQuotas::server_max_stored_bytes`]).
    async fn server_stored_bytes(&self) -> Result<u64, JobError>;
    /// Terminal, unexpired jobs whose `callback_url` has not been settled, oldest first (at
    /// most `limit`): what [`super::webhooks`] still has to deliver. Kept in the record, so a
    /// restart (or another node) finds them again.
    async fn pending_callbacks(&self, limit: usize) -> Result<Vec<JobStatus>, JobError>;
    /// The job's callback is delivered (or given up): it is pending no more.
    async fn settle_callback(&self, id: &str) -> Result<(), JobError>;
}

/// What [`JobStore::start`] found.
#[derive(Debug)]
pub enum Started {
    /// The job is the caller's to run, under its fence.
    Run(Box<JobStatus>),
    /// Terminal, deleted or unknown: nothing to run (ack the delivery).
    Gone,
    /// Another worker's fence holds the job and has not lapsed: do not run it.
    Held,
}

/// A worker's hold on the job it runs, kept in the job's record by backends whose queue can
/// hand one job to two workers (NATS: a message delivered again after a missed heartbeat,
/// or after a server restart, while its first worker still runs it). Every write of the
/// worker to the record checks the token, so a worker that lost the job is refused before it
/// writes anything more; a hold not renewed for `ttl` (the worker died) may be taken over.
/// The embedded backend, whose queue never hands out a running job, ignores it.
#[derive(Clone, Debug)]
pub struct Fence {
    /// Unique for one run of one delivery.
    pub token: String,
    /// How long the hold lasts without a renewal.
    pub ttl: std::time::Duration,
    /// Cancelled when the store finds the job held by another fence (or finished by another
    /// worker): the run stops, and writes, acks and releases nothing more.
    pub lost: CancellationToken,
    /// When (unix ms, taken before the write) the store last confirmed the hold.
    renewed_at: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl Fence {
    pub fn new(ttl: std::time::Duration) -> Fence {
        Fence {
            token: uuid::Uuid::new_v4().simple().to_string(),
            ttl,
            lost: CancellationToken::new(),
            renewed_at: Default::default(),
        }
    }

    /// The store confirmed the hold with a write that began at `at` (unix ms).
    pub fn renewed(&self, at: u64) {
        self.renewed_at
            .fetch_max(at, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether the hold may have lapsed by `now` for all this worker knows: no confirmation
    /// for half its length (frozen, or cut off). A worker checks with the store (`renew`)
    /// before it writes more, so that one whose job was taken over meanwhile writes nothing.
    pub fn stale(&self, now: u64) -> bool {
        let half = u64::try_from(self.ttl.as_millis() / 2).unwrap_or(u64::MAX);
        now.saturating_sub(self.renewed_at.load(std::sync::atomic::Ordering::Relaxed)) > half
    }

    /// The error of a write this fence may no longer make (and marks it lost).
    pub fn lost_error(&self, id: &str) -> JobError {
        self.lost.cancel();
        JobError::Conflict(format!(
            "job `{id}` is no longer held by this worker (another took it over, or it finished)"
        ))
    }
}

/// What a blob holds; the backend names it (file path, object name).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BlobKey {
    /// The uploaded file as received.
    Input { id: JobId, format: Format },
    /// A step's positions: in the file's vertex order as f32 (`welded: false`, what watchers
    /// get), or welded as f64 (`welded: true`, to write the frame's mesh).
    Frame {
        id: JobId,
        step: usize,
        welded: bool,
    },
    /// The final welded positions, f64.
    Result { id: JobId },
    /// The flow's latest checkpoint ([`super::codec::encode_checkpoint`]).
    Checkpoint { id: JobId },
    /// An upload stored ahead of its job.
    Upload { id: String, format: Format },
    /// A mesh download rendered once and kept, so that it is streamed from storage (a slow
    /// reader then pins a chunk, not the whole file) and a repeat download renders nothing:
    /// the result (`step: None`) or a kept frame, in `format`.
    ///
    /// `source` is the [`BlobStore::version`] of the positions it was rendered from (a
    /// frame's welded positions), so a step that a resumed job writes again is rendered
    /// again instead of being served stale; `None` for the result, which is written once,
    /// when its job succeeds. A [`rendered_source`] token: safe in a file or object name.
    Rendered {
        id: JobId,
        step: Option<usize>,
        format: Format,
        source: Option<String>,
    },
}

/// `version` as a token for a rendered blob's name ([`BlobKey::Rendered::source`]): its
/// ASCII letters, digits, `-` and `_`, at most 64 of them (a version from a backend is one of
/// these already: hex, or a base64url digest without its padding).
pub fn rendered_source(version: &str) -> String {
    version
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_'))
        .take(64)
        .collect()
}

/// The file or object name of a rendered blob inside its job's `rendered/` folder:
/// `result.{ext}`, `{step}.{ext}`, or `{step}-{source}.{ext}`.
pub fn rendered_name(step: Option<usize>, format: Format, source: Option<&str>) -> String {
    let ext = super::format_name(format);
    match (step, source) {
        (None, _) => format!("result.{ext}"),
        (Some(s), None) => format!("{s}.{ext}"),
        (Some(s), Some(v)) => format!("{s}-{}.{ext}", rendered_source(v)),
    }
}

/// A blob read in pieces ([`BlobStore::open`]): its length, then its bytes in order, a chunk
/// at a time, each read from storage only when the one before it was taken.
pub struct BlobReader {
    pub len: u64,
    pub chunks: BoxStream<'static, Result<bytes::Bytes, JobError>>,
}

impl BlobReader {
    /// A blob already in memory, as one chunk.
    pub fn whole(data: bytes::Bytes) -> BlobReader {
        BlobReader {
            len: data.len() as u64,
            chunks: futures::stream::once(async move { Ok(data) }).boxed(),
        }
    }
}

impl BlobKey {
    /// Whether losing the blob in a power cut would lose accepted work (inputs, results,
    /// checkpoints, uploads), as opposed to what a resumed job writes again (frames).
    pub fn durable(&self) -> bool {
        !matches!(self, BlobKey::Frame { .. } | BlobKey::Rendered { .. })
    }

    /// The job the blob belongs to, if any.
    pub fn job(&self) -> Option<&str> {
        match self {
            BlobKey::Input { id, .. }
            | BlobKey::Frame { id, .. }
            | BlobKey::Result { id }
            | BlobKey::Checkpoint { id }
            | BlobKey::Rendered { id, .. } => Some(id),
            BlobKey::Upload { .. } => None,
        }
    }
}

/// Mesh files, frame positions, results and checkpoints.
#[async_trait]
pub trait BlobStore: Send + Sync + 'static {
    /// Write atomically: a reader sees the old blob or the whole new one.
    async fn put(&self, key: BlobKey, data: bytes::Bytes) -> Result<(), JobError>;
    /// `None` when there is no such blob.
    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError>;
    /// The blob to read in chunks, `None` when there is no such blob. A backend that can read
    /// part of a blob overrides this so that what a reader holds is a chunk; this default
    /// reads it whole.
    async fn open(&self, key: BlobKey) -> Result<Option<BlobReader>, JobError> {
        Ok(self.get(key).await?.map(BlobReader::whole))
    }
    /// What identifies the blob's current content, `None` when there is no such blob: it
    /// changes when the blob is written again with other bytes (the embedded backend: the
    /// file's inode, modification time and length, a `stat`; NATS: the object's SHA-256
    /// digest, from its info). Renderings are named after the version of their source
    /// ([`BlobKey::Rendered::source`]). This default reads the blob and hashes it.
    async fn version(&self, key: BlobKey) -> Result<Option<String>, JobError> {
        use sha2::Digest;
        Ok(self.get(key).await?.map(|b| {
            let d = sha2::Sha256::digest(&b);
            d[..16].iter().map(|x| format!("{x:02x}")).collect()
        }))
    }
    async fn delete(&self, key: BlobKey) -> Result<(), JobError>;
    /// Every blob of a job.
    async fn delete_job(&self, id: &str) -> Result<(), JobError>;
    /// Whether the store has room for writes again, asked while storage is known full:
    /// `None` when the store cannot tell (the embedded backend probes its data dir itself).
    async fn room(&self) -> Option<bool> {
        None
    }
    /// Remove what failed writes left behind that no blob names (called with the expiry
    /// sweep; the store decides how often it looks); how many such sets were removed.
    async fn sweep_orphans(&self) -> Result<usize, JobError> {
        Ok(0)
    }
}

/// A job handed to one worker until it acks, releases, or stops heartbeating.
pub struct Lease {
    /// The job's id as the queue carried it: checked when the worker looks the job up.
    pub id: String,
    /// How many times the job has been delivered, this time included (1 = first time).
    pub attempt: u32,
    pub control: std::sync::Arc<dyn LeaseControl>,
}

/// What a worker tells the queue about its lease.
#[async_trait]
pub trait LeaseControl: Send + Sync {
    /// Still working: do not give the job to another worker yet.
    async fn heartbeat(&self) -> Result<(), JobError>;
    /// The job is terminal: remove it from the queue.
    async fn ack(&self) -> Result<(), JobError>;
    /// Give the job back now, for another worker or a later start (shutdown).
    async fn release(&self) -> Result<(), JobError>;
}

/// The admission queue: bounded, with leases, fair between tenants.
#[async_trait]
pub trait WorkQueue: Send + Sync + 'static {
    /// Append `tenant`'s admitted job; `QueueFull` at capacity (cluster-wide where the backend
    /// is).
    async fn push(&self, tenant: &str, id: &str) -> Result<(), JobError>;
    /// Append regardless of capacity: jobs recovered at start were admitted before. Its next
    /// lease is attempt `delivered + 1`.
    async fn push_recovered(&self, job: Recovered) -> Result<(), JobError>;
    /// Wait for the next job. Tenants take turns: the next lease goes to the waiting tenant
    /// served least recently, so one tenant's burst delays another's job by at most one job
    /// per worker, not by the whole burst.
    async fn lease(&self) -> Result<Lease, JobError>;
    /// Take a waiting job out; `false` if no worker can be kept from it any more (it was
    /// leased, or never queued). A `true` may still race a delivery in flight: the worker
    /// then finds the job terminal at [`JobStore::start`].
    async fn withdraw(&self, id: &str) -> Result<bool, JobError>;
    /// Jobs waiting (a cluster's count may lag by a moment).
    fn depth(&self) -> usize;
    fn capacity(&self) -> usize;
    /// Whether the queue's server is reachable (always, for the embedded queue).
    fn connected(&self) -> bool {
        true
    }
}

/// One item of a job's live event subscription.
// `Lagged` is rare and carries nothing; boxing every event to shrink it would cost an
// allocation per frame per watcher.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum BusEvent {
    /// An event. A frame's positions may be left out (`Frame::positions` is `None` while
    /// `has_positions` is true); the watcher then reads them from the blob store.
    Event {
        event: JobEvent,
        has_positions: bool,
    },
    /// The subscriber fell behind and missed events: it catches up from the store.
    Lagged,
}

/// Live fan-out of job events to every watcher on every node.
#[async_trait]
pub trait EventBus: Send + Sync + 'static {
    /// Send to current subscribers; nobody listening is fine. Never waits for a watcher.
    async fn publish(&self, id: &str, event: JobEvent) -> Result<(), JobError>;
    /// Live events of `id` from now on. The stream ends when the job's channel is closed
    /// (after its `Done`) or the bus goes away.
    async fn subscribe(&self, id: &str) -> Result<BoxStream<'static, BusEvent>, JobError>;
    /// The job is terminal: release what its channel holds.
    async fn close(&self, id: &str);
}

/// Cancellation that reaches the node running the job.
#[async_trait]
pub trait CancelBus: Send + Sync + 'static {
    /// Ask whoever runs `id` to stop it at its next step.
    async fn cancel(&self, id: &str) -> Result<(), JobError>;
    /// The token the running worker checks between steps: cancelled by [`CancelBus::cancel`]
    /// on any node, including a cancel that came before this call.
    async fn watch(&self, id: &str) -> CancellationToken;
    /// The job stopped running here.
    async fn forget(&self, id: &str);
}

/// The five ports of one backend.
#[derive(Clone)]
pub struct Backend {
    pub store: std::sync::Arc<dyn JobStore>,
    pub blobs: std::sync::Arc<dyn BlobStore>,
    pub queue: std::sync::Arc<dyn WorkQueue>,
    pub events: std::sync::Arc<dyn EventBus>,
    pub cancels: std::sync::Arc<dyn CancelBus>,
    /// For logs and `/readyz`: `embedded` or `nats://…`.
    pub name: String,
    /// How long a client's request may wait on this backend before it answers `unavailable`
    /// (503 + `Retry-After`, gRPC `UNAVAILABLE`): a server across the network may be away,
    /// and a request must not hang for the length of its outage. `None` for the embedded
    /// backend: its store is the local disk, and a slow disk is no outage.
    pub request_timeout: Option<std::time::Duration>,
}

tokio::task_local! {
    /// The deadline of the client request being served, set by the core around the
    /// request's backend calls ([`with_request_deadline`]): a backend that retries
    /// (NATS) stops retrying there instead of riding out an outage, as a worker does.
    static REQUEST_DEADLINE: std::time::Instant;
}

/// Run `f` with `deadline` as the request deadline its backend calls see.
pub async fn with_request_deadline<F: std::future::Future>(
    deadline: std::time::Instant,
    f: F,
) -> F::Output {
    REQUEST_DEADLINE.scope(deadline, f).await
}

/// The deadline of the client request this call serves; `None` off the request path
/// (workers, sweeps, webhooks), which may wait out an outage.
pub fn request_deadline() -> Option<std::time::Instant> {
    REQUEST_DEADLINE.try_with(|d| *d).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: u64 = MINUTE_MS;

    fn windows(start: u64, current: u64, previous: u64) -> MinuteWindows {
        MinuteWindows {
            start,
            current,
            previous,
        }
    }

    /// The estimate on cases worked by hand: exact within one fixed minute, the previous
    /// minute weighted by the part of it still inside the sliding one (rounded up), nothing
    /// older.
    #[test]
    fn last_minute_weights_the_previous_minute() {
        let t = 1_000 * MIN;
        // All in the current minute: exact.
        assert_eq!(windows(t, 5, 0).last_minute(t + 30_000), 5);
        // A quarter into the minute: 3/4 of the previous minute's 8, plus this minute's 2.
        assert_eq!(windows(t, 2, 8).last_minute(t + MIN / 4), 6 + 2);
        // Rounded up: a burst of 3 just before the boundary still counts 3 right after it.
        assert_eq!(windows(t, 0, 3).last_minute(t + 100), 3);
        // The windows are a minute behind `now`: their current minute is now the previous.
        assert_eq!(windows(t - MIN, 10, 99).last_minute(t + MIN / 2), 5);
        // Older windows count nothing.
        assert_eq!(windows(t - 2 * MIN, 10, 10).last_minute(t + 1), 0);
        // Windows ahead of `now` (the clock stepped back) count in full.
        assert_eq!(windows(t + MIN, 4, 1).last_minute(t), 5);
    }

    /// Receiving moves the windows on minute by minute, resets them after a quiet minute,
    /// and counts a late mesh of the previous minute there (and an older one nowhere).
    #[test]
    fn receive_moves_the_windows_on() {
        let t = 1_000 * MIN;
        let mut w = MinuteWindows::default();
        w.receive(t + 5);
        w.receive(t + 59_999);
        assert_eq!(w, windows(t, 2, 0));
        w.receive(t + MIN);
        assert_eq!(w, windows(t + MIN, 1, 2));
        w.receive(t + 10);
        assert_eq!(w, windows(t + MIN, 1, 3), "late, in the previous minute");
        w.receive(t - MIN);
        assert_eq!(w, windows(t + MIN, 1, 3), "older than the windows");
        w.receive(t + 3 * MIN + 1);
        assert_eq!(w, windows(t + 3 * MIN, 1, 0), "after a quiet minute");
    }

    /// The server's disk budget refuses whoever would pass it, though that tenant is well
    /// within its own quota; a download rendered is charged to it as well; off at 0.
    #[test]
    fn the_server_budget_counts_every_tenant() {
        let q = TenantQuotas {
            server_max_stored_bytes: 1_000,
            max_live_jobs: 0,
            max_stored_bytes: 1 << 40,
            uploads_per_minute: 0,
        };
        let usage = Usage {
            stored_bytes: 10,
            server_stored_bytes: 900,
            ..Usage::default()
        };
        assert_eq!(
            over_quota(&q, &usage, 100, Admitting::Upload),
            None,
            "exactly full"
        );
        for admitting in [
            Admitting::Upload,
            Admitting::Job { received: true },
            Admitting::Rendered,
        ] {
            assert_eq!(
                over_quota(&q, &usage, 101, admitting),
                Some(OverQuota {
                    quota: "server_stored_bytes",
                    limit: 1_000,
                    used: 900,
                }),
                "{admitting:?}"
            );
        }
        let off = TenantQuotas {
            server_max_stored_bytes: 0,
            ..q
        };
        assert_eq!(over_quota(&off, &usage, 1 << 30, Admitting::Upload), None);
        assert!(off.any(), "the tenant's own quota is still on");
        let only_server = TenantQuotas {
            server_max_stored_bytes: 1,
            max_live_jobs: 0,
            max_stored_bytes: 0,
            uploads_per_minute: 0,
        };
        assert!(
            only_server.any(),
            "usage must be counted for the server budget alone"
        );
    }
}
