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

use super::super::ids::well_formed;
use super::super::ports::{BlobKey, BlobReader, BlobStore};
use super::super::{format_name, JobError, JobId};
use super::{nats_err, retry};
use async_nats::jetstream::object_store::{ObjectInfo, ObjectStore};
use async_nats::jetstream::stream::{DirectGetError, DirectGetErrorKind, Stream};
use async_trait::async_trait;
use base64::engine::general_purpose::URL_SAFE;
use base64::Engine;
use futures::StreamExt;
use sha2::{Digest, Sha256};

pub(crate) struct ObjectBlobs {
    store: ObjectStore,
    /// The bucket's stream (`OBJ_{bucket}`), with `allow_direct`: reads are direct gets on it.
    stream: Stream,
    bucket: String,
}

impl ObjectBlobs {
    /// `stream` is the bucket's stream, which must allow direct gets (see [`super::connect`]).
    pub fn new(store: ObjectStore, stream: Stream, bucket: &str) -> ObjectBlobs {
        ObjectBlobs {
            store,
            stream,
            bucket: bucket.to_string(),
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
        BlobKey::Rendered { id, step, format } => {
            let name = step.map_or_else(|| "result".to_string(), |s| s.to_string());
            format!("jobs/{id}/rendered/{name}.{}", format_name(*format))
        }
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
        // A put replaces the object whole once its last chunk is in: readers see the old
        // blob or the new one.
        retry(|| async {
            self.store
                .put(name.as_str(), &mut data.as_ref())
                .await
                .map_err(|e| nats_err("storing a blob", e))
        })
        .await?;
        Ok(())
    }

    async fn get(&self, key: BlobKey) -> Result<Option<bytes::Bytes>, JobError> {
        let name = name(&key)?;
        retry(|| self.get_once(&name)).await
    }

    async fn open(&self, key: BlobKey) -> Result<Option<BlobReader>, JobError> {
        let name = name(&key)?;
        let Some((info, info_sequence)) = retry(|| self.read_info(&name)).await? else {
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

    async fn delete(&self, key: BlobKey) -> Result<(), JobError> {
        let name = name(&key)?;
        match self.store.delete(name.as_str()).await {
            Ok(()) => Ok(()),
            Err(e) if e.to_string().contains("not found") => Ok(()),
            Err(e) => Err(nats_err("deleting a blob", e)),
        }
    }

    async fn delete_job(&self, id: &str) -> Result<(), JobError> {
        self.delete_job_blobs(id).await
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
    /// or it was deleted.
    async fn read_info(&self, name: &str) -> Result<Option<(ObjectInfo, u64)>, JobError> {
        let meta = format!("$O.{}.M.{}", self.bucket, URL_SAFE.encode(name));
        let message = match self.stream.direct_get_last_for_subject(meta).await {
            Ok(m) => m,
            Err(e) if e.kind() == DirectGetErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(direct_err("reading a blob's info", e)),
        };
        let info: ObjectInfo = serde_json::from_slice(&message.payload).map_err(|e| {
            JobError::Internal(format!("nats: blob {name} has an unreadable info: {e}"))
        })?;
        Ok((!info.deleted).then_some((info, message.sequence)))
    }

    /// One read of `name` by direct gets: its info, then its chunks in order.
    async fn read_direct(&self, name: &str) -> Result<Read, JobError> {
        let Some((info, info_sequence)) = self.read_info(name).await? else {
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
        for n in names {
            // Deleted objects keep their meta subject (a deletion marker): skip those.
            if matches!(self.read_info(&n).await, Ok(None)) {
                continue;
            }
            if let Err(e) = self.store.delete(n.as_str()).await {
                tracing::warn!(blob = %n, error = %e, "could not delete a blob");
            }
        }
        Ok(())
    }
}
