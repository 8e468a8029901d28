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
//!
//! [`JobStore`]: crate::jobs::ports::JobStore
//! [`JobStore::start`]: crate::jobs::ports::JobStore::start
//! [`JobStore::rewind`]: crate::jobs::ports::JobStore::rewind

mod store;
mod usage;

use super::super::codec::{decode_metrics, encode_metrics};
use super::super::ids::well_formed;
use super::super::ports::{Fence, MinuteWindows, Started, Usage};
use super::super::{now_ms, JobError, JobId, JobState, JobStatus};
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
    /// The job has a `callback_url` whose delivery is not settled yet (absent in records from
    /// before webhooks: they have none).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    callback_pending: bool,
    /// Progress across deliveries ([`JobStore::delivered`]); absent in records from before
    /// it, which read as a job with no checkpoint and no delivery yet.
    ///
    /// [`JobStore::delivered`]: crate::jobs::ports::JobStore::delivered
    #[serde(default, skip_serializing_if = "Ledger::is_empty")]
    ledger: Ledger,
    /// Downloads rendered and stored for the job, by blob name, with their sizes: counted in
    /// its tenant's bytes while the job is unexpired ([`JobStore::charge_rendered`]); absent
    /// in records from before they were counted.
    ///
    /// [`JobStore::charge_rendered`]: crate::jobs::ports::JobStore::charge_rendered
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    rendered: std::collections::BTreeMap<String, u64>,
}

impl Record {
    /// What the job counts in its tenant's bytes while unexpired: its upload, what it may
    /// store besides (`jobs::stored`) and its stored renderings.
    fn stored_bytes(&self) -> u64 {
        self.rendered.values().fold(
            self.status
                .input_bytes
                .saturating_add(self.status.planned_bytes),
            |a, b| a.saturating_add(*b),
        )
    }
}

/// A job's delivery ledger: the step of its checkpoint, the one its last delivery saw, and
/// the deliveries in a row that found no newer one.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
struct Ledger {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    checkpoint: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    at_delivery: Option<usize>,
    #[serde(default)]
    stalled: u32,
}

impl Ledger {
    fn is_empty(&self) -> bool {
        *self == Ledger::default()
    }

    /// Count a delivery: the deliveries in a row without a newer checkpoint, this one
    /// included.
    fn deliver(&mut self) -> u32 {
        self.stalled = if self.checkpoint == self.at_delivery {
            self.stalled.saturating_add(1)
        } else {
            1
        };
        self.at_delivery = self.checkpoint;
        self.stalled
    }
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
            // Filled in by the caller that needs it ([`KvStore::server_stored_bytes`]).
            server_stored_bytes: 0,
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

#[cfg(test)]
mod tests {
    use super::Ledger;

    /// The same cases as the embedded store's ledger test, on the NATS record's ledger.
    #[test]
    fn deliveries_count_only_runs_that_made_no_progress() {
        let mut l = Ledger::default();
        assert_eq!(l.deliver(), 1, "a new job");
        assert_eq!(l.deliver(), 2, "died before any checkpoint");
        l.checkpoint = Some(40);
        assert_eq!(l.deliver(), 1, "died after a new checkpoint");
        assert_eq!(l.deliver(), 2, "died before the next one");
        assert_eq!(l.deliver(), 3);
        l.stalled = 0; // handed back in order (`requeue`)
        assert_eq!(l.deliver(), 1);
        // A record from before the ledger reads as a job never delivered.
        let old: Ledger = serde_json::from_str("{}").expect("empty ledger");
        assert!(old.is_empty());
    }
}
