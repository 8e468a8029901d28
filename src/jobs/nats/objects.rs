//! The NATS [`BlobStore`]: the object store `willow-blobs`, objects named like the embedded
//! backend's files (`jobs/{id}/input.obj`, `jobs/{id}/frames/3.f32`, …). The object store
//! chunks large blobs (a 1M-vertex frame is 12 MB) under the server's message size limit.
//!
//! Writes go through the client's object store (`put`, `delete`). Reads do not: the client's
//! `get` streams the chunks through an ordered consumer that the server keeps for ~30 s after
//! the read, and a stream holds at most 1000 consumers, so a busy API node (a read per live
//! frame per watcher) filled the bucket's stream with dead consumers within seconds and every
//! blob read failed after that. Here a read is direct gets only (the stream has
//! `allow_direct`): the object's info is the last message on its meta subject, then its chunks
//! one by one on the chunk subject, each the next after the previous one's sequence. Nothing
//! is left on the server, any node (or replica) answers, and the bytes are checked against
//! the info's size and SHA-256 digest. The layout is the object store's own, so objects stored
//! before this read path (or by other clients) read the same.
//!
//! Writes and deletes are this module's too, in the same layout (issue 25):
//! - **A write leaves no chunks behind.** The client's `put` publishes the chunks under a
//!   fresh id, then the info; a write cut midway (NATS stopped, JetStream full) left the
//!   chunks published so far under an id no info names, and every retry left another such
//!   set. Here each try's chunk id is known, so the chunks of a try that failed are purged
//!   (once the write succeeds, or at once when it finally fails), as are the replaced
//!   object's chunks.
//! - **A delete writes nothing**: the object's chunks are purged, then its info subject. The
//!   client's `delete` publishes a deletion marker first, which a JetStream over its
//!   `max_file_store` refuses, so no job could be deleted to make room.

use super::super::ids::well_formed;
use super::super::ports::{rendered_name, BlobKey, BlobReader, BlobStore};
use super::super::{format_name, JobError, JobId};
use super::{nats_err, retry};
use async_nats::jetstream::object_store::{ObjectInfo, ObjectOptions};
use async_nats::jetstream::stream::{DirectGetError, DirectGetErrorKind, Stream};
use async_nats::jetstream::{self, stream::PurgeError};
use async_trait::async_trait;
use base64::engine::general_purpose::URL_SAFE;
use base64::Engine;
use futures::StreamExt;
use sha2::{Digest, Sha256};
use std::collections::HashSet;

pub(crate) struct ObjectBlobs {
    js: jetstream::Context,
    /// The bucket's stream (`OBJ_{bucket}`), with `allow_direct`: reads are direct gets on it.
    stream: Stream,
    bucket: String,
    /// See [`super::NatsOptions::orphan_min_age`].
    orphan_min_age: std::time::Duration,
    /// Chunk ids no info named at the last scan, and when that scan was; `None` before the
    /// first.
    orphans_seen: std::sync::Mutex<Option<(std::time::Instant, HashSet<String>)>>,
}

impl ObjectBlobs {
    /// `stream` is the bucket's stream, which must allow direct gets (see [`super::connect`]).
    pub fn new(
        js: jetstream::Context,
        stream: Stream,
        bucket: &str,
        orphan_min_age: std::time::Duration,
    ) -> ObjectBlobs {
        ObjectBlobs {
            js,
            stream,
            bucket: bucket.to_string(),
            orphan_min_age,
            orphans_seen: std::sync::Mutex::new(None),
        }
    }
}

/// What one try at reading an object found.
enum Read {
    Found(bytes::Bytes),
    Missing,
    /// The object changed while its chunks were read (a put replaced it, or it was deleted,
    /// and its old chunks were purged): read it again from its info.
    Changed(String),
}

/// Reads of one blob that find it changing under them before the read gives up.
const READ_TRIES: usize = 5;

/// Allocation up front for a blob, whatever size its (stored, untrusted) info claims.
const MAX_PREALLOCATION: usize = 64 << 20;

/// Bytes per chunk message: the object store's own default (the Go and Rust clients'), under
/// any server's `max_payload`.
const CHUNK_BYTES: usize = 128 * 1024;

/// The object [`BlobStore::room`] writes (and purges again) to find whether JetStream has
/// room: not a name [`name`] can give, so no blob is ever replaced by it.
const ROOM_PROBE: &str = "willow/room-probe";

/// What the room probe writes: headroom for a job's next frames, as the embedded probe's
/// [`crate::jobs::storage::PROBE_BYTES`] is for a disk.
const ROOM_PROBE_BYTES: usize = crate::jobs::storage::PROBE_BYTES as usize;

/// A fresh id for one try's chunks (the object store calls it the object's nuid; any token
/// valid in a subject will do).
fn chunk_id() -> String {
    uuid::Uuid::new_v4().simple().to_string()
}

/// A purge's error as the core sees it.
fn purge_err(what: &str, e: PurgeError) -> JobError {
    nats_err(what, e)
}

/// A direct get's error as the core sees it: no answer in time or no responder (NATS away or
/// reconnecting) is worth retrying.
fn direct_err(what: &str, e: DirectGetError) -> JobError {
    match e.kind() {
        DirectGetErrorKind::TimedOut | DirectGetErrorKind::Request => {
            JobError::Unavailable(format!("nats: {what}: {e}"))
        }
        _ => nats_err(what, e),
    }
}

fn name(key: &BlobKey) -> Result<String, JobError> {
    if let Some(id) = key.job() {
        JobId::parse(id)?;
    }
    Ok(match key {
        BlobKey::Input { id, format } => format!("jobs/{id}/input.{}", format_name(*format)),
        BlobKey::Frame { id, step, welded } => {
            format!(
                "jobs/{id}/frames/{step}.{}",
                if *welded { "f64" } else { "f32" }
            )
        }
        BlobKey::Result { id } => format!("jobs/{id}/result.f64"),
        BlobKey::Checkpoint { id } => format!("jobs/{id}/checkpoint"),
        BlobKey::Rendered {
            id,
            step,
            format,
            source,
        } => format!(
            "jobs/{id}/rendered/{}",
            rendered_name(*step, *format, source.as_deref())
        ),
        BlobKey::Upload { id, format } => {
            if !well_formed(id) {
                return Err(JobError::UploadNotFound(id.clone()));
            }
            format!("uploads/{id}.{}", format_name(*format))
        }
    })
}

#[async_trait]
impl BlobStore for ObjectBlobs {
    async fn put(&self, key: BlobKey, data: bytes::Bytes) -> Result<(), JobError> {
        let name = name(&key)?;
        self.put_named(&name, &data).await
    }

    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError> {
        let name = name(&key)?;
        retry(|| self.get_once(&name)).await
    }

    async fn open(&self, key: BlobKey) -> Result<Option<BlobReader>, JobError> {
        let name = name(&key)?;
        let Some((info, info_sequence)) =
            retry(|| self.read_info(&name, "reading a blob's info")).await?
        else {
            return Ok(None);
        };
        if info.options.as_ref().is_some_and(|o| o.link.is_some()) {
            return Err(JobError::Internal(format!(
                "nats: blob {name} is a link, which this service never writes"
            )));
        }
        let len = info.size as u64;
        let chunks = futures::stream::try_unfold(
            ChunkReader {
                stream: self.stream.clone(),
                subject: format!("$O.{}.C.{}", self.bucket, info.nuid),
                next: 1,
                chunks_left: info.chunks,
                read: 0,
                digest: Sha256::new(),
                info,
                info_sequence,
                name,
            },
            |mut r| async move {
                match r.next_chunk().await? {
                    Some(chunk) => Ok(Some((chunk, r))),
                    None => Ok(None),
                }
            },
        );
        Ok(Some(BlobReader {
            len,
            chunks: Box::pin(chunks),
        }))
    }

    /// The object's SHA-256 digest from its info (one direct get), or its chunk id when the
    /// info has none (objects the client wrote without one): equal bytes, equal version.
    async fn version(&self, key: BlobKey) -> Result<Option<String>, JobError> {
        let name = name(&key)?;
        let info = retry(|| self.read_info(&name, "reading a blob's info")).await?;
        Ok(info.map(|(info, _)| {
            info.digest
                .as_deref()
                .and_then(|d| d.strip_prefix("SHA-256="))
                .map(|d| d.trim_end_matches('=').to_string())
                .unwrap_or(info.nuid)
        }))
    }

    async fn delete(&self, key: BlobKey) -> Result<(), JobError> {
        let name = name(&key)?;
        retry(|| self.purge_object(&name)).await
    }

    async fn delete_job(&self, id: &str) -> Result<(), JobError> {
        self.delete_job_blobs(id).await
    }

    /// Whether [`ROOM_PROBE_BYTES`] fit in JetStream now: written, then purged. A JetStream
    /// over its `max_file_store` (or the account's limit) refuses the first chunk.
    async fn room(&self) -> Option<bool> {
        let probe = bytes::Bytes::from(vec![0u8; ROOM_PROBE_BYTES]);
        // A probe refused midway leaves no chunks: `put_named` purges a failed try's.
        let fits = match self.put_named(ROOM_PROBE, &probe).await {
            Ok(()) => true,
            Err(JobError::StorageFull { .. }) => false,
            Err(e) => {
                tracing::debug!(error = %e, "probing JetStream for room");
                return Some(false);
            }
        };
        if let Err(e) = self.purge_object(ROOM_PROBE).await {
            tracing::warn!(error = %e, "could not remove the room probe");
        }
        Some(fits)
    }

    /// Chunk sets that no info names, found unnamed by two scans at least
    /// `orphan_min_age` apart, are purged: a writer killed between its chunks and its info
    /// (a crash, not a failed try, which `put_named` cleans up itself) leaves such a set,
    /// and a write in flight has its info within seconds. Scans no more often than that.
    async fn sweep_orphans(&self) -> Result<usize, JobError> {
        let now = std::time::Instant::now();
        let seen = {
            let guard = self.orphans_seen.lock().unwrap_or_else(|p| p.into_inner());
            match &*guard {
                Some((at, _)) if now.duration_since(*at) < self.orphan_min_age => return Ok(0),
                Some((_, seen)) => seen.clone(),
                None => HashSet::new(),
            }
        };
        let unnamed = self.unnamed_chunk_sets().await?;
        let mut purged = 0;
        let mut left = HashSet::new();
        for nuid in unnamed {
            if !seen.contains(&nuid) {
                left.insert(nuid);
                continue;
            }
            let subject = format!("$O.{}.C.{nuid}", self.bucket);
            match self.stream.purge().filter(subject.as_str()).await {
                Ok(_) => purged += 1,
                Err(e) => {
                    tracing::debug!(error = %e, "purging unnamed chunks");
                    left.insert(nuid);
                }
            }
        }
        *self.orphans_seen.lock().unwrap_or_else(|p| p.into_inner()) = Some((now, left));
        Ok(purged)
    }
}

/// An object read chunk by chunk with direct gets ([`BlobStore::open`]): one chunk in memory
/// at a time. Unlike a whole read, a read whose object changes under it cannot start over
/// (its first bytes are already sent): it ends with an error.
struct ChunkReader {
    stream: Stream,
    subject: String,
    /// The stream sequence to look for the next chunk from.
    next: u64,
    chunks_left: usize,
    read: usize,
    digest: Sha256,
    info: ObjectInfo,
    info_sequence: u64,
    name: String,
}

impl ChunkReader {
    /// The next chunk, `None` after the last; the last is checked against the info's size and
    /// digest before it is handed out.
    async fn next_chunk(&mut self) -> Result<Option<bytes::Bytes>, JobError> {
        if self.chunks_left == 0 {
            return Ok(None);
        }
        let changed = |why: String| {
            JobError::Internal(format!(
                "nats: blob {} changed while it was read: {why}",
                self.name
            ))
        };
        let (stream, subject, next) = (&self.stream, self.subject.as_str(), self.next);
        let chunk = retry(|| async move {
            match stream
                .direct_get_next_for_subject(subject, Some(next))
                .await
            {
                Ok(c) => Ok(Some(c)),
                Err(e) if e.kind() == DirectGetErrorKind::NotFound => Ok(None),
                Err(e) => Err(direct_err("reading a blob's chunk", e)),
            }
        })
        .await?
        .ok_or_else(|| changed(format!("chunk at byte {} is gone", self.read)))?;
        if chunk.sequence >= self.info_sequence {
            return Err(changed("a chunk is newer than the info".into()));
        }
        self.next = chunk.sequence + 1;
        self.chunks_left -= 1;
        self.read += chunk.payload.len();
        self.digest.update(&chunk.payload);
        if self.read > self.info.size {
            return Err(changed(format!(
                "more bytes than its info's {}",
                self.info.size
            )));
        }
        if self.chunks_left == 0 {
            if self.read != self.info.size {
                return Err(changed(format!(
                    "{} bytes in its chunks, {} in its info",
                    self.read, self.info.size
                )));
            }
            if let Some(want) = self.info.digest.as_deref() {
                let got = format!(
                    "SHA-256={}",
                    URL_SAFE.encode(std::mem::take(&mut self.digest).finalize())
                );
                if got != want {
                    return Err(changed(format!("digest {got}, its info says {want}")));
                }
            }
        }
        Ok(Some(chunk.payload))
    }
}

impl ObjectBlobs {
    /// Store `data` as object `name`, retried as [`retry`] does; the chunks of every try that
    /// failed are purged (see the module's doc).
    async fn put_named(&self, name: &str, data: &bytes::Bytes) -> Result<(), JobError> {
        // The chunk ids of failed tries, carried from one try to the next (a try holds them
        // while it runs; a lock is never held across an await).
        let carried = std::sync::Mutex::new(Vec::new());
        let take = || std::mem::take(&mut *carried.lock().unwrap_or_else(|p| p.into_inner()));
        let stored = retry(|| async {
            let mut tries = take();
            // A try after a failed one first removes that one's chunks (best effort: NATS
            // may still be away; they are purged again below).
            self.purge_failed_tries(name, &mut tries).await;
            let stored = self.put_once(name, data, &mut tries).await;
            *carried.lock().unwrap_or_else(|p| p.into_inner()) = tries;
            stored
        })
        .await;
        let mut failed_tries = take();
        if !failed_tries.is_empty() {
            // After a success the current info names this try's chunks, never a failed
            // try's; after a failure the current info may name a try whose info was stored
            // but not acknowledged, which `purge_failed_tries` keeps.
            self.purge_failed_tries(name, &mut failed_tries).await;
            if !failed_tries.is_empty() {
                tracing::warn!(blob = %name, tries = failed_tries.len(), "chunks of a failed blob write could not be removed");
            }
        }
        stored
    }

    /// One try at storing `name`: the chunks under a fresh id (pushed onto `tries` first, so
    /// a try that fails midway is known), then the info, which replaces the object's previous
    /// info whole (a rollup); then the previous version's chunks are purged.
    async fn put_once(
        &self,
        name: &str,
        data: &bytes::Bytes,
        tries: &mut Vec<String>,
    ) -> Result<(), JobError> {
        // Named as the write it belongs to, so an outage met here reads as a blob write's.
        let previous = self
            .read_info(name, "storing a blob (its current info)")
            .await?;
        let nuid = chunk_id();
        tries.push(nuid.clone());
        let chunks_subject = format!("$O.{}.C.{nuid}", self.bucket);
        let mut digest = Sha256::new();
        let mut chunks = 0;
        for start in (0..data.len()).step_by(CHUNK_BYTES) {
            // A view of `data`, not a copy.
            let chunk = data.slice(start..data.len().min(start + CHUNK_BYTES));
            digest.update(&chunk);
            chunks += 1;
            self.js
                .publish(chunks_subject.clone(), chunk)
                .await
                .map_err(|e| nats_err("storing a blob", format!("failed chunk publish: {e}")))?
                .await
                .map_err(|e| {
                    nats_err("storing a blob", format!("failed getting chunk ack: {e}"))
                })?;
        }
        let info = ObjectInfo {
            name: name.to_string(),
            description: None,
            metadata: Default::default(),
            headers: None,
            options: Some(ObjectOptions {
                link: None,
                max_chunk_size: Some(CHUNK_BYTES),
            }),
            bucket: self.bucket.clone(),
            nuid: nuid.clone(),
            size: data.len(),
            chunks,
            modified: None,
            digest: Some(format!("SHA-256={}", URL_SAFE.encode(digest.finalize()))),
            deleted: false,
        };
        let payload = serde_json::to_vec(&info)
            .map_err(|e| JobError::Internal(format!("nats: encoding a blob's info: {e}")))?;
        let mut headers = async_nats::HeaderMap::new();
        // Replace every earlier message on the info subject: one info per object.
        headers.insert("Nats-Rollup", "sub");
        self.js
            .publish_with_headers(self.meta_subject(name), headers, payload.into())
            .await
            .map_err(|e| nats_err("storing a blob", format!("failed publishing metadata: {e}")))?
            .await
            .map_err(|e| {
                nats_err(
                    "storing a blob",
                    format!("failed ack from metadata publish: {e}"),
                )
            })?;
        tries.pop();
        if let Some((old, _)) = previous.filter(|(old, _)| old.nuid != nuid) {
            let stale = format!("$O.{}.C.{}", self.bucket, old.nuid);
            // The write stands; a purge that fails leaves the old chunks, which is logged.
            if let Err(e) = retry(|| async {
                self.stream
                    .purge()
                    .filter(stale.as_str())
                    .await
                    .map_err(|e| purge_err("removing a replaced blob's chunks", e))
            })
            .await
            {
                tracing::warn!(blob = %name, error = %e, "chunks of a replaced blob could not be removed");
            }
        }
        Ok(())
    }

    /// Purge the chunks of the failed tries in `tries`, keeping any the current info names (a
    /// try whose info was stored though its ack was lost is the object now); what could not
    /// be purged stays in `tries`.
    async fn purge_failed_tries(&self, name: &str, tries: &mut Vec<String>) {
        if tries.is_empty() {
            return;
        }
        let current = match self.read_info(name, "reading a blob's info").await {
            Ok(info) => info.map(|(i, _)| i.nuid),
            // NATS still away: try again later.
            Err(_) => return,
        };
        let mut left = Vec::new();
        for nuid in tries.drain(..) {
            if current.as_deref() == Some(nuid.as_str()) {
                continue;
            }
            let subject = format!("$O.{}.C.{nuid}", self.bucket);
            if let Err(e) = self.stream.purge().filter(subject.as_str()).await {
                tracing::debug!(blob = %name, error = %e, "purging a failed write's chunks");
                left.push(nuid);
            }
        }
        *tries = left;
    }

    /// Remove object `name` without writing anything: its chunks, then its info subject (a
    /// reader between the two finds chunks gone and reads again, then finds no object).
    async fn purge_object(&self, name: &str) -> Result<(), JobError> {
        let meta = self.meta_subject(name);
        let message = match self.stream.direct_get_last_for_subject(meta.as_str()).await {
            Ok(m) => m,
            Err(e) if e.kind() == DirectGetErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(direct_err("reading a blob's info", e)),
        };
        // An unreadable info still gets its subject purged; its chunks cannot be named.
        if let Ok(info) = serde_json::from_slice::<ObjectInfo>(&message.payload) {
            if !info.nuid.is_empty() {
                let chunks = format!("$O.{}.C.{}", self.bucket, info.nuid);
                self.stream
                    .purge()
                    .filter(chunks.as_str())
                    .await
                    .map_err(|e| purge_err("deleting a blob's chunks", e))?;
            }
        }
        self.stream
            .purge()
            .filter(meta.as_str())
            .await
            .map_err(|e| purge_err("deleting a blob", e))?;
        Ok(())
    }

    /// The chunk ids in the stream that no object's info names (deletion markers name
    /// none). The infos are read after the chunk subjects are listed: a write that
    /// completes in between is named.
    async fn unnamed_chunk_sets(&self) -> Result<HashSet<String>, JobError> {
        let chunks_prefix = format!("$O.{}.C.", self.bucket);
        let meta_prefix = format!("$O.{}.M.", self.bucket);
        let mut unnamed = HashSet::new();
        let mut subjects = self
            .stream
            .info_with_subjects(format!("{chunks_prefix}>"))
            .await
            .map_err(|e| nats_err("listing blob chunks", e))?;
        while let Some(subject) = subjects.next().await {
            let (subject, _) = subject.map_err(|e| nats_err("listing blob chunks", e))?;
            if let Some(nuid) = subject.strip_prefix(chunks_prefix.as_str()) {
                unnamed.insert(nuid.to_string());
            }
        }
        if unnamed.is_empty() {
            return Ok(unnamed);
        }
        let mut metas = self
            .stream
            .info_with_subjects(format!("{meta_prefix}>"))
            .await
            .map_err(|e| nats_err("listing blobs", e))?;
        let mut meta_subjects = Vec::new();
        while let Some(subject) = metas.next().await {
            let (subject, _) = subject.map_err(|e| nats_err("listing blobs", e))?;
            meta_subjects.push(subject);
        }
        for subject in meta_subjects {
            let message = match self
                .stream
                .direct_get_last_for_subject(subject.as_str())
                .await
            {
                Ok(m) => m,
                Err(e) if e.kind() == DirectGetErrorKind::NotFound => continue,
                Err(e) => return Err(direct_err("reading a blob's info", e)),
            };
            if let Ok(info) = serde_json::from_slice::<ObjectInfo>(&message.payload) {
                unnamed.remove(&info.nuid);
            }
        }
        Ok(unnamed)
    }

    fn meta_subject(&self, name: &str) -> String {
        format!("$O.{}.M.{}", self.bucket, URL_SAFE.encode(name))
    }

    async fn get_once(&self, name: &str) -> Result<Option<bytes::Bytes>, JobError> {
        let mut last = String::new();
        for _ in 0..READ_TRIES {
            match self.read_direct(name).await? {
                Read::Found(b) => return Ok(Some(b)),
                Read::Missing => return Ok(None),
                Read::Changed(why) => {
                    tracing::debug!(blob = %name, %why, "blob changed while read, reading again");
                    last = why;
                }
            }
        }
        Err(JobError::Internal(format!(
            "nats: reading blob {name}: it kept changing while read ({last})"
        )))
    }

    /// The info of `name` and its sequence in the stream; `None` if there is no such object
    /// or it was deleted. `what` names the operation in an error.
    async fn read_info(
        &self,
        name: &str,
        what: &str,
    ) -> Result<Option<(ObjectInfo, u64)>, JobError> {
        let message = match self
            .stream
            .direct_get_last_for_subject(self.meta_subject(name))
            .await
        {
            Ok(m) => m,
            Err(e) if e.kind() == DirectGetErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(direct_err(what, e)),
        };
        let info: ObjectInfo = serde_json::from_slice(&message.payload).map_err(|e| {
            JobError::Internal(format!("nats: blob {name} has an unreadable info: {e}"))
        })?;
        Ok((!info.deleted).then_some((info, message.sequence)))
    }

    /// One read of `name` by direct gets: its info, then its chunks in order.
    async fn read_direct(&self, name: &str) -> Result<Read, JobError> {
        let Some((info, info_sequence)) = self.read_info(name, "reading a blob's info").await?
        else {
            return Ok(Read::Missing);
        };
        if info.options.as_ref().is_some_and(|o| o.link.is_some()) {
            return Err(JobError::Internal(format!(
                "nats: blob {name} is a link, which this service never writes"
            )));
        }
        let chunks_subject = format!("$O.{}.C.{}", self.bucket, info.nuid);
        let mut out = Vec::with_capacity(info.size.min(MAX_PREALLOCATION));
        let mut digest = Sha256::new();
        // A chunk is published before its info, so each is after the previous one and all are
        // before the info's own sequence.
        let mut next = 1;
        for _ in 0..info.chunks {
            let chunk = match self
                .stream
                .direct_get_next_for_subject(chunks_subject.as_str(), Some(next))
                .await
            {
                Ok(c) => c,
                Err(e) if e.kind() == DirectGetErrorKind::NotFound => {
                    return Ok(Read::Changed(format!(
                        "chunk {} of {} is gone",
                        out.len(),
                        info.size
                    )))
                }
                Err(e) => return Err(direct_err("reading a blob's chunk", e)),
            };
            if chunk.sequence >= info_sequence {
                return Ok(Read::Changed("a chunk is newer than the info".into()));
            }
            next = chunk.sequence + 1;
            digest.update(&chunk.payload);
            out.extend_from_slice(&chunk.payload);
            if out.len() > info.size {
                break;
            }
        }
        if out.len() != info.size {
            return Ok(Read::Changed(format!(
                "{} bytes in its chunks, {} in its info",
                out.len(),
                info.size
            )));
        }
        if let Some(want) = info.digest.as_deref() {
            let got = format!("SHA-256={}", URL_SAFE.encode(digest.finalize()));
            if got != want {
                return Ok(Read::Changed(format!("digest {got}, its info says {want}")));
            }
        }
        Ok(Read::Found(out.into()))
    }

    /// Every object under `jobs/{id}/`, found from the bucket's meta subjects (the stream's
    /// per-subject info, no consumer: the client's `list` leaves one behind like `get` did, and
    /// a sweep deletes many jobs at once).
    async fn delete_job_blobs(&self, id: &str) -> Result<(), JobError> {
        JobId::parse(id)?;
        let prefix = format!("jobs/{id}/");
        let meta = format!("$O.{}.M.", self.bucket);
        let mut subjects = self
            .stream
            .info_with_subjects(format!("{meta}>"))
            .await
            .map_err(|e| nats_err("listing blobs", e))?;
        let mut names = Vec::new();
        while let Some(subject) = subjects.next().await {
            let (subject, _) = subject.map_err(|e| nats_err("listing blobs", e))?;
            let name = subject
                .strip_prefix(meta.as_str())
                .and_then(|encoded| URL_SAFE.decode(encoded).ok())
                .and_then(|raw| String::from_utf8(raw).ok());
            if let Some(name) = name.filter(|n| n.starts_with(&prefix)) {
                names.push(name);
            }
        }
        let mut first_error = None;
        for n in names {
            // Objects deleted by a client's `delete` keep their info subject (a deletion
            // marker, chunks already gone): it is purged like any other.
            if let Err(e) = self.purge_object(&n).await {
                tracing::warn!(blob = %n, error = %e, "could not delete a blob");
                first_error.get_or_insert(e);
            }
        }
        // A job's DELETE must not answer success with its blobs still held (on a full
        // JetStream the DELETE is what makes room).
        first_error.map_or(Ok(()), Err)
    }
}
