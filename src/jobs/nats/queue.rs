//! The NATS [`WorkQueue`]: the work-queue stream `WILLOW_JOBS`, one durable pull consumer per
//! tenant, and workers that take turns between the tenants.
//!
//! - **Admission** is the stream's: `max_msgs` = capacity with discard-new, so a publish
//!   beyond it is refused by the server whichever API node sends it (jobs waiting and jobs
//!   running count, since a message leaves a work-queue stream when it is acked).
//! - **Fairness**: a job is published on `willow.jobs.{tenant}`. A worker looking for work
//!   asks the stream which tenants' subjects hold messages, and fetches from the consumer of
//!   the tenant this node served least recently (then the next, when that one has nothing
//!   deliverable). One tenant's burst therefore delays another tenant's job by about one job
//!   per worker, not by the burst. The order is each node's own: across nodes it is
//!   approximately, not exactly, round-robin.
//! - **Leases**: a worker fetches one message at a time (no prefetch, so an idle node never
//!   sits on jobs another could run); heartbeats are progress acks, which restart `ack_wait`;
//!   a worker that dies stops them, and the server delivers the job again after `ack_wait`,
//!   up to `max_deliver`.
//! - **Waiting**: an idle worker sleeps until a job is queued (the publisher sends a core
//!   message on [`WAKE_SUBJECT`] once the stream has stored the job) or [`idle_look`] of
//!   `ack_wait` passes, then looks again; the second covers redeliveries, which publish
//!   nothing, so a crashed worker's job waits at most a fifth of `ack_wait` past its
//!   redelivery.
//! - **Withdrawing** a queued job deletes its message by sequence (kept in KV at push).

use super::super::ports::{Lease, LeaseControl, Recovered, WorkQueue};
use super::super::JobError;
use super::{error_chain, nats_err, Nats, JOBS_SUBJECT, WORKERS_CONSUMER};
use async_nats::jetstream::consumer::{pull, Consumer};
use async_nats::jetstream::message::AckKind;
use async_nats::jetstream::stream::Stream;
use async_trait::async_trait;
use futures::StreamExt;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The longest an idle worker sleeps before it looks for jobs again without being woken.
const FETCH_WAIT: Duration = Duration::from_secs(5);
/// The shortest: a fetch request a fifth of a second per idle worker is still nothing to the
/// server.
const FETCH_WAIT_MIN: Duration = Duration::from_millis(200);

/// How long an idle worker sleeps between looks when nothing wakes it: a fifth of
/// `ack_wait`, within [`FETCH_WAIT_MIN`, `FETCH_WAIT`]. Redeliveries publish nothing, so
/// this is how late a crashed worker's job can be picked up after the server delivers it
/// again; a fixed 5 s doubled the recovery time at `--nats-ack-wait-secs 5` (the load
/// benchmark's part 6 figures, docs/measurements.md).
fn idle_look(ack_wait: Duration) -> Duration {
    (ack_wait / 5).clamp(FETCH_WAIT_MIN, FETCH_WAIT)
}
/// Core subject (outside the jobs stream) that tells idle workers a job was stored.
const WAKE_SUBJECT: &str = "willow.wake.jobs";
/// A tenant's consumer unused this long is removed by the server (created again on demand).
const TENANT_CONSUMER_IDLE: Duration = Duration::from_secs(3600);
/// How often the depth gauge and the connection flag are refreshed.
const REFRESH: Duration = Duration::from_millis(500);

pub(crate) struct NatsQueue {
    nats: Arc<Nats>,
    stream: Stream,
    /// Jobs published on `willow.jobs` before tenants.
    legacy: Consumer<pull::Config>,
    /// Settings of the tenants' consumers (ack wait, deliveries).
    template: pull::Config,
    /// An idle worker's sleep between looks ([`idle_look`] of the ack wait).
    idle_look: Duration,
    /// Tenant → its consumer, as created or found.
    consumers: tokio::sync::Mutex<HashMap<String, Consumer<pull::Config>>>,
    /// Tenant → the turn this node last served it at; a tenant never served sorts first.
    served: Mutex<HashMap<String, u64>>,
    turn: AtomicU64,
    /// Bumped whenever a job is queued (seen through the wake-up subscription).
    published: tokio::sync::watch::Receiver<u64>,
    capacity: usize,
    depth: Arc<AtomicUsize>,
    connected: Arc<AtomicBool>,
}

/// The subject jobs of `tenant` are published on.
fn tenant_subject(tenant: &str) -> String {
    format!("{JOBS_SUBJECT}.{tenant}")
}

/// A consumer name holds no `.`, which tenant ids may: a digest of the id instead.
fn tenant_consumer(tenant: &str) -> String {
    let h = Sha256::digest(tenant.as_bytes());
    let hex: String = h.iter().take(10).map(|b| format!("{b:02x}")).collect();
    format!("{WORKERS_CONSUMER}-{hex}")
}

impl NatsQueue {
    /// The queue, and a task that keeps its depth and connection state fresh.
    pub fn start(
        nats: Arc<Nats>,
        stream: Stream,
        legacy: Consumer<pull::Config>,
        template: pull::Config,
        capacity: usize,
    ) -> NatsQueue {
        let depth = Arc::new(AtomicUsize::new(0));
        let connected = Arc::new(AtomicBool::new(true));
        let (d, c, client, mut stream2) = (
            Arc::downgrade(&depth),
            connected.clone(),
            nats.client.clone(),
            stream.clone(),
        );
        tokio::spawn(async move {
            loop {
                let Some(depth) = d.upgrade() else { return };
                let up = client.connection_state() == async_nats::connection::State::Connected;
                c.store(up, Ordering::Relaxed);
                if up {
                    if let Some(waiting) = waiting_jobs(&mut stream2).await {
                        depth.store(waiting, Ordering::Relaxed);
                    }
                }
                drop(depth);
                tokio::time::sleep(REFRESH).await;
            }
        });
        let (tx, published) = tokio::sync::watch::channel(0u64);
        let client = nats.client.clone();
        tokio::spawn(async move {
            let Ok(mut sub) = client.subscribe(WAKE_SUBJECT).await else {
                // Without it idle workers still look every `idle_look`.
                return;
            };
            while sub.next().await.is_some() {
                tx.send_modify(|n| *n = n.wrapping_add(1));
                if tx.is_closed() {
                    return;
                }
            }
        });
        NatsQueue {
            nats,
            stream,
            legacy,
            idle_look: idle_look(template.ack_wait),
            template,
            consumers: tokio::sync::Mutex::new(HashMap::new()),
            served: Mutex::new(HashMap::new()),
            turn: AtomicU64::new(0),
            published,
            capacity,
            depth,
            connected,
        }
    }

    /// Tenants with messages in the stream (waiting or leased), least recently served first.
    async fn tenants_in_turn(&self) -> Result<Vec<String>, JobError> {
        let prefix = format!("{JOBS_SUBJECT}.");
        let mut subjects = self
            .stream
            .clone()
            .info_with_subjects(format!("{JOBS_SUBJECT}.>"))
            .await
            .map_err(|e| nats_err("listing the tenants with jobs", e))?;
        let mut tenants = Vec::new();
        while let Some(s) = subjects.next().await {
            let (subject, count) = s.map_err(|e| nats_err("listing the tenants with jobs", e))?;
            if count > 0 {
                if let Some(t) = subject.strip_prefix(&prefix) {
                    tenants.push(t.to_string());
                }
            }
        }
        let served = self.served.lock().unwrap_or_else(|p| p.into_inner());
        tenants.sort_by_key(|t| (served.get(t).copied().unwrap_or(0), t.clone()));
        Ok(tenants)
    }

    /// `tenant`'s consumer, created on first use.
    async fn consumer(&self, tenant: &str) -> Result<Consumer<pull::Config>, JobError> {
        let mut consumers = self.consumers.lock().await;
        if let Some(c) = consumers.get(tenant) {
            return Ok(c.clone());
        }
        let config = pull::Config {
            durable_name: Some(tenant_consumer(tenant)),
            filter_subject: tenant_subject(tenant),
            inactive_threshold: TENANT_CONSUMER_IDLE,
            ..self.template.clone()
        };
        let consumer = match self.stream.create_consumer(config.clone()).await {
            Ok(c) => c,
            // Exists with other settings (an earlier ack_wait): update it.
            Err(_) => self
                .stream
                .update_consumer(config)
                .await
                .map_err(|e| nats_err("creating a tenant's consumer", e))?,
        };
        consumers.insert(tenant.to_string(), consumer.clone());
        Ok(consumer)
    }

    fn mark_served(&self, tenant: &str) {
        let turn = self.turn.fetch_add(1, Ordering::Relaxed) + 1;
        let mut served = self.served.lock().unwrap_or_else(|p| p.into_inner());
        served.insert(tenant.to_string(), turn);
        // Forget the oldest turns once many tenants came and went: a forgotten tenant sorts
        // first again, which is only fair to a tenant that was idle.
        if served.len() > 4096 {
            let mut turns: Vec<u64> = served.values().copied().collect();
            turns.sort_unstable();
            let cut = turns[turns.len() / 2];
            served.retain(|_, t| *t >= cut);
        }
    }

    fn lease_of(&self, message: async_nats::jetstream::Message) -> Lease {
        let attempt = message
            .info()
            .map(|i| u32::try_from(i.delivered).unwrap_or(u32::MAX))
            .unwrap_or(1);
        let id = String::from_utf8_lossy(&message.payload).into_owned();
        Lease {
            id: id.clone(),
            attempt,
            control: Arc::new(NatsLease {
                message,
                nats: self.nats.clone(),
                id,
            }),
        }
    }
}

/// One message deliverable now from `consumer`, without waiting.
async fn fetch_one(
    consumer: &Consumer<pull::Config>,
) -> Result<Option<async_nats::jetstream::Message>, JobError> {
    let mut batch = consumer
        .fetch()
        .max_messages(1)
        .messages()
        .await
        .map_err(|e| nats_err("fetching a job", e))?;
    match batch.next().await {
        Some(Ok(m)) => Ok(Some(m)),
        Some(Err(e)) => Err(nats_err("fetching a job", e)),
        None => Ok(None),
    }
}

/// Jobs waiting for a worker: the stream's messages less those leased (acked or not yet).
async fn waiting_jobs(stream: &mut Stream) -> Option<usize> {
    let total = stream.info().await.ok()?.state.messages;
    let mut leased = 0u64;
    let mut consumers = stream.consumers();
    while let Some(info) = consumers.next().await {
        leased += info.ok()?.num_ack_pending as u64;
    }
    usize::try_from(total.saturating_sub(leased)).ok()
}

struct NatsLease {
    message: async_nats::jetstream::Message,
    nats: Arc<Nats>,
    id: String,
}

#[async_trait]
impl LeaseControl for NatsLease {
    async fn heartbeat(&self) -> Result<(), JobError> {
        self.message
            .ack_with(AckKind::Progress)
            .await
            .map_err(|e| nats_err("heartbeat", e))
    }

    async fn ack(&self) -> Result<(), JobError> {
        // Double ack: wait for the server to confirm, so a job never runs twice because an
        // ack was lost.
        self.message
            .double_ack()
            .await
            .map_err(|e| nats_err("ack", e))
    }

    /// A clean hand-back (shutdown, the backend away) must not count as a delivery that
    /// killed its worker, or a long job would fail `max_deliver` after a few rolling updates:
    /// the job is queued again as a new message (a fresh delivery count) and the old one
    /// acked. Only if that publish is refused (the stream full) is the old one nak'ed, which
    /// keeps its place and its count.
    async fn release(&self) -> Result<(), JobError> {
        match publish_job(
            &self.nats,
            self.message.subject.as_str(),
            &self.id,
            &format!("{}.{}", self.id, uuid::Uuid::new_v4()),
        )
        .await
        {
            Ok(()) => self
                .message
                .double_ack()
                .await
                .map_err(|e| nats_err("ack", e)),
            Err(e) => {
                tracing::warn!(job_id = %self.id, error = %e, "could not queue the job again: nak");
                self.message
                    .ack_with(AckKind::Nak(None))
                    .await
                    .map_err(|e| nats_err("nak", e))
            }
        }
    }
}

/// Publish job `id` on the work queue's `subject` as message `msg_id` (the stream drops a
/// second message with one id within its duplicate window, so a retried publish is one job),
/// and record its sequence for [`WorkQueue::withdraw`]. `QueueFull` when the stream is at
/// capacity.
async fn publish_job(nats: &Nats, subject: &str, id: &str, msg_id: &str) -> Result<(), JobError> {
    let mut headers = async_nats::HeaderMap::new();
    headers.insert("Nats-Msg-Id", msg_id);
    let ack = nats
        .js
        .publish_with_headers(subject.to_string(), headers, id.to_string().into())
        .await
        .map_err(|e| nats_err("queueing a job", e))?
        .await;
    let ack = match ack {
        Ok(a) => a,
        Err(e) => {
            let text = error_chain(&e);
            if text.contains("maximum messages") {
                return Err(JobError::QueueFull {
                    retry_after_secs: 1,
                    capacity: 0,
                });
            }
            return Err(nats_err("queueing a job", text));
        }
    };
    nats.kv
        .put(format!("qseq.{id}"), ack.sequence.to_string().into())
        .await
        .map_err(|e| nats_err("recording a job's queue entry", e))?;
    // After the stream's ack: a woken worker finds the job stored. Best effort: a lost wake-up
    // costs at most `idle_look`.
    let _ = nats.client.publish(WAKE_SUBJECT, bytes::Bytes::new()).await;
    Ok(())
}

#[async_trait]
impl WorkQueue for NatsQueue {
    async fn push(&self, tenant: &str, id: &str) -> Result<(), JobError> {
        match publish_job(&self.nats, &tenant_subject(tenant), id, id).await {
            Err(JobError::QueueFull {
                retry_after_secs, ..
            }) => Err(JobError::QueueFull {
                retry_after_secs,
                capacity: self.capacity,
            }),
            other => {
                other?;
                self.depth.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    async fn push_recovered(&self, job: Recovered) -> Result<(), JobError> {
        self.push(&job.tenant, &job.id).await
    }

    async fn lease(&self) -> Result<Lease, JobError> {
        let mut published = self.published.clone();
        loop {
            published.borrow_and_update();
            for tenant in self.tenants_in_turn().await? {
                let consumer = self.consumer(&tenant).await?;
                match fetch_one(&consumer).await {
                    Ok(Some(message)) => {
                        self.mark_served(&tenant);
                        return Ok(self.lease_of(message));
                    }
                    // Its messages are all leased: the next tenant.
                    Ok(None) => {}
                    Err(e) => {
                        // Removed by the server after a long idle time: made again next turn.
                        self.consumers.lock().await.remove(&tenant);
                        tracing::debug!(tenant, error = %e, "fetch from a tenant's consumer failed");
                    }
                }
            }
            if let Some(message) = fetch_one(&self.legacy).await? {
                return Ok(self.lease_of(message));
            }
            // Nothing deliverable: sleep until a job is queued or `idle_look` passes (a
            // redelivery after `ack_wait` publishes nothing).
            if let Ok(Err(_)) = tokio::time::timeout(self.idle_look, published.changed()).await {
                // No wake-ups (the subscription failed): look every `idle_look`.
                tokio::time::sleep(self.idle_look).await;
            }
        }
    }

    async fn withdraw(&self, id: &str) -> Result<bool, JobError> {
        let key = format!("qseq.{id}");
        let Some(seq) = self
            .nats
            .kv
            .get(&key)
            .await
            .map_err(|e| nats_err("reading a job's queue entry", e))?
        else {
            return Ok(false);
        };
        let Some(seq) = std::str::from_utf8(&seq)
            .ok()
            .and_then(|s| s.parse::<u64>().ok())
        else {
            return Ok(false);
        };
        let deleted = self.stream.delete_message(seq).await.unwrap_or(false);
        if deleted {
            let _ = self.nats.kv.purge(&key).await;
            // Saturating: the refresh task may have counted this job out already.
            let _ = self
                .depth
                .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |d| d.checked_sub(1));
        }
        Ok(deleted)
    }

    fn depth(&self) -> usize {
        self.depth.load(Ordering::Relaxed)
    }

    fn capacity(&self) -> usize {
        self.capacity
    }

    fn connected(&self) -> bool {
        // The client's own state, not the refresher's copy: a request checks it before it
        // waits on NATS, and the copy lags by up to a refresh (longer if a refresh's call
        // was caught by the outage).
        self.connected.load(Ordering::Relaxed)
            && self.nats.client.connection_state() == async_nats::connection::State::Connected
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_idle_worker_looks_a_fifth_of_ack_wait_apart_within_its_bounds() {
        assert_eq!(idle_look(Duration::from_secs(5)), Duration::from_secs(1));
        assert_eq!(idle_look(Duration::from_secs(10)), Duration::from_secs(2));
        // The default ack wait (30 s) and longer keep the 5 s ceiling.
        assert_eq!(idle_look(Duration::from_secs(30)), FETCH_WAIT);
        assert_eq!(idle_look(Duration::from_secs(600)), FETCH_WAIT);
        // The 1 s minimum ack wait: not a tight loop.
        assert_eq!(idle_look(Duration::from_secs(1)), FETCH_WAIT_MIN);
    }
}
