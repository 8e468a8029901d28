//! Admission: a mesh and a spec become a stored, queued job, or a clear refusal. Validation
//! runs before anything is stored; the backend's atomic operations decide between concurrent
//! submissions, on this node and across nodes (the idempotency key's create and, on SQLite,
//! the tenant's quota, in the insert; the queue's capacity, in the push).

use super::ports::{over_quota, Admitting, BlobKey, Inserted, NewJob, OverQuota};
use super::{
    audit, codec, join_err, mesh_error, now_ms, Caller, FailureCode, JobError, JobId, JobSpec,
    JobState, JobStatus, Jobs, UploadRef,
};
use std::sync::atomic::Ordering;
use std::time::Instant;
use willow::mesh::io::{Asset, Format};

impl Jobs {
    /// Parse and validate the mesh (on a blocking thread), then store and enqueue the job.
    ///
    /// With an idempotency key, a repeat of the same request returns the job it created (even
    /// when the queue has since filled up, and on any node); the same key with a different
    /// mesh or spec is [`JobError::IdempotencyMismatch`]. Keys are the caller's tenant's: two
    /// tenants never see each other's jobs through them.
    ///
    /// The caller's tenant quotas ([`super::TenantQuotas`]) are checked at admission, each
    /// refusal naming its quota ([`JobError::QuotaExceeded`]).
    pub async fn submit(
        &self,
        caller: &Caller,
        upload: UploadRef,
        spec: JobSpec,
        idempotency_key: Option<String>,
    ) -> Result<JobStatus, JobError> {
        self.on_request(self.submit_now(caller, upload, spec, idempotency_key))
            .await
    }

    async fn submit_now(
        &self,
        caller: &Caller,
        upload: UploadRef,
        spec: JobSpec,
        idempotency_key: Option<String>,
    ) -> Result<JobStatus, JobError> {
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        // While the disk is full a submission would only eat the reserve deletes need.
        self.inner.storage.refuse_if_full()?;
        spec.validate(&self.inner.config)?;
        if let Some(url) = &spec.callback_url {
            super::webhooks::check_callback(url, &self.inner.config).await?;
        }
        let backend = &self.inner.backend;
        let received = matches!(upload, UploadRef::Bytes { .. });
        let (data, format) = match upload {
            UploadRef::Bytes { data, format } => (data, format),
            UploadRef::Stored { upload_id } => {
                let format = backend.store.upload(&caller.tenant, &upload_id).await?;
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
            if let Some(status) = backend.store.idempotent(&caller.tenant, k, h).await? {
                return Ok(status);
            }
        }

        // Parse and validate off the runtime: a large OBJ takes a while and the async threads
        // must keep serving status polls and streams meanwhile.
        let limits = self.inner.config.limits.clone();
        let parse_data = data.clone();
        let t = Instant::now();
        let parse_spec = spec.clone();
        let (vertex_count, face_count, sizes, repairs, notes) =
            tokio::task::spawn_blocking(move || {
                let asset = parse_spec.read_asset(&parse_data, format, &limits.mesh_limits())?;
                let surface = asset.surface();
                parse_spec.validate_for_asset(&asset)?;
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
                // Only what changed: repair is the default, and a file that needed none says
                // nothing about it.
                let repairs =
                    Some(asset.repairs().clone()).filter(|r| parse_spec.repair && !r.is_empty());
                let sizes = super::stored::JobSizes {
                    file_vertices: asset.file_vertex_count(),
                    surface_vertices: surface.vertex_count(),
                };
                Ok((
                    asset.file_vertex_count(),
                    surface.face_count(),
                    sizes,
                    repairs,
                    asset.notes(),
                ))
            })
            .await
            .map_err(join_err)??;
        let telemetry = &self.inner.telemetry;
        telemetry.phase("parse", t);
        let planned_bytes = super::stored::planned_bytes(&spec, sizes);
        self.check_job_fits_quota(&spec, sizes, data.len() as u64, planned_bytes)?;

        let id = JobId::random();
        let data_len = data.len() as u64;
        // Write the blob before taking the admission lock: fsync is slow and need not be
        // serialised. A refused job's blob is removed again below.
        let t = Instant::now();
        let input = BlobKey::Input {
            id: id.clone(),
            format,
        };
        let put = backend.blobs.put(input, data).await;
        if put.is_err() {
            // A full disk may have left the job's directory behind.
            let _ = backend.blobs.delete_job(&id).await;
        }
        self.inner.storage.note(put)?;
        telemetry.phase("blob_put", t);
        let job = NewJob {
            id: id.clone(),
            tenant: caller.tenant.clone(),
            spec: spec.clone(),
            format,
            vertex_count,
            face_count,
            repairs: repairs.clone(),
            notes,
            input_bytes: data_len,
            planned_bytes,
            received,
            // Set by `admit`.
            quotas: super::TenantQuotas::default(),
            created_at: now_ms(),
            idempotency: key.zip(request_hash),
        };
        match self.admit(job).await {
            Ok(Inserted::New(status)) => {
                tracing::info!(
                    target: "audit",
                    action = "create",
                    tenant = %caller.tenant,
                    subject = %caller.subject,
                    job_id = %status.id,
                    vertex_count,
                    face_count,
                    steps = spec.steps,
                    "audit"
                );
                if let Some(r) = repairs.as_ref().filter(|r| !r.is_empty()) {
                    tracing::info!(job_id = %status.id, repairs = %r, "upload repaired");
                }
                Ok(status)
            }
            Ok(Inserted::Existing(status)) => {
                let _ = backend.blobs.delete_job(&id).await;
                Ok(status)
            }
            Ok(Inserted::OverQuota(over)) => {
                let _ = backend.blobs.delete_job(&id).await;
                Err(self.over_quota(&caller.tenant, over))
            }
            Err(e) => {
                let _ = backend.blobs.delete_job(&id).await;
                Err(e)
            }
        }
    }

    /// Store and queue the job. No lock: the store's insert is atomic (idempotency key, and
    /// on SQLite the quota count), and so is the queue's push (capacity). A lock here
    /// serialised every submission of the node behind two store round trips: at 50
    /// concurrent clients its wait was most of a submission's time (`cargo bench --bench
    /// service_load`, part 7).
    async fn admit(&self, mut job: NewJob) -> Result<Inserted, JobError> {
        let backend = &self.inner.backend;
        let telemetry = &self.inner.telemetry;
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        // A quick local refusal; the queue's own `push` is the cluster-wide decision.
        if backend.queue.depth() >= backend.queue.capacity() {
            return Err(self.queue_full());
        }
        job.quotas = self.inner.config.quotas.clone();
        let (id, tenant) = (job.id.clone(), job.tenant.clone());
        let t = Instant::now();
        let inserted = self.inner.storage.note(backend.store.insert(job).await)?;
        telemetry.phase("insert", t);
        if !matches!(inserted, Inserted::New(_)) {
            return Ok(inserted);
        }
        let t = Instant::now();
        let pushed = backend.queue.push(&tenant, &id).await;
        telemetry.phase("push", t);
        if let Err(e) = pushed {
            // Lost the race for the last slot (to another submission or node), or the queue
            // is away: the record goes again, key and all, so a retry can succeed.
            let now = now_ms();
            let withdrawn = Some((FailureCode::QueueFull, e.to_string()));
            let _ = backend
                .store
                .finish(&id, JobState::Failed, withdrawn, now, now, None)
                .await;
            let _ = backend.store.delete(&tenant, &id).await;
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

    /// The refusal for `over`, counted and logged, with a `Retry-After` that fits the quota:
    /// live jobs free up as jobs finish, the minute's uploads within a minute, stored bytes
    /// when finished jobs are deleted or expire.
    fn over_quota(&self, tenant: &str, over: OverQuota) -> JobError {
        self.inner
            .telemetry
            .rejected_quota
            .get_or_create(&super::telemetry::QuotaLabels { quota: over.quota })
            .inc();
        tracing::info!(
            tenant,
            quota = over.quota,
            limit = over.limit,
            used = over.used,
            "tenant quota spent"
        );
        if over.quota == "server_stored_bytes" {
            tracing::warn!(
                limit = over.limit,
                used = over.used,
                "the server's disk budget is spent: refusing every tenant's new work"
            );
        }
        let retry_after_secs = match over.quota {
            "live_jobs" => self.retry_after_secs(),
            "uploads_per_minute" => 60,
            _ => self.inner.config.result_ttl.as_secs().clamp(1, 3600),
        };
        JobError::QuotaExceeded {
            quota: over.quota,
            limit: over.limit,
            used: Some(over.used),
            retry_after_secs,
        }
    }

    /// Refuse a job that could not fit in its tenant's `stored_bytes` quota even alone: its
    /// input fits, but with what its frames would store ([`super::stored`]) it passes the
    /// whole quota, so it is a request to change (fewer kept frames), not a wait. 400 on
    /// `frame_interval`, with the interval that would fit.
    fn check_job_fits_quota(
        &self,
        spec: &JobSpec,
        sizes: super::stored::JobSizes,
        input_bytes: u64,
        planned_bytes: u64,
    ) -> Result<(), JobError> {
        let limit = self.inner.config.quotas.max_stored_bytes;
        let total = input_bytes.saturating_add(planned_bytes);
        // An input past the quota by itself is the quota's own refusal (`QuotaExceeded`, with
        // the usage), as for an upload.
        if limit == 0 || total <= limit || input_bytes > limit {
            return Ok(());
        }
        let frames = super::stored::kept_frames(spec, spec.steps);
        let hint = match super::stored::interval_that_fits(spec, sizes, input_bytes, limit) {
            Some(k) => {
                format!("keep fewer frames: frame_interval={k} fits, or include_positions=false")
            }
            None => "even keeping only the first and last frames it does not fit: fewer \
                     steps or a smaller mesh"
                .to_string(),
        };
        Err(JobError::InvalidSpec {
            field: "frame_interval",
            reason: format!(
                "the job would store {total} bytes ({input_bytes} of input, {frames} kept frames \
                 of {} bytes each, its checkpoint, result and step metrics), more than the \
                 tenant's whole stored_bytes quota of {limit}: {hint}",
                sizes.frame_bytes()
            ),
        })
    }

    /// Refuse an upload of `bytes` that `tenant`'s quotas have no room for.
    async fn check_upload_quotas(&self, tenant: &str, bytes: u64) -> Result<(), JobError> {
        let quotas = &self.inner.config.quotas;
        if !quotas.any() {
            return Ok(());
        }
        let mut usage = self.inner.backend.store.usage(tenant, now_ms()).await?;
        if quotas.server_max_stored_bytes > 0 {
            usage.server_stored_bytes = self.inner.backend.store.server_stored_bytes().await?;
        }
        match over_quota(quotas, &usage, bytes, Admitting::Upload) {
            Some(over) => Err(self.over_quota(tenant, over)),
            None => Ok(()),
        }
    }

    fn queue_full(&self) -> JobError {
        self.inner.telemetry.rejected.inc();
        JobError::QueueFull {
            retry_after_secs: self.retry_after_secs(),
            capacity: self.inner.backend.queue.capacity(),
        }
    }

    /// `Retry-After` estimate ([`retry_after_estimate`]) from this node's job durations.
    fn retry_after_secs(&self) -> u64 {
        retry_after_estimate(
            self.inner.avg_job_ms.load(Ordering::Relaxed),
            self.inner.config.workers,
        )
    }

    /// Store an upload for later use by [`UploadRef::Stored`]. The mesh is validated now, so a
    /// bad upload fails here and not at job creation.
    pub async fn store_upload(
        &self,
        caller: &Caller,
        data: bytes::Bytes,
        format: Format,
    ) -> Result<String, JobError> {
        self.on_request(self.store_upload_now(caller, data, format))
            .await
    }

    async fn store_upload_now(
        &self,
        caller: &Caller,
        data: bytes::Bytes,
        format: Format,
    ) -> Result<String, JobError> {
        if self.inner.draining.load(Ordering::SeqCst) {
            return Err(JobError::ShuttingDown);
        }
        self.inner.storage.refuse_if_full()?;
        let limit = self.inner.config.limits.max_upload_bytes;
        if data.len() as u64 > limit {
            return Err(JobError::TooLarge {
                what: "upload bytes",
                limit,
            });
        }
        let limits = self.inner.config.limits.mesh_limits();
        let check = data.clone();
        // Checked as `repair` would read it: a job that asks for no repair is checked again
        // (strictly) when it uses the upload.
        tokio::task::spawn_blocking(move || {
            Asset::read_repaired(&check, format, &limits).map(|_| ())
        })
        .await
        .map_err(join_err)?
        .map_err(mesh_error)?;
        let id = uuid::Uuid::new_v4().to_string();
        let expires = now_ms() + self.inner.config.result_ttl.as_millis() as u64;
        let size = data.len() as u64;
        let backend = &self.inner.backend;
        {
            let _guard = self.inner.admission.lock().await;
            self.check_upload_quotas(&caller.tenant, size).await?;
            let key = BlobKey::Upload {
                id: id.clone(),
                format,
            };
            let storage = &self.inner.storage;
            storage.note(backend.blobs.put(key, data).await)?;
            storage.note(
                backend
                    .store
                    .put_upload(&caller.tenant, &id, format, size, expires)
                    .await,
            )?;
        }
        audit("upload", caller, &id);
        Ok(id)
    }
}

/// `Retry-After` for a full queue (or a tenant's live jobs): a place opens when the first
/// running job ends, about one job's time over the workers running them. Not the whole
/// queue's drain time: the client needs one place, and a queue of short jobs advised tens of
/// seconds. No job ended on this node yet (or an API-only node, which runs none): 1 s.
/// Clamped to 1..=300 s.
pub(crate) fn retry_after_estimate(avg_job_ms: u64, workers: usize) -> u64 {
    if avg_job_ms == 0 {
        return 1;
    }
    (avg_job_ms / workers.max(1) as u64)
        .div_ceil(1000)
        .clamp(1, 300)
}

#[cfg(test)]
mod tests {
    use super::retry_after_estimate;

    #[test]
    fn retry_after_is_one_job_over_the_workers() {
        assert_eq!(retry_after_estimate(0, 1), 1, "nothing measured yet");
        assert_eq!(retry_after_estimate(120, 1), 1, "short jobs: a second");
        assert_eq!(retry_after_estimate(12_000, 4), 3);
        assert_eq!(retry_after_estimate(12_004, 4), 4, "rounded up");
        assert_eq!(
            retry_after_estimate(10_000_000, 1),
            300,
            "at most five minutes"
        );
        assert_eq!(
            retry_after_estimate(5_000, 0),
            5,
            "no workers counts as one"
        );
    }
}
