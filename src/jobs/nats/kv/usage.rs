//! A tenant's usage in KV (`usage.{sha256(tenant)}`: bytes, live jobs, the minute windows),
//! counted by compare-and-set, healed from the records, and a job record created against it.

use super::super::super::ports::{Inserted, JobStore, NewJob};
use super::super::super::{JobError, JobState, JobStatus};
use super::super::{nats_err, retry};
use super::*;

impl KvStore {
    /// `tenant`'s usage entry and its revision (`None`: no entry yet).
    pub(super) async fn usage_entry(
        &self,
        tenant: &str,
    ) -> Result<(UsageEntry, Option<u64>), JobError> {
        let entry = retry(|| async {
            self.nats
                .kv
                .entry(usage_key(tenant))
                .await
                .map_err(|e| nats_err("reading a tenant's usage", e))
        })
        .await?;
        match entry {
            Some(e) if !e.value.is_empty() => Ok((from_json(&e.value)?, Some(e.revision))),
            // Absent, or deleted/purged (a create succeeds on those).
            _ => Ok((
                UsageEntry {
                    tenant: tenant.to_string(),
                    ..UsageEntry::default()
                },
                None,
            )),
        }
    }

    /// Every tenant's stored bytes together, for the server's disk budget: one KV read per
    /// tenant, so only asked for when the budget is on. Not one compare-and-set with the
    /// tenant's own count (that stays exact): admissions of different tenants racing on
    /// different nodes can pass the budget by what they add together, and the next admission
    /// sees it.
    pub(super) async fn sum_stored_bytes(&self) -> Result<u64, JobError> {
        let mut total = 0u64;
        for k in self.keys("usage.").await? {
            let entry = retry(|| async {
                self.nats
                    .kv
                    .entry(&k)
                    .await
                    .map_err(|e| nats_err("reading a tenant's usage", e))
            })
            .await?;
            if let Some(e) = entry.filter(|e| !e.value.is_empty()) {
                let u: UsageEntry = from_json(&e.value)?;
                total = total.saturating_add(u.bytes);
            }
        }
        Ok(total)
    }

    /// Write `entry` over `revision` (`None`: create it); `false` when another node wrote
    /// first.
    pub(super) async fn put_usage(
        &self,
        entry: &UsageEntry,
        revision: Option<u64>,
    ) -> Result<bool, JobError> {
        let (key, value) = (usage_key(&entry.tenant), to_json(entry)?);
        retry(|| async {
            let kv = &self.nats.kv;
            match revision {
                Some(r) => match kv.update(&key, value.clone(), r).await {
                    Ok(_) => Ok(true),
                    Err(e) if e.kind() == UpdateErrorKind::WrongLastRevision => Ok(false),
                    Err(e) => Err(nats_err("updating a tenant's usage", e)),
                },
                None => match kv.create(&key, value.clone()).await {
                    Ok(_) => Ok(true),
                    Err(e) if e.kind() == CreateErrorKind::AlreadyExists => Ok(false),
                    Err(e) => Err(nats_err("storing a tenant's usage", e)),
                },
            }
        })
        .await
    }

    /// Apply `change` to `tenant`'s usage with compare-and-set, retrying on a concurrent
    /// write; `change` returns `false` to leave it as it is (then so does this).
    pub(super) async fn update_usage(
        &self,
        tenant: &str,
        mut change: impl FnMut(&mut UsageEntry) -> bool,
    ) -> Result<bool, JobError> {
        for _ in 0..64 {
            let (mut entry, revision) = self.usage_entry(tenant).await?;
            if !change(&mut entry) {
                return Ok(false);
            }
            if self.put_usage(&entry, revision).await? {
                return Ok(true);
            }
        }
        Err(JobError::Unavailable(format!(
            "the usage of tenant `{tenant}` kept changing under 64 updates"
        )))
    }

    /// Give back what an admission reserved and did not use.
    pub(super) async fn release(&self, tenant: &str, bytes: u64) -> Result<(), JobError> {
        self.update_usage(tenant, |u| {
            u.live = u.live.saturating_sub(1);
            u.bytes = u.bytes.saturating_sub(bytes);
            true
        })
        .await
        .map(drop)
    }

    /// Recount every tenant's live jobs and bytes from the records and uploads, and write
    /// those that differ. An entry that changed during the scan (its revision moved) is left
    /// for the next recount. Run at connect (entries from before counters existed) and by
    /// every sweep. O(records): the sweep scans them anyway.
    pub(crate) async fn heal_usage(&self) -> Result<usize, JobError> {
        use std::collections::BTreeMap;
        let mut before: BTreeMap<String, (UsageEntry, Option<u64>)> = BTreeMap::new();
        for k in self.keys("usage.").await? {
            let entry = self
                .nats
                .kv
                .entry(&k)
                .await
                .map_err(|e| nats_err("reading a tenant's usage", e))?;
            if let Some(e) = entry.filter(|e| !e.value.is_empty()) {
                let u: UsageEntry = from_json(&e.value)?;
                before.insert(u.tenant.clone(), (u, Some(e.revision)));
            }
        }
        let mut counted: BTreeMap<String, (u64, u64)> = BTreeMap::new();
        for rec in self.list_records().await? {
            if rec.expired {
                continue;
            }
            let c = counted.entry(rec.status.tenant.clone()).or_default();
            c.0 += u64::from(!rec.status.state.is_terminal());
            c.1 = c.1.saturating_add(rec.stored_bytes());
        }
        for k in self.keys("upload.").await? {
            let Some(b) = self
                .nats
                .kv
                .get(&k)
                .await
                .map_err(|e| nats_err("reading an upload", e))?
            else {
                continue;
            };
            let entry: UploadEntry = from_json(&b)?;
            if !entry.swept {
                let c = counted.entry(entry.tenant).or_default();
                c.1 = c.1.saturating_add(entry.size);
            }
        }
        let mut healed = 0;
        let tenants: std::collections::BTreeSet<String> =
            before.keys().chain(counted.keys()).cloned().collect();
        for tenant in tenants {
            let (live, bytes) = counted.get(&tenant).copied().unwrap_or_default();
            let (mut entry, revision) = before.remove(&tenant).unwrap_or_else(|| {
                (
                    UsageEntry {
                        tenant: tenant.clone(),
                        ..UsageEntry::default()
                    },
                    None,
                )
            });
            if (entry.live, entry.bytes) == (live, bytes) {
                continue;
            }
            (entry.live, entry.bytes) = (live, bytes);
            if self.put_usage(&entry, revision).await? {
                healed += 1;
            }
        }
        Ok(healed)
    }

    /// Store `job`'s idempotency key (if any) and record: `Existing` when its key already
    /// names a job.
    pub(super) async fn create_job(&self, job: &NewJob) -> Result<Inserted, JobError> {
        let kv = &self.nats.kv;
        let mut idem = None;
        if let Some((key, hash)) = &job.idempotency {
            let k = idem_key(&job.tenant, key);
            let entry = IdemEntry {
                hash: hash.clone(),
                job: job.id.clone(),
            };
            match kv.create(&k, to_json(&entry)?).await {
                Ok(_) => idem = Some(k),
                Err(e) if e.kind() == CreateErrorKind::AlreadyExists => {
                    return match self.idempotent(&job.tenant, key, hash).await? {
                        Some(status) => Ok(Inserted::Existing(status)),
                        None => Err(JobError::Conflict(format!(
                            "idempotency key `{key}` is being used by a request in flight; retry"
                        ))),
                    };
                }
                Err(e) => return Err(nats_err("storing an idempotency key", e)),
            }
        }
        let status = JobStatus {
            id: job.id.clone(),
            tenant: job.tenant.clone(),
            state: JobState::Queued,
            step: 0,
            total_steps: job.spec.steps,
            spec: job.spec.clone(),
            input_format: job.format,
            vertex_count: job.vertex_count,
            face_count: job.face_count,
            input_bytes: job.input_bytes,
            planned_bytes: job.planned_bytes,
            latest: None,
            error: None,
            error_code: None,
            created_at: job.created_at,
            started_at: None,
            finished_at: None,
            expires_at: None,
            repairs: job.repairs.clone(),
            notes: job.notes.clone(),
        };
        let rec = Record {
            status: status.clone(),
            latest: None,
            idem,
            expired: false,
            hold: None,
            callback_pending: job.spec.callback_url.is_some(),
            ledger: Ledger::default(),
            rendered: Default::default(),
        };
        kv.create(job_key(&job.id), to_json(&rec)?)
            .await
            .map_err(|e| nats_err("storing a job", e))?;
        Ok(Inserted::New(status))
    }
}
