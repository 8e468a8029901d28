//! The job core: fairing jobs accepted, queued, run, streamed and kept, for every transport.
//!
//! HTTP (`api::http`), gRPC (`api::grpc`) and the CLI all call the same [`Jobs`] handle; nothing
//! in here knows about axum, tonic, protobuf messages or an HTTP status: no handler, request or
//! response type of either transport. What crosses the border in is a [`UploadRef`] plus a
//! validated [`JobSpec`]; what crosses out is a [`JobStatus`], a stream of [`JobEvent`]s (each
//! step's [`Frame`]) and result bytes. Errors are one enum, [`JobError`], which each transport
//! maps once to its own status codes (`api::status`).
//!
//! Two things here do face the wire, on purpose. The JSON form of a job's parameters is
//! [`JobSpec`]'s own serde form, and its OpenAPI schema is derived from the declaration
//! (`utoipa::ToSchema` on [`JobSpec`] and the option types in [`spec`], their doc comments the
//! API's descriptions), so the API cannot describe a field the core does not take; the
//! library's types in it are described by mirrors in `api::schema`, named in `job_spec.rs`'s
//! schema attributes: the one path from here into `api`, and a type name only. And
//! [`webhooks`] POSTs a job's end with hyper-util's HTTP client: an outgoing call, not a
//! transport of the API.
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
//! - [`webhooks`]: a job's end POSTed, signed, to its `callback_url`, at least once.
//! - [`curve`]: synchronous curve fairing ([`Jobs::fair_curve`]) on its own bounded slots.
//!
//! Times in [`JobStatus`] are **unix milliseconds** (`u64`): cheap to compare and to turn into a
//! protobuf `Timestamp` or an RFC 3339 string at the edge ([`rfc3339`] does the latter).
//!
//! Restart semantics: every accepted job is in the store before `submit` returns. On start,
//! finished jobs keep their results, queued jobs are queued again in their original order, and
//! jobs that were running are re-queued and **resume from their last checkpoint** (step 0 if
//! they had none): the frames after it are taken again, and watchers see each step once.

mod admission;
pub mod codec;
pub mod curve;
mod downloads;
pub mod embedded;
mod error;
mod ids;
mod job_spec;
mod model;
pub mod nats;
mod page_token;
pub mod ports;
pub mod render_memory;
pub mod spec;
pub mod storage;
pub mod stored;
pub mod telemetry;
pub mod watch;
pub mod webhooks;
pub mod worker;

pub use downloads::MeshDownload;
pub use error::{is_storage_full, FailureCode, JobError, STORAGE_FULL_RETRY_SECS};
pub use ids::JobId;
pub use model::*;
pub(crate) use page_token::page_token_key;
use page_token::{seal_page_token, unseal_page_token};
pub use render_memory::DownloadMemory;

use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio_util::sync::CancellationToken;
use willow::mesh::io::Format;
use willow::mesh::MeshError;
use willow::metrics::StepMetrics;

use ports::{Backend, BlobKey};
/// One audit line (target `audit`) for a change a caller made: who (tenant and subject), what,
/// to which job. Creations are logged by admission with the job's size.
pub(crate) fn audit(action: &'static str, caller: &Caller, job_id: &str) {
    tracing::info!(
        target: "audit",
        action,
        tenant = %caller.tenant,
        subject = %caller.subject,
        job_id = %job_id,
        "audit"
    );
}

/// Shared state behind the [`Jobs`] handle.
pub(crate) struct Inner {
    pub config: Config,
    pub backend: Backend,
    /// Serialises this node's stored uploads between their quota count and their record
    /// (jobs need no lock: their quota is counted in the store's insert).
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
    /// Exponential moving average of job wall time in ms, for `Retry-After` estimates; 0
    /// until a job has ended on this node.
    pub avg_job_ms: AtomicU64,
    /// Permits for curve requests ([`Config::curve_slots`]).
    pub curve_slots: Arc<tokio::sync::Semaphore>,
    /// Woken when a job with a `callback_url` ends on this node ([`webhooks::delivery_loop`]).
    pub callbacks_due: Arc<tokio::sync::Notify>,
    /// Whether the data dir is full ([`storage`]).
    pub storage: storage::StorageHealth,
    /// The key of list page tokens' HMAC ([`page_token_key`]).
    pub page_token_key: ring::hmac::Key,
    /// Downloads being rendered ([`Jobs::rendered`]): one lock per stripe of keys.
    pub renders: Box<[tokio::sync::Mutex<()>]>,
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
    ///
    /// On a full disk it still starts and serves reads: a first open that fails releases the
    /// reserves ([`storage`]) and tries once more.
    pub async fn start(config: Config) -> Result<(Jobs, Shutdown), JobError> {
        let (dir, capacity) = (config.data_dir.clone(), config.queue_capacity);
        let backend = tokio::task::spawn_blocking(move || {
            match embedded::open(&dir, capacity) {
                // SQLite reports ENOSPC on its `-shm` file as a plain I/O error, so any failure
                // is worth one more try if there was a reserve to free.
                Err(e) if storage::release_for_start(&dir) => {
                    tracing::error!(error = %e, "the store did not open: reserves released, trying again (a full disk?)");
                    embedded::open(&dir, capacity)
                }
                other => other,
            }
        })
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
        // The embedded backend's storage is the data dir: probed, and holding the reserve.
        let storage = storage::StorageHealth::new(
            (backend.name == "embedded").then(|| config.data_dir.clone()),
        );
        if let Some(dir) = (backend.name == "embedded").then(|| config.data_dir.clone()) {
            let made = tokio::task::spawn_blocking(move || storage::ensure_reserve(&dir))
                .await
                .map_err(join_err)?;
            if let Err(e) = made {
                // No room for it: the disk is full now, and the server says so.
                tracing::warn!(error = %e, "could not write the storage reserve");
                let _ = storage.noted(JobError::from(e));
            }
        }
        // On a full disk recovery cannot write: the server starts anyway (reads work), and
        // recovers once the probe finds room.
        let recovered = match storage.note(backend.store.recover().await) {
            Err(JobError::StorageFull { .. }) => None,
            other => Some(other?),
        };
        let pending_recovery = recovered.is_none();
        if let Some(recovered) = recovered {
            requeue_recovered(&backend, recovered).await?;
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
            avg_job_ms: AtomicU64::new(0),
            curve_slots: Arc::new(tokio::sync::Semaphore::new(config.curve_slots)),
            callbacks_due: Arc::new(tokio::sync::Notify::new()),
            storage,
            page_token_key: page_token_key(config.webhook_secret.as_deref()),
            renders: (0..downloads::RENDER_STRIPES)
                .map(|_| tokio::sync::Mutex::new(()))
                .collect(),
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
        // Every node delivers: jobs end on workers, and queued jobs are cancelled on API
        // nodes. Two nodes may both send one event (at least once); its `webhook-id` is the
        // same, for the receiver to drop the repeat.
        {
            let (deliverer, stop) = (jobs.clone(), stop_polling.clone());
            tokio::spawn(async move { webhooks::delivery_loop(deliverer, stop).await });
        }
        if config.role.serves_api() {
            let sweeper = jobs.clone();
            let stop = stop_polling.clone();
            tokio::spawn(async move { sweeper.sweep_loop(stop).await });
        }
        let prober = jobs.clone();
        let stop = stop_polling.clone();
        tokio::spawn(async move { prober.storage_loop(stop, pending_recovery).await });
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

    /// The caller's job's current status; `Gone` once it expired. Another tenant's job is
    /// `NotFound`, exactly like an unknown id (so is every call below).
    pub async fn get(&self, caller: &Caller, id: &str) -> Result<JobStatus, JobError> {
        self.read(self.inner.backend.store.status(id, Some(&caller.tenant)))
            .await
    }

    /// A client request's backend calls `f`: on a backend across the network
    /// ([`Backend::request_timeout`]), refused at once while it is disconnected, and its
    /// retries end at the request's time budget ([`ports::request_deadline`]), so that a
    /// request answers `unavailable` (503 + `Retry-After`, gRPC `UNAVAILABLE`) within a few
    /// seconds of an outage instead of hanging through it (issue 25). Writes are not cut
    /// mid-way (a half-made submission or cancel is worse than a slow one): each of their
    /// calls is bounded by the backend's own call timeout.
    pub(crate) async fn on_request<T>(
        &self,
        f: impl std::future::Future<Output = Result<T, JobError>>,
    ) -> Result<T, JobError> {
        let backend = &self.inner.backend;
        let Some(budget) = backend.request_timeout else {
            return f.await;
        };
        if !backend.queue.connected() {
            return Err(JobError::Unavailable(format!(
                "not connected to {}; retry shortly",
                backend.name
            )));
        }
        ports::with_request_deadline(std::time::Instant::now() + budget, f).await
    }

    /// [`Self::on_request`] for a read of records or metrics, which is also cut at the time
    /// budget: a read may be abandoned at any point.
    pub(crate) async fn read<T>(
        &self,
        f: impl std::future::Future<Output = Result<T, JobError>>,
    ) -> Result<T, JobError> {
        let Some(budget) = self.inner.backend.request_timeout else {
            return f.await;
        };
        tokio::time::timeout(budget, self.on_request(f))
            .await
            .unwrap_or_else(|_| {
                Err(JobError::Unavailable(format!(
                    "{} did not answer within {} s",
                    self.inner.backend.name,
                    budget.as_secs_f64()
                )))
            })
    }

    /// The caller's jobs newest first, optionally of one state. `page_token` is the opaque
    /// `next_page_token` of the previous page; `page_size` 0 means 50, at most 1000.
    pub async fn list(
        &self,
        caller: &Caller,
        state: Option<JobState>,
        page_size: usize,
        page_token: Option<String>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError> {
        let size = match page_size {
            0 => 50,
            n => n.min(1000),
        };
        // Backends' tokens are positions in the tenant's own listing (the last job's creation
        // time and id: never a global sequence, which would let a tenant count the others'
        // jobs). A hand-edited one would still decode and silently list the wrong page, and
        // one tenant's would position another's listing: the core seals each with an HMAC
        // over the tenant and the token, so any token it did not hand out to this tenant is
        // refused, on every backend, with `page_token` named.
        let key = &self.inner.page_token_key;
        let inner = match page_token.as_deref() {
            None | Some("") => None,
            Some(t) => Some(unseal_page_token(key, &caller.tenant, t).ok_or_else(|| {
                JobError::InvalidSpec {
                    field: "page_token",
                    reason: "not a token this server returned to this tenant".into(),
                }
            })?),
        };
        let (jobs, next) = self
            .read(
                self.inner
                    .backend
                    .store
                    .list(&caller.tenant, state, size, inner),
            )
            .await?;
        Ok((jobs, next.map(|t| seal_page_token(key, &caller.tenant, &t))))
    }

    /// Cancel a job. Queued: removed from the queue and cancelled now. Running (on any node):
    /// it stops at the next step boundary (the returned status may still say `running`; watch
    /// or poll for `cancelled`). Terminal: [`JobError::Conflict`].
    pub async fn cancel(&self, caller: &Caller, id: &str) -> Result<JobStatus, JobError> {
        self.on_request(self.cancel_now(caller, id)).await
    }

    async fn cancel_now(&self, caller: &Caller, id: &str) -> Result<JobStatus, JobError> {
        let status = self.get(caller, id).await?;
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
            let status = worker::finish(
                &self.inner,
                id,
                JobState::Cancelled,
                Some((FailureCode::Cancelled, "cancelled while queued".to_string())),
                None,
            )
            .await?;
            audit("cancel", caller, id);
            return Ok(status);
        }
        backend.cancels.cancel(id).await?;
        audit("cancel", caller, id);
        self.get(caller, id).await
    }

    /// Remove the caller's terminal job, its frames and its files. Queued or running:
    /// `Conflict`.
    pub async fn delete(&self, caller: &Caller, id: &str) -> Result<(), JobError> {
        self.on_request(self.delete_now(caller, id)).await
    }

    async fn delete_now(&self, caller: &Caller, id: &str) -> Result<(), JobError> {
        let backend = &self.inner.backend;
        // Files first: on a full disk they free the room SQLite's delete needs for its WAL
        // frames (the reserve covers a disk with nothing else to free). A delete the store
        // then refuses (not found, another tenant's, still running) must not have removed
        // them: so the store is asked first whether it would.
        let status = backend.store.status(id, Some(&caller.tenant)).await;
        match status {
            Ok(s) if s.state.is_terminal() => self
                .inner
                .storage
                .note(backend.blobs.delete_job(id).await)?,
            // Expired, unknown or not deletable: the store's delete says which.
            _ => {}
        }
        self.inner
            .storage
            .note(backend.store.delete(&caller.tenant, id).await)?;
        audit("delete", caller, id);
        self.inner.storage.note(backend.blobs.delete_job(id).await)
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

    /// Ready to take traffic: not draining, the backend reachable, storage not full, every
    /// worker loop alive, and, when a job is running, a step finished within `stall_after`.
    pub fn is_ready(&self) -> bool {
        let inner = &self.inner;
        if inner.draining.load(Ordering::SeqCst)
            || !inner.backend.queue.connected()
            || inner.storage.is_full()
        {
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

    /// Whether the data dir is known full (readiness says so until a probe finds room).
    pub fn storage_full(&self) -> bool {
        self.inner.storage.is_full()
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

    /// While storage is full, probe it every [`storage::STORAGE_PROBE_SECS`]; once it has
    /// room, run a recovery the start could not write (`pending_recovery`).
    async fn storage_loop(self, stop: CancellationToken, mut pending_recovery: bool) {
        let period = Duration::from_secs(storage::STORAGE_PROBE_SECS);
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = tokio::time::sleep(period) => {}
            }
            // A remote store (NATS) is asked whether it has room; only while full.
            let remote = if self.inner.storage.is_full() {
                self.inner.backend.blobs.room().await
            } else {
                None
            };
            let me = self.clone();
            let full =
                tokio::task::spawn_blocking(move || me.inner.storage.probe_with(now_ms(), remote))
                    .await
                    .unwrap_or(true);
            if full || !pending_recovery {
                continue;
            }
            let backend = &self.inner.backend;
            match self.inner.storage.note(backend.store.recover().await) {
                Ok(recovered) => match requeue_recovered(backend, recovered).await {
                    Ok(()) => pending_recovery = false,
                    Err(e) => tracing::warn!(error = %e, "recovery after a full disk failed"),
                },
                Err(e) => tracing::warn!(error = %e, "recovery after a full disk failed"),
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
        match backend.blobs.sweep_orphans().await {
            Ok(n) if n > 0 => tracing::info!(count = n, "chunks of failed blob writes removed"),
            Ok(_) => {}
            Err(e) => tracing::warn!(error = %e, "sweeping chunks of failed blob writes"),
        }
        Ok(swept.jobs.len())
    }
}

/// Put the jobs a recovery found back on the queue.
async fn requeue_recovered(
    backend: &Backend,
    recovered: Vec<ports::Recovered>,
) -> Result<(), JobError> {
    let count = recovered.len();
    for job in recovered {
        // Recovered jobs bypass the capacity check: they were admitted before.
        backend.queue.push_recovered(job).await?;
    }
    if count > 0 {
        tracing::info!(count, "re-queued jobs from the store");
    }
    Ok(())
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
