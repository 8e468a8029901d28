//! Whether the data dir has room to write ([`StorageHealth`]), and the reserve file that keeps
//! a full disk manageable.
//!
//! A full disk is noticed where a write fails ([`JobError::StorageFull`]: ENOSPC, EDQUOT,
//! `SQLITE_FULL`). From then on, until a probe write succeeds again:
//! - readiness is false, with the reason (`/readyz`, gRPC health);
//! - submissions and uploads are refused at once with `storage_full` (507), so they do not eat
//!   the room the reserve freed;
//! - workers re-queue the job that met it and wait (it resumes from its checkpoint).
//!
//! **The reserve.** The embedded backend keeps a file of [`RESERVE_BYTES`] in its data dir.
//! The first full write releases it, so that what must still work on a full disk has room:
//! SQLite's WAL frames for a DELETE (a delete writes before it frees), the `-wal`/`-shm` files
//! a restart recreates, a running job's re-queue. A second, smaller file
//! ([`start_reserve_path`]) is released only by a start that cannot open the store otherwise:
//! the first one is spent by then if the server was stopped on a full disk. Both are written
//! again (with real bytes: a
//! sparse file reserves nothing) by the probe, and the probe counts as passed only once the
//! reserve is back *and* [`PROBE_BYTES`] more fit, so readiness returns with headroom.

use super::JobError;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// Size of the reserve file: room for a few hundred WAL frames (4 KiB pages), the `-shm`
/// index and a restart's schema check, with margin.
pub const RESERVE_BYTES: u64 = 4 << 20;

/// What the probe writes (and removes) after the reserve: headroom for a job's next frames.
pub const PROBE_BYTES: u64 = 1 << 20;

/// How often a full disk is probed, in seconds.
pub const STORAGE_PROBE_SECS: u64 = 2;

/// Without a data dir to probe (the NATS backend's storage is the server's) and a store that
/// cannot say whether it has room: how long after the last full write storage counts as full.
const REMOTE_FULL_MS: u64 = 30_000;

/// Size of the start reserve: what opening the database needs (SQLite recreates its `-wal`
/// and `-shm` files, removed by the last clean close, before it reads anything).
pub const START_RESERVE_BYTES: u64 = 1 << 20;

/// The reserve file in a data dir.
pub fn reserve_path(dir: &Path) -> PathBuf {
    dir.join("reserve")
}

/// The start reserve: released only by a start that cannot open the store otherwise, so a
/// server stopped on a full disk (whose reserve is spent) still starts and serves reads.
pub fn start_reserve_path(dir: &Path) -> PathBuf {
    dir.join("reserve-start")
}

/// Release both reserves for a start that failed to open the store; whether there was any to
/// release (and so whether trying again can help).
pub fn release_for_start(dir: &Path) -> bool {
    [reserve_path(dir), start_reserve_path(dir)]
        .iter()
        // Both, not the first that goes (no short-circuit).
        .filter(|p| std::fs::remove_file(p).is_ok())
        .count()
        > 0
}

/// Whether storage is known full, since when, and why.
pub struct StorageHealth {
    /// Unix ms since which storage is known full; 0: not known full.
    full_since: AtomicU64,
    /// The embedded backend's data dir (probed, holds the reserve); `None` for NATS.
    dir: Option<PathBuf>,
}

impl StorageHealth {
    pub fn new(dir: Option<PathBuf>) -> StorageHealth {
        StorageHealth {
            full_since: AtomicU64::new(0),
            dir,
        }
    }

    /// Whether storage is known full now.
    pub fn is_full(&self) -> bool {
        self.full_since.load(Ordering::SeqCst) != 0
    }

    /// `Err(StorageFull)` while storage is known full: what a write that needs room answers
    /// before trying.
    pub fn refuse_if_full(&self) -> Result<(), JobError> {
        if self.is_full() {
            return Err(JobError::StorageFull {
                detail: "storage is known full; waiting for the probe to find room".into(),
            });
        }
        Ok(())
    }

    /// Pass `e` on, having noted it if it says storage is full: the first such error marks
    /// storage full and releases the reserve.
    pub fn noted(&self, e: JobError) -> JobError {
        if let JobError::StorageFull { detail } = &e {
            self.mark_full(detail, super::now_ms());
        }
        e
    }

    /// [`StorageHealth::noted`] on a result.
    pub fn note<T>(&self, r: Result<T, JobError>) -> Result<T, JobError> {
        r.map_err(|e| self.noted(e))
    }

    fn mark_full(&self, detail: &str, now: u64) {
        let was = self.full_since.swap(now.max(1), Ordering::SeqCst);
        if was != 0 && self.dir.is_some() {
            // Already full (the remote case keeps the latest time: its window restarts).
            self.full_since.store(was, Ordering::SeqCst);
            return;
        }
        if was == 0 {
            tracing::error!(error = %detail, "storage full: not ready, new jobs refused, running jobs re-queued until there is room");
        }
        if let Some(dir) = &self.dir {
            match std::fs::remove_file(reserve_path(dir)) {
                Ok(()) => tracing::warn!(
                    bytes = RESERVE_BYTES,
                    "storage reserve released, for deletes and re-queues"
                ),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => tracing::warn!(error = %e, "could not release the storage reserve"),
            }
        }
    }

    /// Wait until storage has room again (the probe clears the mark) or `stop` is cancelled.
    pub async fn wait_for_room(&self, stop: &tokio_util::sync::CancellationToken) {
        let period = std::time::Duration::from_secs(STORAGE_PROBE_SECS);
        while self.is_full() && !stop.is_cancelled() {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = tokio::time::sleep(period) => {}
            }
        }
    }

    /// Check a full disk again (blocking: call on a blocking thread): with a data dir, the
    /// reserve is written back and [`PROBE_BYTES`] more must fit; without one, storage counts
    /// full for `REMOTE_FULL_MS` after the last full write. Returns whether storage is full.
    pub fn probe(&self, now: u64) -> bool {
        self.probe_with(now, None)
    }

    /// [`StorageHealth::probe`], where a remote store answered whether it has room (`remote`,
    /// from [`super::ports::BlobStore::room`]): its answer stands for the window's.
    pub fn probe_with(&self, now: u64, remote: Option<bool>) -> bool {
        let since = self.full_since.load(Ordering::SeqCst);
        if since == 0 {
            return false;
        }
        let room = match (&self.dir, remote) {
            (Some(dir), _) => ensure_reserve(dir).and_then(|()| probe_write(dir)).is_ok(),
            (None, Some(room)) => room,
            (None, None) => now.saturating_sub(since) >= REMOTE_FULL_MS,
        };
        if room {
            self.full_since.store(0, Ordering::SeqCst);
            tracing::info!("storage has room again: ready, jobs admitted and resumed");
        }
        !room
    }
}

/// Write the reserve files if they are missing or short (the start reserve first: it is the
/// one a restart needs). On failure nothing partial is left.
pub fn ensure_reserve(dir: &Path) -> std::io::Result<()> {
    ensure_file(&start_reserve_path(dir), START_RESERVE_BYTES)?;
    ensure_file(&reserve_path(dir), RESERVE_BYTES)
}

fn ensure_file(path: &Path, len: u64) -> std::io::Result<()> {
    if std::fs::metadata(path).is_ok_and(|m| m.len() >= len) {
        return Ok(());
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    let written = fill(&tmp, len).and_then(|()| std::fs::rename(&tmp, path));
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Whether [`PROBE_BYTES`] fit in `dir` now (the file is removed again).
fn probe_write(dir: &Path) -> std::io::Result<()> {
    let tmp = dir.join(".probe.tmp");
    let written = fill(&tmp, PROBE_BYTES);
    let _ = std::fs::remove_file(&tmp);
    written
}

/// Write `len` zero bytes to a new file at `path` and sync it (a file system that delays
/// allocation reports ENOSPC only then).
fn fill(path: &Path, len: u64) -> std::io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    let chunk = [0u8; 64 * 1024];
    let mut left = len;
    while left > 0 {
        let n = left.min(chunk.len() as u64) as usize;
        f.write_all(&chunk[..n])?;
        left -= n as u64;
    }
    f.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn full() -> JobError {
        JobError::from(std::io::Error::from(std::io::ErrorKind::StorageFull))
    }

    #[test]
    fn enospc_and_edquot_are_storage_full_other_io_errors_are_not() {
        assert_eq!(full().code(), "storage_full");
        let quota = JobError::from(std::io::Error::from_raw_os_error(libc_edquot()));
        assert_eq!(quota.code(), "storage_full");
        let denied = JobError::from(std::io::Error::from(std::io::ErrorKind::PermissionDenied));
        assert_eq!(denied.code(), "internal");
    }

    /// EDQUOT on Linux.
    fn libc_edquot() -> i32 {
        122
    }

    #[test]
    fn a_full_write_releases_the_reserve_and_the_probe_restores_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        ensure_reserve(dir.path()).expect("reserve");
        let health = StorageHealth::new(Some(dir.path().to_path_buf()));
        assert!(!health.is_full());
        assert!(health.refuse_if_full().is_ok());
        let e = health.noted(full());
        assert_eq!(e.code(), "storage_full");
        assert!(health.is_full());
        assert!(!reserve_path(dir.path()).exists(), "released");
        assert!(start_reserve_path(dir.path()).exists(), "kept for a start");
        assert_eq!(
            health.refuse_if_full().map_err(|e| e.code()),
            Err("storage_full")
        );
        // This disk has room: the probe writes the reserve back and clears the mark.
        assert!(!health.probe(super::super::now_ms()));
        assert!(!health.is_full());
        let len = std::fs::metadata(reserve_path(dir.path()))
            .expect("reserve back")
            .len();
        assert_eq!(len, RESERVE_BYTES);
        assert!(release_for_start(dir.path()));
        assert!(!start_reserve_path(dir.path()).exists());
        assert!(!release_for_start(dir.path()), "nothing left to release");
        // Other errors leave it alone.
        let _ = health.noted(JobError::Internal("x".into()));
        assert!(!health.is_full());
    }

    #[test]
    fn without_a_data_dir_full_lasts_a_window_after_the_last_full_write() {
        let health = StorageHealth::new(None);
        health.mark_full("nats", 1_000);
        assert!(health.probe(1_000 + REMOTE_FULL_MS - 1));
        assert!(!health.probe(1_000 + REMOTE_FULL_MS));
        assert!(!health.is_full());
    }

    /// A remote store that can say whether it has room (NATS writes a probe) decides at once,
    /// either way, whatever the window says.
    #[test]
    fn a_remote_stores_own_answer_decides_before_the_window() {
        let health = StorageHealth::new(None);
        health.mark_full("nats", 1_000);
        assert!(health.probe_with(1_000 + REMOTE_FULL_MS, Some(false)));
        assert!(health.is_full());
        assert!(!health.probe_with(1_001, Some(true)));
        assert!(!health.is_full());
        // Not full: nothing to decide.
        assert!(!health.probe_with(1_002, Some(false)));
    }
}
