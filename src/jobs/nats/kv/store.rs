//! [`KvStore`] behind the [`JobStore`] port.

use super::super::super::ports::{
    over_quota, Admitting, Fence, Inserted, JobStore, NewJob, OverQuota, Recovered, Started, Swept,
    Usage,
};
use super::super::super::{
    now_ms, FailureCode, JobError, JobId, JobState, JobStatus, TenantQuotas,
};
use super::super::{nats_err, retry};
use super::*;

#[async_trait]
impl JobStore for KvStore {
    async fn insert(&self, job: NewJob) -> Result<Inserted, JobError> {
        // A repeat is answered before the quota is counted (it adds nothing).
        if let Some((key, hash)) = &job.idempotency {
            if let Some(status) = self.idempotent(&job.tenant, key, hash).await? {
                return Ok(Inserted::Existing(status));
            }
        }
        // Reserve the job's room in its tenant's usage first: the quota check and the count
        // are one compare-and-set, so concurrent admissions on any nodes cannot overshoot.
        let mut over = None;
        let now = now_ms();
        let bytes = job.input_bytes.saturating_add(job.planned_bytes);
        let server = self.server_bytes_for(&job.quotas).await?;
        self.update_usage(&job.tenant, |u| {
            over = job
                .quotas
                .any()
                .then(|| {
                    let admitting = Admitting::Job {
                        received: job.received,
                    };
                    let usage = Usage {
                        server_stored_bytes: server,
                        ..u.usage(now)
                    };
                    over_quota(&job.quotas, &usage, bytes, admitting)
                })
                .flatten();
            if over.is_some() {
                return false;
            }
            u.live += 1;
            u.bytes = u.bytes.saturating_add(bytes);
            if job.received {
                u.windows.receive(job.created_at);
            }
            true
        })
        .await?;
        if let Some(over) = over {
            return Ok(Inserted::OverQuota(over));
        }
        match self.create_job(&job).await {
            Ok(inserted @ Inserted::New(_)) => Ok(inserted),
            other => {
                self.release(&job.tenant, bytes).await?;
                other
            }
        }
    }

    async fn idempotent(
        &self,
        tenant: &str,
        key: &str,
        hash: &str,
    ) -> Result<Option<JobStatus>, JobError> {
        let Some(b) = self
            .nats
            .kv
            .get(idem_key(tenant, key))
            .await
            .map_err(|e| nats_err("reading an idempotency key", e))?
        else {
            return Ok(None);
        };
        let entry: IdemEntry = from_json(&b)?;
        if entry.hash != hash {
            return Err(JobError::IdempotencyMismatch(format!(
                "key `{key}` was first used with a different mesh or parameters"
            )));
        }
        // The key is written just before its job: a moment later the job is there.
        for _ in 0..20 {
            match self.status(&entry.job, Some(tenant)).await {
                Err(JobError::NotFound(_)) => tokio::time::sleep(Duration::from_millis(25)).await,
                other => return other.map(Some),
            }
        }
        Ok(None)
    }

    async fn status(&self, id: &str, tenant: Option<&str>) -> Result<JobStatus, JobError> {
        let (rec, _) = self.record(id).await?;
        if tenant.is_some_and(|t| t != rec.status.tenant) {
            return Err(JobError::NotFound(id.to_string()));
        }
        Self::live(id, &rec)
    }

    async fn list(
        &self,
        tenant: &str,
        state: Option<JobState>,
        size: usize,
        token: Option<String>,
    ) -> Result<(Vec<JobStatus>, Option<String>), JobError> {
        // Newest first by (created_at, id); the token is the last one of the previous page.
        let before: Option<(u64, String)> = match token.as_deref() {
            None | Some("") => None,
            Some(t) => Some(
                base64::engine::general_purpose::URL_SAFE_NO_PAD
                    .decode(t)
                    .ok()
                    .and_then(|b| String::from_utf8(b).ok())
                    .and_then(|s| {
                        let (t, id) = s.strip_prefix("at:")?.split_once(':')?;
                        Some((t.parse().ok()?, id.to_string()))
                    })
                    .ok_or_else(|| JobError::InvalidSpec {
                        field: "page_token",
                        reason: "not a token this server returned".into(),
                    })?,
            ),
        };
        let mut all: Vec<JobStatus> = Vec::new();
        for rec in self.list_records().await? {
            if rec.status.tenant != tenant {
                continue;
            }
            if let Ok(s) = Self::live(&rec.status.id, &rec) {
                if state.is_none_or(|st| s.state == st) {
                    all.push(s);
                }
            }
        }
        all.sort_by(|a, b| (b.created_at, &b.id).cmp(&(a.created_at, &a.id)));
        let mut page: Vec<JobStatus> = all
            .into_iter()
            .filter(|s| {
                before
                    .as_ref()
                    .is_none_or(|(t, id)| (s.created_at, s.id.as_str()) < (*t, id.as_str()))
            })
            .take(size + 1)
            .collect();
        let next = if page.len() > size {
            page.truncate(size);
            page.last().map(|s| {
                base64::engine::general_purpose::URL_SAFE_NO_PAD
                    .encode(format!("at:{}:{}", s.created_at, s.id))
            })
        } else {
            None
        };
        Ok((page, next))
    }

    async fn start(&self, id: &str, fence: &Fence, at: u64) -> Result<Started, JobError> {
        for _ in 0..32 {
            let (mut rec, revision) = match self.record(id).await {
                Ok(r) => r,
                Err(JobError::NotFound(_)) => return Ok(self.settled(id, Started::Gone)),
                Err(e) => return Err(e),
            };
            if rec.expired || rec.status.state.is_terminal() {
                return Ok(self.settled(id, Started::Gone));
            }
            if let Some(h) = rec.hold.as_ref().filter(|h| h.token != fence.token) {
                if !self.may_take_over(id, h, revision, fence.ttl, at) {
                    return Ok(Started::Held);
                }
                tracing::warn!(job_id = %id, "taking over a lapsed hold: its worker is gone");
            }
            rec.status.state = JobState::Running;
            rec.status.started_at.get_or_insert(at);
            rec.hold = Some(Hold::of(fence, at));
            if self.write(id, &rec, revision).await? {
                fence.renewed(at);
                return rec
                    .status()
                    .map(|s| self.settled(id, Started::Run(Box::new(s))));
            }
        }
        Err(JobError::Unavailable(format!(
            "job `{id}` kept changing under 32 starts"
        )))
    }

    async fn renew(&self, id: &str, fence: &Fence) -> Result<(), JobError> {
        // One try, no backoff: the heartbeat tries again soon, and a renewal right after an
        // outage is what keeps the hold.
        JobId::parse(id)?;
        let at = now_ms();
        for _ in 0..8 {
            let entry = self
                .nats
                .kv
                .entry(job_key(id))
                .await
                .map_err(|e| nats_err("renewing a job's hold", e))?;
            let Some(entry) = entry.filter(|e| !e.value.is_empty()) else {
                return Err(fence.lost_error(id));
            };
            let mut rec: Record = from_json(&entry.value)?;
            fenced(id, &mut rec, fence)?;
            match self
                .nats
                .kv
                .update(job_key(id), to_json(&rec)?, entry.revision)
                .await
            {
                Ok(_) => {
                    fence.renewed(at);
                    return Ok(());
                }
                Err(e) if e.kind() == UpdateErrorKind::WrongLastRevision => continue,
                Err(e) => return Err(nats_err("renewing a job's hold", e)),
            }
        }
        Err(JobError::Unavailable(format!(
            "job `{id}` kept changing under 8 renewals"
        )))
    }

    async fn record_frame(
        &self,
        id: &str,
        metrics: StepMetrics,
        has_positions: bool,
        fence: &Fence,
    ) -> Result<(), JobError> {
        if fence.lost.is_cancelled() {
            return Err(fence.lost_error(id));
        }
        let mut payload = Vec::with_capacity(1 + 96);
        payload.push(u8::from(has_positions));
        payload.extend_from_slice(&encode_metrics(&metrics));
        // Publishing a step twice is harmless: readers keep one message per step.
        let payload = bytes::Bytes::from(payload);
        retry(|| async {
            self.nats
                .js
                .publish(frame_subject(id, metrics.step), payload.clone())
                .await
                .map_err(|e| nats_err("storing a frame", e))?
                .await
                .map_err(|e| nats_err("storing a frame", e))
        })
        .await?;
        let at = now_ms();
        self.update(id, |r| {
            fenced(id, r, fence)?;
            r.status.step = metrics.step;
            r.set_latest(Some(&metrics));
            Ok(true)
        })
        .await?;
        fence.renewed(at);
        Ok(())
    }

    async fn rewind(&self, id: &str, step: usize, fence: &Fence) -> Result<(), JobError> {
        let kept = self.read_frames(id, step, step, 1).await?;
        let latest = kept.into_iter().next().map(|(m, _)| m);
        self.update(id, |r| {
            fenced(id, r, fence)?;
            r.status.step = if latest.is_some() { step } else { 0 };
            r.set_latest(latest.as_ref());
            Ok(true)
        })
        .await?;
        Ok(())
    }

    async fn frame_rows(
        &self,
        id: &str,
        from: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError> {
        let (rec, _) = self.record(id).await?;
        if rec.latest.is_none() {
            return Ok(Vec::new());
        }
        self.read_frames(id, from, rec.status.step, limit).await
    }

    async fn finish(
        &self,
        id: &str,
        state: JobState,
        error: Option<(FailureCode, String)>,
        at: u64,
        expires_at: u64,
        fence: Option<&Fence>,
    ) -> Result<Option<JobStatus>, JobError> {
        let mut released = 0;
        let rec = self
            .update(id, |r| {
                if r.status.state.is_terminal() {
                    return Ok(false);
                }
                if let Some(fence) = fence {
                    fenced(id, r, fence)?;
                }
                // A job that never started stored nothing but its input: its plan goes.
                released = 0;
                if r.status.started_at.is_none() && !r.expired {
                    released = r.status.planned_bytes;
                    r.status.planned_bytes = 0;
                }
                r.hold = None;
                r.status.state = state;
                let (code, msg) = error.clone().unzip();
                r.status.error_code = code.map(|c| c.as_str().to_string());
                r.status.error = msg;
                r.status.finished_at = Some(at);
                r.status.expires_at = Some(expires_at);
                Ok(true)
            })
            .await?;
        if let Some(r) = &rec {
            // This node made the job terminal: it alone counts it off.
            self.update_usage(&r.status.tenant, |u| {
                u.live = u.live.saturating_sub(1);
                u.bytes = u.bytes.saturating_sub(released);
                true
            })
            .await?;
        }
        rec.map(|r| r.status()).transpose()
    }

    async fn requeue(&self, id: &str, fence: &Fence) -> Result<(), JobError> {
        self.update(id, |r| {
            let mine = r.hold.as_ref().is_some_and(|h| h.token == fence.token);
            if r.status.state != JobState::Running || !mine {
                return Ok(false);
            }
            r.hold = None;
            r.status.state = JobState::Queued;
            r.ledger.stalled = 0;
            Ok(true)
        })
        .await?;
        Ok(())
    }

    async fn checkpointed(&self, id: &str, step: usize, fence: &Fence) -> Result<(), JobError> {
        let at = now_ms();
        self.update(id, |r| {
            fenced(id, r, fence)?;
            r.ledger.checkpoint = Some(step);
            Ok(true)
        })
        .await?;
        fence.renewed(at);
        Ok(())
    }

    async fn settle_planned(&self, id: &str, bytes: u64, fence: &Fence) -> Result<(), JobError> {
        let mut released = 0;
        let rec = self
            .update(id, |r| {
                fenced(id, r, fence)?;
                released = r.status.planned_bytes.saturating_sub(bytes);
                if released == 0 || r.expired {
                    return Ok(false);
                }
                r.status.planned_bytes = bytes;
                Ok(true)
            })
            .await?;
        // The record first, then the count: a node lost between the two leaves the tenant
        // counted high (the safe side) until the next recount.
        if let Some(r) = rec.filter(|_| released > 0) {
            self.update_usage(&r.status.tenant, |u| {
                u.bytes = u.bytes.saturating_sub(released);
                true
            })
            .await?;
        }
        Ok(())
    }

    async fn delivered(&self, id: &str, fence: &Fence) -> Result<u32, JobError> {
        let mut stalled = 0;
        self.update(id, |r| {
            fenced(id, r, fence)?;
            stalled = r.ledger.deliver();
            Ok(true)
        })
        .await?;
        Ok(stalled)
    }

    async fn delete(&self, tenant: &str, id: &str) -> Result<(), JobError> {
        let (rec, _) = self.record(id).await?;
        if rec.status.tenant != tenant {
            return Err(JobError::NotFound(id.to_string()));
        }
        if !rec.expired && !rec.status.state.is_terminal() {
            return Err(JobError::Conflict(format!(
                "job `{id}` is {}: cancel it first, only finished jobs can be deleted",
                rec.status.state.as_str()
            )));
        }
        // Retire it before purging: the node whose compare-and-set retires it counts its
        // bytes off (a job the sweeper retired was counted off then).
        let retired = self
            .update(id, |r| {
                if r.expired {
                    return Ok(false);
                }
                r.expired = true;
                Ok(true)
            })
            .await?;
        if let Some(r) = retired {
            self.update_usage(tenant, |u| {
                u.bytes = u.bytes.saturating_sub(r.stored_bytes());
                true
            })
            .await?;
        }
        let kv = &self.nats.kv;
        if let Some(k) = &rec.idem {
            kv.purge(k)
                .await
                .map_err(|e| nats_err("deleting a job", e))?;
        }
        for k in [format!("qseq.{id}"), format!("cancel.{id}"), job_key(id)] {
            kv.purge(&k)
                .await
                .map_err(|e| nats_err("deleting a job", e))?;
        }
        self.frames
            .purge()
            .filter(frames_subject(id))
            .await
            .map_err(|e| nats_err("deleting a job's frames", e))?;
        Ok(())
    }

    /// The tenant's bytes first, with the quota check (one compare-and-set, as an
    /// admission), then the name in the job's record; a name another node recorded first,
    /// or a job retired meanwhile, gives the bytes back.
    async fn charge_rendered(
        &self,
        id: &str,
        name: &str,
        bytes: u64,
        quotas: &TenantQuotas,
    ) -> Result<Option<OverQuota>, JobError> {
        let (rec, _) = self.record(id).await?;
        if rec.expired {
            return Err(JobError::Gone(id.to_string()));
        }
        if rec.rendered.contains_key(name) {
            return Ok(None);
        }
        let tenant = rec.status.tenant.clone();
        let mut over = None;
        let now = now_ms();
        let server = self.server_bytes_for(quotas).await?;
        self.update_usage(&tenant, |u| {
            let usage = Usage {
                server_stored_bytes: server,
                ..u.usage(now)
            };
            over = quotas
                .any()
                .then(|| over_quota(quotas, &usage, bytes, Admitting::Rendered))
                .flatten();
            if over.is_some() {
                return false;
            }
            u.bytes = u.bytes.saturating_add(bytes);
            true
        })
        .await?;
        if over.is_some() {
            return Ok(over);
        }
        let mut gone = false;
        let recorded = self
            .update(id, |r| {
                gone = r.expired;
                if r.expired || r.rendered.contains_key(name) {
                    return Ok(false);
                }
                r.rendered.insert(name.to_string(), bytes);
                Ok(true)
            })
            .await;
        if !matches!(recorded, Ok(Some(_))) {
            self.update_usage(&tenant, |u| {
                u.bytes = u.bytes.saturating_sub(bytes);
                true
            })
            .await?;
        }
        match recorded {
            Err(e) => Err(e),
            Ok(_) if gone => Err(JobError::Gone(id.to_string())),
            Ok(_) => Ok(None),
        }
    }

    async fn refund_rendered(&self, id: &str, name: &str) -> Result<(), JobError> {
        let mut refund = 0;
        let removed = self
            .update(id, |r| {
                if r.expired {
                    return Ok(false);
                }
                refund = r.rendered.remove(name).unwrap_or(0);
                Ok(refund > 0)
            })
            .await?;
        if let Some(r) = removed {
            self.update_usage(&r.status.tenant, |u| {
                u.bytes = u.bytes.saturating_sub(refund);
                true
            })
            .await?;
        }
        Ok(())
    }

    async fn sweep_expired(&self, now: u64) -> Result<Swept, JobError> {
        let mut swept = Swept::default();
        for rec in self.list_records().await? {
            let id = rec.status.id.clone();
            if rec.expired || rec.status.expires_at.is_none_or(|t| t > now) {
                continue;
            }
            let retired = self
                .update(&id, |r| {
                    if r.expired {
                        return Ok(false);
                    }
                    r.expired = true;
                    Ok(true)
                })
                .await?;
            let Some(r) = retired else {
                // Another node's sweep (or a delete) retired it first.
                continue;
            };
            self.update_usage(&r.status.tenant, |u| {
                u.bytes = u.bytes.saturating_sub(r.stored_bytes());
                true
            })
            .await?;
            self.frames
                .purge()
                .filter(frames_subject(&id))
                .await
                .map_err(|e| nats_err("sweeping a job's frames", e))?;
            swept.jobs.push(id);
        }
        let uploads: Vec<String> = self
            .keys("upload.")
            .await?
            .into_iter()
            .filter_map(|k| k.strip_prefix("upload.").map(str::to_string))
            .collect();
        for id in uploads {
            let key = format!("upload.{id}");
            let Some(e) = self
                .nats
                .kv
                .entry(&key)
                .await
                .map_err(|e| nats_err("reading an upload", e))?
                .filter(|e| !e.value.is_empty())
            else {
                continue;
            };
            let mut entry: UploadEntry = from_json(&e.value)?;
            if entry.expires_at <= now {
                if !entry.swept {
                    // Mark it swept with compare-and-set: the node that wins counts it off.
                    entry.swept = true;
                    match self
                        .nats
                        .kv
                        .update(&key, to_json(&entry)?, e.revision)
                        .await
                    {
                        Ok(_) => {
                            self.update_usage(&entry.tenant, |u| {
                                u.bytes = u.bytes.saturating_sub(entry.size);
                                true
                            })
                            .await?;
                        }
                        Err(e) if e.kind() == UpdateErrorKind::WrongLastRevision => continue,
                        Err(e) => return Err(nats_err("sweeping an upload", e)),
                    }
                }
                self.nats
                    .kv
                    .purge(&key)
                    .await
                    .map_err(|e| nats_err("sweeping an upload", e))?;
                if let Some(f) = crate::jobs::parse_format(&entry.format) {
                    swept.uploads.push((id, f));
                }
            }
        }
        let healed = self.heal_usage().await?;
        if healed > 0 {
            tracing::info!(tenants = healed, "tenant usage recounted");
        }
        Ok(swept)
    }

    async fn pending_callbacks(&self, limit: usize) -> Result<Vec<JobStatus>, JobError> {
        // A scan of every record, as `sweep_expired`'s: the webhook loop calls it at start,
        // after each job that ends on this node and every few seconds (jobs that ended on
        // other nodes), which keeps a bucket of thousands of jobs to a few reads a second.
        let mut out = Vec::new();
        for rec in self.list_records().await? {
            if rec.callback_pending && rec.status.state.is_terminal() && !rec.expired {
                out.push(rec.status()?);
            }
        }
        out.sort_by_key(|s| (s.finished_at, s.created_at));
        out.truncate(limit);
        Ok(out)
    }

    async fn settle_callback(&self, id: &str) -> Result<(), JobError> {
        match self
            .update(id, |r| {
                Ok(std::mem::replace(&mut r.callback_pending, false))
            })
            .await
        {
            Ok(_) | Err(JobError::NotFound(_)) => Ok(()),
            Err(e) => Err(e),
        }
    }

    async fn recover(&self) -> Result<Vec<Recovered>, JobError> {
        // The work-queue stream is durable: queued jobs are still in it, and running ones are
        // delivered again when their lease lapses.
        Ok(Vec::new())
    }

    async fn put_upload(
        &self,
        tenant: &str,
        id: &str,
        format: Format,
        size: u64,
        expires_at: u64,
    ) -> Result<(), JobError> {
        let entry = UploadEntry {
            format: crate::jobs::format_name(format).to_string(),
            expires_at,
            tenant: tenant.to_string(),
            size,
            created_at: now_ms(),
            swept: false,
        };
        self.nats
            .kv
            .put(format!("upload.{id}"), to_json(&entry)?)
            .await
            .map_err(|e| nats_err("storing an upload", e))?;
        self.update_usage(tenant, |u| {
            u.bytes = u.bytes.saturating_add(size);
            u.windows.receive(entry.created_at);
            true
        })
        .await
        .map(drop)
    }

    async fn upload(&self, tenant: &str, id: &str) -> Result<Format, JobError> {
        if !well_formed(id) {
            return Err(JobError::UploadNotFound(id.to_string()));
        }
        let b = self
            .nats
            .kv
            .get(format!("upload.{id}"))
            .await
            .map_err(|e| nats_err("reading an upload", e))?
            .ok_or_else(|| JobError::UploadNotFound(id.to_string()))?;
        let entry: UploadEntry = from_json(&b)?;
        if entry.expires_at <= now_ms() || entry.tenant != tenant {
            return Err(JobError::UploadNotFound(id.to_string()));
        }
        crate::jobs::parse_format(&entry.format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{}`", entry.format)))
    }

    async fn usage(&self, tenant: &str, now: u64) -> Result<Usage, JobError> {
        Ok(self.usage_entry(tenant).await?.0.usage(now))
    }

    async fn server_stored_bytes(&self) -> Result<u64, JobError> {
        self.sum_stored_bytes().await
    }
}

impl KvStore {
    /// The server's stored bytes when `quotas` has a budget to check them against, else 0
    /// (not read).
    async fn server_bytes_for(&self, quotas: &TenantQuotas) -> Result<u64, JobError> {
        if quotas.server_max_stored_bytes > 0 {
            self.sum_stored_bytes().await
        } else {
            Ok(0)
        }
    }
}
