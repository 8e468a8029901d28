//! The embedded backend, the default: everything in one process and one data dir.
//!
//! - [`sqlite`]: job records, frames' metrics, idempotency keys and uploads (SQLite, WAL);
//! - [`files`]: inputs, frame positions, results, checkpoints and uploads as files;
//! - [`queue`]: a bounded in-memory FIFO (queued jobs are also in SQLite, and are queued
//!   again by the next start);
//! - [`broadcast`]: per-job broadcast channels and in-process cancellation tokens.

pub mod broadcast;
pub mod files;
pub mod queue;
pub mod sqlite;

use super::ports::Backend;
use super::JobError;
use std::path::Path;
use std::sync::Arc;

/// Open (creating if needed) the embedded backend in `dir`, with a queue of `capacity`.
pub fn open(dir: &Path, capacity: usize) -> Result<Backend, JobError> {
    let store = sqlite::SqliteStore::open(dir)?;
    let blobs = files::FileBlobs::open(dir)?;
    Ok(Backend {
        store: Arc::new(store),
        blobs: Arc::new(blobs),
        queue: Arc::new(queue::SharedQueue(Arc::new(queue::EmbeddedQueue::new(
            capacity,
        )))),
        events: Arc::new(broadcast::Broadcast::default()),
        cancels: Arc::new(broadcast::LocalCancels::default()),
        name: "embedded".into(),
        request_timeout: None,
    })
}
