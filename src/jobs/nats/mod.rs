//! The NATS JetStream backend: many API nodes and many workers on one NATS.
//!
//! | port | JetStream |
//! |---|---|
//! | [`WorkQueue`](super::ports::WorkQueue) | stream `WILLOW_JOBS` (work-queue retention, `max_msgs` = capacity, discard new) on `willow.jobs.{tenant}`, one durable pull consumer per tenant that workers take turns on (fair between tenants): explicit ack, `ack_wait`, progress acks as heartbeats, `max_deliver` |
//! | [`JobStore`](super::ports::JobStore) | KV bucket `willow-jobs` (records, idempotency keys, uploads, queue sequence numbers, cancel marks); per-step metrics in stream `WILLOW_FRAMES` (limits retention, `max_age` = the result TTL) on `willow.frames.{id}` |
//! | [`BlobStore`](super::ports::BlobStore) | object store `willow-blobs` |
//! | [`EventBus`](super::ports::EventBus) | core subjects `willow.live.{id}` (frames) and `willow.events.{id}` (states): any API node streams any job |
//! | [`CancelBus`](super::ports::CancelBus) | a `cancel.{id}` mark in KV plus `willow.cancel.{id}`, which every worker node subscribes to |
//!
//! Everything is created on first connect (`create_or_update`, so a changed capacity or
//! `ack_wait` takes effect). Durable state lives in NATS only: a node's data dir is scratch.

mod bus;
mod errors;
mod kv;
mod objects;
mod queue;

use super::ports::{request_deadline, Backend};
use super::{Config, JobError};
use async_nats::jetstream::{self, consumer, stream};
pub(crate) use errors::nats_err;
use std::sync::Arc;
use std::time::Duration;

/// The work-queue stream and its subject: jobs are published on `willow.jobs.{tenant}`.
pub const JOBS_STREAM: &str = "WILLOW_JOBS";
pub const JOBS_SUBJECT: &str = "willow.jobs";
/// The durable pull consumer of jobs queued before tenants, on `willow.jobs` itself; each
/// tenant's consumer is `willow-workers-{hash of the tenant}`.
pub const WORKERS_CONSUMER: &str = "willow-workers";
/// The stream of per-step metrics, one subject per job.
pub const FRAMES_STREAM: &str = "WILLOW_FRAMES";
pub const KV_BUCKET: &str = "willow-jobs";
pub const OBJECT_BUCKET: &str = "willow-blobs";

/// The default of [`NatsOptions::request_timeout`]: a healthy NATS answers in milliseconds,
/// and a client told 503 with `Retry-After: 2` within ~3 s can retry or fail over; long
/// enough for a KV update's compare-and-set retries on a loaded server.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(3);

/// The default of [`NatsOptions::call_timeout`]: the client's defaults (5 s for JetStream,
/// 10 s for a request) made a request that met an outage wait 10-25 s before its first retry.
pub const CALL_TIMEOUT: Duration = Duration::from_millis(2500);

/// How the NATS backend runs, beyond the core's [`Config`].
#[derive(Clone, Debug)]
pub struct NatsOptions {
    /// `nats://host:port`.
    pub url: String,
    /// Redelivery of a job whose worker stopped heartbeating (the heartbeat interval is a
    /// third of it).
    pub ack_wait: Duration,
    /// How long start-up waits for NATS before it gives up.
    pub connect_timeout: Duration,
    /// How long a client's request waits on NATS before it answers `unavailable` (503 +
    /// `Retry-After`): [`Backend::request_timeout`].
    pub request_timeout: Duration,
    /// How long one NATS call (a request, a publish's ack) waits for its answer.
    pub call_timeout: Duration,
    /// How long chunks that no blob names must stay so before the sweep purges them (what a
    /// writer killed between its chunks and its info leaves): far past any write's retries,
    /// so a write in flight is never taken for one. Also the least time between two scans.
    pub orphan_min_age: Duration,
}

/// The default of [`NatsOptions::orphan_min_age`].
pub const ORPHAN_MIN_AGE: Duration = Duration::from_secs(600);

impl NatsOptions {
    pub fn new(url: impl Into<String>) -> NatsOptions {
        NatsOptions {
            url: url.into(),
            ack_wait: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(30),
            request_timeout: REQUEST_TIMEOUT,
            call_timeout: CALL_TIMEOUT,
            orphan_min_age: ORPHAN_MIN_AGE,
        }
    }
}

/// What the ports of this backend share.
pub(crate) struct Nats {
    pub client: async_nats::Client,
    pub js: jetstream::Context,
    pub kv: jetstream::kv::Store,
}

/// Run `op` again, with a short backoff, while it fails with [`JobError::Unavailable`]: an
/// operation in flight when the connection dropped times out after the client has already
/// reconnected, and a second try then succeeds. Only for operations that may be repeated.
///
/// On a client's request ([`request_deadline`] set) no try starts after the deadline: the
/// request answers `unavailable` within its budget instead of waiting out the outage (issue
/// 25: `GET /v1/jobs/{id}` blocked for a 20 s outage). Each NATS call is bounded by
/// [`NatsOptions::call_timeout`]. Off the request path (workers) the tries ride out a short
/// restart.
async fn retry<T, F, Fut>(mut op: F) -> Result<T, JobError>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, JobError>>,
{
    let deadline = request_deadline();
    let mut pause = Duration::from_millis(250);
    for _ in 0..RETRIES {
        match op().await {
            Err(JobError::Unavailable(e)) => {
                if deadline.is_some_and(|d| std::time::Instant::now() + pause >= d) {
                    return Err(JobError::Unavailable(e));
                }
                tracing::info!(error = %e, "NATS operation retried");
                tokio::time::sleep(pause).await;
                pause *= 2;
            }
            other => return other,
        }
    }
    op().await
}

/// Tries of [`retry`] before the last: 0.25 + 0.5 + 1 + 2 s, which covers a server restart.
const RETRIES: usize = 4;

/// `e` and its sources, for matching server error texts that the client folds into `Other`.
fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        out.push_str(": ");
        out.push_str(&s.to_string());
        source = s.source();
    }
    out
}

/// Connect, create or update the streams, consumer, bucket and object store, and assemble the
/// ports. Retries the connection for `options.connect_timeout` (NATS may start after us).
pub async fn connect(config: &Config, options: &NatsOptions) -> Result<Backend, JobError> {
    let client = {
        let started = std::time::Instant::now();
        loop {
            // Reconnects forever once connected; the first connection we retry ourselves, so
            // a bad address fails start-up instead of hanging it.
            let attempt = async_nats::ConnectOptions::new()
                .name("willow")
                .max_reconnects(None)
                .connection_timeout(Duration::from_secs(5))
                .request_timeout(Some(options.call_timeout))
                .connect(options.url.as_str())
                .await;
            match attempt {
                Ok(c) => break c,
                Err(e) if started.elapsed() < options.connect_timeout => {
                    tracing::warn!(url = %options.url, error = %e, "NATS not reachable yet, retrying");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                }
                Err(e) => return Err(nats_err(&format!("connecting to {}", options.url), e)),
            }
        }
    };
    let mut js = jetstream::new(client.clone());
    js.set_timeout(options.call_timeout);
    js.create_or_update_stream(stream::Config {
        name: JOBS_STREAM.into(),
        subjects: vec![JOBS_SUBJECT.into(), format!("{JOBS_SUBJECT}.>")],
        retention: stream::RetentionPolicy::WorkQueue,
        // Admission is cluster-wide: a publish beyond this is refused by the server.
        max_messages: i64::try_from(config.queue_capacity).unwrap_or(i64::MAX),
        discard: stream::DiscardPolicy::New,
        storage: stream::StorageType::File,
        // Two submissions of one job id within this window are one message.
        duplicate_window: Duration::from_secs(120),
        ..Default::default()
    })
    .await
    .map_err(|e| nats_err("creating the jobs stream", e))?;
    let jobs_stream = js
        .get_stream(JOBS_STREAM)
        .await
        .map_err(|e| nats_err("opening the jobs stream", e))?;
    let template = consumer::pull::Config {
        ack_policy: consumer::AckPolicy::Explicit,
        ack_wait: options.ack_wait,
        // No limit here: the core counts the deliveries that made no progress
        // (`JobStore::delivered`) and fails the job with a reason past
        // `Config::max_deliveries`. A server-side count would also count the runs that died
        // after a new checkpoint, and drop a long job that made progress in silence.
        max_deliver: -1,
        ..Default::default()
    };
    // Only `willow.jobs` itself: a work-queue stream refuses consumers whose filters overlap,
    // and the tenants' consumers take `willow.jobs.{tenant}`.
    let workers = consumer::pull::Config {
        durable_name: Some(WORKERS_CONSUMER.into()),
        filter_subject: JOBS_SUBJECT.into(),
        ..template.clone()
    };
    let consumer = match jobs_stream.create_consumer(workers.clone()).await {
        Ok(c) => c,
        Err(_) => {
            // Exists with other settings (an earlier ack_wait): update it.
            jobs_stream
                .update_consumer(workers)
                .await
                .map_err(|e| nats_err("creating the workers' consumer", e))?
        }
    };
    js.create_or_update_stream(stream::Config {
        name: FRAMES_STREAM.into(),
        subjects: vec!["willow.frames.>".into()],
        retention: stream::RetentionPolicy::Limits,
        max_age: config.result_ttl,
        // One message per step: a step taken again after a resume replaces the first.
        max_messages_per_subject: 1,
        storage: stream::StorageType::File,
        allow_direct: true,
        ..Default::default()
    })
    .await
    .map_err(|e| nats_err("creating the frames stream", e))?;
    let kv = js
        .create_or_update_key_value(jetstream::kv::Config {
            bucket: KV_BUCKET.into(),
            history: 1,
            storage: stream::StorageType::File,
            ..Default::default()
        })
        .await
        .map_err(|e| nats_err("creating the KV bucket", e))?;
    // Made by the client's own call (its stream's settings are the object store's); written
    // and read by `objects` itself.
    match js.get_object_store(OBJECT_BUCKET).await {
        Ok(_) => {}
        Err(_) => {
            js.create_object_store(jetstream::object_store::Config {
                bucket: OBJECT_BUCKET.into(),
                storage: stream::StorageType::File,
                ..Default::default()
            })
            .await
            .map_err(|e| nats_err("creating the object store", e))?;
        }
    }
    // Blob reads are direct gets (see `objects`): a bucket made by an older client, or by
    // hand, may not allow them yet.
    let mut blobs_stream = js
        .get_stream(format!("OBJ_{OBJECT_BUCKET}"))
        .await
        .map_err(|e| nats_err("opening the object store's stream", e))?;
    if !blobs_stream.cached_info().config.allow_direct {
        let mut config = blobs_stream.cached_info().config.clone();
        config.allow_direct = true;
        js.update_stream(&config)
            .await
            .map_err(|e| nats_err("allowing direct gets on the object store", e))?;
        blobs_stream = js
            .get_stream(format!("OBJ_{OBJECT_BUCKET}"))
            .await
            .map_err(|e| nats_err("opening the object store's stream", e))?;
    }
    let frames = js
        .get_stream(FRAMES_STREAM)
        .await
        .map_err(|e| nats_err("opening the frames stream", e))?;
    let kv_stream = js
        .get_stream(format!("KV_{KV_BUCKET}"))
        .await
        .map_err(|e| nats_err("opening the KV stream", e))?;
    let nats = Arc::new(Nats {
        client: client.clone(),
        js: js.clone(),
        kv,
    });
    let queue = queue::NatsQueue::start(
        nats.clone(),
        jobs_stream,
        consumer,
        template,
        config.queue_capacity,
    );
    let cancels = bus::NatsCancels::start(nats.clone()).await?;
    tracing::info!(url = %options.url, "connected to NATS JetStream");
    let store = kv::KvStore::new(nats.clone(), frames, kv_stream);
    // Tenants' usage counters from the records: entries from before they existed, or left off
    // by a node that died mid-transition.
    store.heal_usage().await?;
    Ok(Backend {
        store: Arc::new(store),
        blobs: Arc::new(objects::ObjectBlobs::new(
            js.clone(),
            blobs_stream,
            OBJECT_BUCKET,
            options.orphan_min_age,
        )),
        queue: Arc::new(queue),
        events: Arc::new(bus::NatsBus::new(nats)),
        cancels: Arc::new(cancels),
        name: options.url.clone(),
        request_timeout: Some(options.request_timeout),
    })
}
