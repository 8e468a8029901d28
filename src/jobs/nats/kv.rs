//! The NATS [`JobStore`]: job records in the KV bucket, per-step metrics in the frames stream.
//!
//! Keys: `job.{id}` (the [`Record`], JSON), `idem.{sha256(key)}` (an idempotency key's request
//! hash and job), `upload.{id}`, `usage.{sha256(tenant)}` (a tenant's [`UsageEntry`]),
//! `qseq.{id}` (the job's sequence in the work-queue stream, for withdrawing it) and
//! `cancel.{id}`. Every change of a record is a compare-and-set on its revision, so two nodes
//! never overwrite each other's transitions.
//!
//! A running job's record holds its worker's [`Fence`] ([`Hold`]: token and lapse time), and a
//! worker's writes (start, frames, rewind, finish, requeue, renew) also check the token: a
//! worker that lost the job is refused. [`JobStore::start`] answers [`Started::Held`] while
//! another worker's hold is live, and takes a hold over only once it has lapsed and the record
//! has not moved for half a hold as seen from this node.
//!
//! A step's metrics are a message on `willow.frames.{id}.{step}`: one byte (positions kept or
//! not) and the metrics in [`codec`](super::super::codec) form (JSON cannot carry NaN). The
//! stream keeps one message per subject, so a job resumed from a checkpoint replaces the steps
//! it takes again; readers stop at the record's progress, which is what [`JobStore::rewind`]
//! means here.

use super::super::codec::{decode_metrics, encode_metrics};
use super::super::ids::well_formed;
use super::super::ports::{
    over_quota, Admitting, Fence, Inserted, JobStore, MinuteWindows, NewJob, Recovered, Started,
    Swept, Usage,
};
use super::super::{now_ms, FailureCode, JobError, JobId, JobState, JobStatus};
use super::{nats_err, retry, Nats};
use async_nats::jetstream::kv::{CreateErrorKind, UpdateErrorKind};
use async_nats::jetstream::stream::DirectGetErrorKind;
use async_trait::async_trait;
use base64::Engine as _;
use futures::StreamExt;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::sync::Arc;
use std::time::Duration;
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

/// A job as kept in KV.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct Record {
    /// `latest` is kept apart (below): it may hold NaN.
    status: JobStatus,
    /// `status.latest` in codec form, base64.
    latest: Option<String>,
    /// The KV key of its idempotency key, to delete with the job.
    idem: Option<String>,
    /// Retired by the sweeper: answers `Gone`.
    expired: bool,
    /// The fence of the worker running the job (absent in records from before fencing, and
    /// while the job waits).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    hold: Option<Hold>,
}

/// A worker's hold on a running job: its [`Fence`]'s token, and until when (unix ms, the
/// holder's clock) the hold lasts without a renewal.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
struct Hold {
    token: String,
    until: u64,
}

impl Hold {
    fn of(fence: &Fence, now: u64) -> Hold {
        Hold {
            token: fence.token.clone(),
            until: now.saturating_add(u64::try_from(fence.ttl.as_millis()).unwrap_or(u64::MAX)),
        }
    }
}

/// A worker's write to a running job: refused (and its fence marked lost) unless the job is
/// still live and held by `fence`; the hold is renewed by the write.
fn fenced(id: &str, r: &mut Record, fence: &Fence) -> Result<(), JobError> {
    let mine = r.hold.as_ref().is_some_and(|h| h.token == fence.token);
    if !mine || r.expired || r.status.state != JobState::Running {
        return Err(fence.lost_error(id));
    }
    r.hold = Some(Hold::of(fence, now_ms()));
    Ok(())
}

impl Record {
    fn status(&self) -> Result<JobStatus, JobError> {
        let mut s = self.status.clone();
        s.latest = match &self.latest {
            Some(b) => Some(decode_metrics(
                &base64::engine::general_purpose::STANDARD
                    .decode(b)
                    .map_err(|e| JobError::Internal(format!("stored metrics: {e}")))?,
            )?),
            None => None,
        };
        Ok(s)
    }

    fn set_latest(&mut self, m: Option<&StepMetrics>) {
        self.latest =
            m.map(|m| base64::engine::general_purpose::STANDARD.encode(encode_metrics(m)));
        self.status.latest = None;
    }
}

#[derive(Serialize, Deserialize)]
struct IdemEntry {
    hash: String,
    job: JobId,
}

#[derive(Serialize, Deserialize)]
struct UploadEntry {
    format: String,
    expires_at: u64,
    /// Entries from before tenants belong to the default tenant.
    #[serde(default = "default_tenant")]
    tenant: String,
    #[serde(default)]
    size: u64,
    #[serde(default)]
    created_at: u64,
    /// Taken off its tenant's usage by the sweeper that won it (compare-and-set), so that two
    /// nodes sweeping at once count it off once; purged next.
    #[serde(default)]
    swept: bool,
}

/// What a tenant's quotas check, under `usage.{sha256(tenant)}`: one KV read per admission
/// (the scan of every record it replaces was O(jobs kept) per submission). Changed only with
/// compare-and-set, by the node that won the transition counted (a job's admission, finish or
/// retirement, an upload stored or swept), so each counts once. An admission reserves its
/// room here before its record exists, so two nodes cannot both take a tenant's last unit.
/// The sweeper recounts `live` and `bytes` from the records ([`KvStore::heal_usage`]): a node
/// that died between a transition and its count leaves the counts off until the next sweep,
/// and so can a transition caught half done by the recount's scan (by one unit, for one sweep
/// interval).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
struct UsageEntry {
    tenant: String,
    /// Queued and running jobs.
    live: u64,
    /// Inputs of unretired jobs and unswept uploads.
    bytes: u64,
    /// Meshes received (uploads, and jobs that brought theirs).
    windows: MinuteWindows,
}

impl UsageEntry {
    fn usage(&self, now: u64) -> Usage {
        Usage {
            live_jobs: usize::try_from(self.live).unwrap_or(usize::MAX),
            stored_bytes: self.bytes,
            uploads_last_minute: self.windows.last_minute(now),
        }
    }
}

fn usage_key(tenant: &str) -> String {
    let h = Sha256::digest(tenant.as_bytes());
    let hex: String = h[..16].iter().map(|b| format!("{b:02x}")).collect();
    format!("usage.{hex}")
}

fn default_tenant() -> String {
    super::super::DEFAULT_TENANT.to_string()
}

pub(crate) struct KvStore {
    nats: Arc<Nats>,
    /// Jobs this node found held by another worker's fence: the record's revision and when
    /// it was first seen. A hold is taken over only once it has lapsed *and* its record has
    /// not moved for a while as seen here, so a holder that was cut off with everyone else
    /// (a NATS restart longer than its hold) gets the time to renew after the outage.
    held_seen: std::sync::Mutex<std::collections::HashMap<String, (u64, std::time::Instant)>>,
    frames: async_nats::jetstream::stream::Stream,
    /// The stream behind the KV bucket, for listing keys.
    kv_stream: async_nats::jetstream::stream::Stream,
}

fn job_key(id: &str) -> String {
    format!("job.{id}")
}

/// A step's frame subject; the job's frames are `willow.frames.{id}.>`.
fn frame_subject(id: &str, step: usize) -> String {
    format!("willow.frames.{id}.{step}")
}

fn frames_subject(id: &str) -> String {
    format!("willow.frames.{id}.>")
}

/// Idempotency keys are the client's text, per tenant: the tenant and the key hashed into a
/// valid KV key (no tenant id holds the `/`).
fn idem_key(tenant: &str, key: &str) -> String {
    let h = Sha256::digest(format!("{tenant}/{key}").as_bytes());
    let hex: String = h.iter().map(|b| format!("{b:02x}")).collect();
    format!("idem.{hex}")
}

fn to_json<T: Serialize>(v: &T) -> Result<bytes::Bytes, JobError> {
    serde_json::to_vec(v)
        .map(bytes::Bytes::from)
        .map_err(|e| JobError::Internal(format!("encoding a record: {e}")))
}

fn from_json<T: for<'de> Deserialize<'de>>(b: &[u8]) -> Result<T, JobError> {
    serde_json::from_slice(b).map_err(|e| JobError::Internal(format!("decoding a record: {e}")))
}

impl KvStore {
    pub fn new(
        nats: Arc<Nats>,
        frames: async_nats::jetstream::stream::Stream,
        kv_stream: async_nats::jetstream::stream::Stream,
    ) -> KvStore {
        KvStore {
            nats,
            held_seen: std::sync::Mutex::new(std::collections::HashMap::new()),
            frames,
            kv_stream,
        }
    }

    async fn record(&self, id: &str) -> Result<(Record, u64), JobError> {
        JobId::parse(id)?;
        let entry = retry(|| async {
            self.nats
                .kv
                .entry(job_key(id))
                .await
                .map_err(|e| nats_err("reading a job", e))
        })
        .await?;
        match entry {
            Some(e) if !e.value.is_empty() => Ok((from_json(&e.value)?, e.revision)),
            _ => Err(JobError::NotFound(id.to_string())),
        }
    }

    /// Apply `change` to the record with compare-and-set, retrying on a concurrent write.
    /// `change` returns `false` to leave the record as it is (the transition does not apply).
    async fn update(
        &self,
        id: &str,
        mut change: impl FnMut(&mut Record) -> Result<bool, JobError>,
    ) -> Result<Option<Record>, JobError> {
        for _ in 0..32 {
            let (mut rec, revision) = self.record(id).await?;
            if !change(&mut rec)? {
                return Ok(None);
            }
            // A retried update that had in fact landed fails on the revision and is read
            // again: compare-and-set makes the retry safe.
            let value = to_json(&rec)?;
            let written = retry(|| async {
                match self
                    .nats
                    .kv
                    .update(job_key(id), value.clone(), revision)
                    .await
                {
                    Ok(_) => Ok(true),
                    Err(e) if e.kind() == UpdateErrorKind::WrongLastRevision => Ok(false),
                    Err(e) => Err(nats_err("updating a job", e)),
                }
            })
            .await?;
            if written {
                return Ok(Some(rec));
            }
        }
        Err(JobError::Internal(format!(
            "job `{id}` kept changing under 32 updates"
        )))
    }

    /// Compare-and-set `rec` over `revision`; `false` when another write came first.
    async fn write(&self, id: &str, rec: &Record, revision: u64) -> Result<bool, JobError> {
        let value = to_json(rec)?;
        retry(|| async {
            match self
                .nats
                .kv
                .update(job_key(id), value.clone(), revision)
                .await
            {
                Ok(_) => Ok(true),
                Err(e) if e.kind() == UpdateErrorKind::WrongLastRevision => Ok(false),
                Err(e) => Err(nats_err("updating a job", e)),
            }
        })
        .await
    }

    /// Whether another worker's `hold` on `id` (its record at `revision`) may be taken over
    /// at `now`: it lapsed, and the record has stayed at `revision` for half a hold's length
    /// as seen from this node (a live holder renews at least every third of one).
    fn may_take_over(&self, id: &str, hold: &Hold, revision: u64, ttl: Duration, now: u64) -> bool {
        let mut seen = self.held_seen.lock().unwrap_or_else(|p| p.into_inner());
        if seen.len() > 4096 {
            seen.clear();
        }
        let first = match seen.get(id) {
            Some(&(r, t)) if r == revision => t,
            _ => {
                seen.insert(id.to_string(), (revision, std::time::Instant::now()));
                return false;
            }
        };
        hold.until <= now && first.elapsed() >= ttl / 2
    }

    /// Forget what [`Self::may_take_over`] saw of `id`, and pass `started` on.
    fn settled(&self, id: &str, started: Started) -> Started {
        self.held_seen
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(id);
        started
    }

    fn live(id: &str, rec: &Record) -> Result<JobStatus, JobError> {
        let expired = rec.expired || rec.status.expires_at.is_some_and(|t| t <= now_ms());
        if expired {
            return Err(JobError::Gone(id.to_string()));
        }
        rec.status()
    }

    /// The job's frames of steps `from..=upto`, at most `limit`: one direct get of the last
    /// message on each step's subject (the stream keeps one per subject), so a replay from any
    /// step costs what it returns, and a step taken again after a resume replaces the old one.
    async fn read_frames(
        &self,
        id: &str,
        from: usize,
        upto: usize,
        limit: usize,
    ) -> Result<Vec<(StepMetrics, bool)>, JobError> {
        let mut rows = Vec::new();
        let mut step = from;
        while step <= upto && rows.len() < limit {
            let got = retry(|| async {
                match self
                    .frames
                    .direct_get_last_for_subject(frame_subject(id, step))
                    .await
                {
                    Ok(m) => Ok(Some(m)),
                    Err(e) if e.kind() == DirectGetErrorKind::NotFound => Ok(None),
                    Err(e) => Err(nats_err("reading a frame", e)),
                }
            })
            .await?;
            let Some(msg) = got else {
                // Expired with the job, or never kept: nothing further either.
                break;
            };
            if let Some((&flag, metrics)) = msg.payload.split_first() {
                rows.push((decode_metrics(metrics)?, flag != 0));
            }
            step += 1;
        }
        Ok(rows)
    }

    /// The keys under `prefix` (`job.`, `upload.`), from the KV stream's subject counts: one
    /// request and no consumer (a key watcher per listing ran into the server's consumer limit
    /// under load, and could miss a key updated during its scan).
    async fn keys(&self, prefix: &str) -> Result<Vec<String>, JobError> {
        let kv_prefix = format!("$KV.{}.", super::KV_BUCKET);
        let mut subjects = self
            .kv_stream
            .info_with_subjects(format!("{kv_prefix}{prefix}>"))
            .await
            .map_err(|e| nats_err("listing keys", e))?;
        let mut out = Vec::new();
        while let Some(s) = subjects.next().await {
            let (subject, _) = s.map_err(|e| nats_err("listing keys", e))?;
            if let Some(key) = subject.strip_prefix(&kv_prefix) {
                out.push(key.to_string());
            }
        }
        Ok(out)
    }

    /// `tenant`'s usage entry and its revision (`None`: no entry yet).
    async fn usage_entry(&self, tenant: &str) -> Result<(UsageEntry, Option<u64>), JobError> {
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

    /// Write `entry` over `revision` (`None`: create it); `false` when another node wrote
    /// first.
    async fn put_usage(&self, entry: &UsageEntry, revision: Option<u64>) -> Result<bool, JobError> {
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
    async fn update_usage(
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
    async fn release(&self, tenant: &str, bytes: u64) -> Result<(), JobError> {
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
            c.1 = c.1.saturating_add(rec.status.input_bytes);
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
    async fn create_job(&self, job: &NewJob) -> Result<Inserted, JobError> {
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
            latest: None,
            error: None,
            error_code: None,
            created_at: job.created_at,
            started_at: None,
            finished_at: None,
            expires_at: None,
        };
        let rec = Record {
            status: status.clone(),
            latest: None,
            idem,
            expired: false,
            hold: None,
        };
        kv.create(job_key(&job.id), to_json(&rec)?)
            .await
            .map_err(|e| nats_err("storing a job", e))?;
        Ok(Inserted::New(status))
    }

    async fn list_records(&self) -> Result<Vec<Record>, JobError> {
        let mut out = Vec::new();
        for k in self.keys("job.").await? {
            let Some(id) = k.strip_prefix("job.") else {
                continue;
            };
            match self.record(id).await {
                Ok((r, _)) => out.push(r),
                Err(JobError::NotFound(_)) => {}
                Err(e) => return Err(e),
            }
        }
        Ok(out)
    }
}

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
        self.update_usage(&job.tenant, |u| {
            over = job
                .quotas
                .any()
                .then(|| {
                    let admitting = Admitting::Job {
                        received: job.received,
                    };
                    over_quota(&job.quotas, &u.usage(now), job.input_bytes, admitting)
                })
                .flatten();
            if over.is_some() {
                return false;
            }
            u.live += 1;
            u.bytes = u.bytes.saturating_add(job.input_bytes);
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
                self.release(&job.tenant, job.input_bytes).await?;
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
        let rec = self
            .update(id, |r| {
                if r.status.state.is_terminal() {
                    return Ok(false);
                }
                if let Some(fence) = fence {
                    fenced(id, r, fence)?;
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
            Ok(true)
        })
        .await?;
        Ok(())
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
                u.bytes = u.bytes.saturating_sub(r.status.input_bytes);
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
                u.bytes = u.bytes.saturating_sub(r.status.input_bytes);
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
                if let Some(f) = super::super::parse_format(&entry.format) {
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
            format: super::super::format_name(format).to_string(),
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
        super::super::parse_format(&entry.format)
            .ok_or_else(|| JobError::Internal(format!("unknown stored format `{}`", entry.format)))
    }

    async fn usage(&self, tenant: &str, now: u64) -> Result<Usage, JobError> {
        Ok(self.usage_entry(tenant).await?.0.usage(now))
    }
}
