//! The NATS [`WorkQueue`]: the work-queue stream `WILLOW_JOBS` and the durable pull consumer
//! `willow-workers` that every worker node shares.
//!
//! - **Admission** is the stream's: `max_msgs` = capacity with discard-new, so a publish
//!   beyond it is refused by the server whichever API node sends it (jobs waiting and jobs
//!   running count, since a message leaves a work-queue stream when it is acked).
//! - **Leases**: a worker fetches one message at a time (no prefetch, so an idle node never
//!   sits on jobs another could run); heartbeats are progress acks, which restart `ack_wait`;
//!   a worker that dies stops them, and the server delivers the job again after `ack_wait`,
//!   up to `max_deliver`.
//! - **Withdrawing** a queued job deletes its message by sequence (kept in KV at push).

use super::super::ports::{Lease, LeaseControl, Recovered, WorkQueue};
use super::super::JobError;
use super::{error_chain, nats_err, Nats, JOBS_SUBJECT};
use async_nats::jetstream::consumer::{pull, Consumer};
use async_nats::jetstream::message::AckKind;
use async_nats::jetstream::stream::Stream;
use async_trait::async_trait;
use futures::StreamExt;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// How long one fetch waits for a job before asking again.
const FETCH_WAIT: Duration = Duration::from_secs(5);
/// How often the depth gauge and the connection flag are refreshed.
const REFRESH: Duration = Duration::from_millis(500);

pub(crate) struct NatsQueue {
    nats: Arc<Nats>,
    stream: Stream,
    consumer: Consumer<pull::Config>,
    capacity: usize,
    depth: Arc<AtomicUsize>,
    connected: Arc<AtomicBool>,
}

impl NatsQueue {
    /// The queue, and a task that keeps its depth and connection state fresh.
    pub fn start(
        nats: Arc<Nats>,
        stream: Stream,
        consumer: Consumer<pull::Config>,
        capacity: usize,
    ) -> NatsQueue {
        let depth = Arc::new(AtomicUsize::new(0));
        let connected = Arc::new(AtomicBool::new(true));
        let (d, c, client, mut consumer2) = (
            Arc::downgrade(&depth),
            connected.clone(),
            nats.client.clone(),
            consumer.clone(),
        );
        tokio::spawn(async move {
            loop {
                let Some(depth) = d.upgrade() else { return };
                let up = client.connection_state() == async_nats::connection::State::Connected;
                c.store(up, Ordering::Relaxed);
                if up {
                    if let Ok(info) = consumer2.info().await {
                        depth.store(info.num_pending as usize, Ordering::Relaxed);
                    }
                }
                drop(depth);
                tokio::time::sleep(REFRESH).await;
            }
        });
        NatsQueue {
            nats,
            stream,
            consumer,
            capacity,
            depth,
            connected,
        }
    }
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

/// Publish job `id` on the work queue as message `msg_id` (the stream drops a second message
/// with one id within its duplicate window, so a retried publish is one job), and record its
/// sequence for [`WorkQueue::withdraw`]. `QueueFull` when the stream is at capacity.
async fn publish_job(nats: &Nats, id: &str, msg_id: &str) -> Result<(), JobError> {
    let mut headers = async_nats::HeaderMap::new();
    headers.insert("Nats-Msg-Id", msg_id);
    let ack = nats
        .js
        .publish_with_headers(JOBS_SUBJECT, headers, id.to_string().into())
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
    Ok(())
}

#[async_trait]
impl WorkQueue for NatsQueue {
    async fn push(&self, _tenant: &str, id: &str) -> Result<(), JobError> {
        match publish_job(&self.nats, id, id).await {
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
        loop {
            let mut batch = self
                .consumer
                .fetch()
                .max_messages(1)
                .expires(FETCH_WAIT)
                .messages()
                .await
                .map_err(|e| nats_err("fetching a job", e))?;
            // Nothing within FETCH_WAIT: ask again.
            if let Some(m) = batch.next().await {
                let message = match m {
                    Ok(m) => m,
                    Err(e) => return Err(nats_err("fetching a job", e)),
                };
                let attempt = message
                    .info()
                    .map(|i| u32::try_from(i.delivered).unwrap_or(u32::MAX))
                    .unwrap_or(1);
                let id = String::from_utf8_lossy(&message.payload).into_owned();
                return Ok(Lease {
                    id: id.clone(),
                    attempt,
                    control: Arc::new(NatsLease {
                        message,
                        nats: self.nats.clone(),
                        id,
                    }),
                });
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
        self.connected.load(Ordering::Relaxed)
    }
}
