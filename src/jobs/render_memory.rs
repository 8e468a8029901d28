//! The server's download memory budget, in bytes, shared by what downloads hold while their
//! clients take them (`api::download`) and by the renders that build them ([`RenderHold`]),
//! so that the memory held for downloads is bounded in total (issue 25 item 6).
//!
//! A download's first render builds the mesh in memory (the writers need the whole asset):
//! the file as read, the asset, the positions and the output. At most
//! [`super::downloads::RENDER_STRIPES`] render at once, but a count bounds no bytes: eight
//! renders of large results could hold far more than the budget. So a render first takes
//! its estimated size ([`render_estimate`]) from the budget, waits for room at most
//! [`RENDER_WAIT`], and is refused with [`JobError::DownloadsBusy`] (503 `downloads_busy`,
//! scope `render`, `Retry-After`) when none came. Once the output exists its hold is fitted to
//! the output's length (grown, or given back), which it keeps while the output is stored.

use super::JobError;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// The budget counts KiB: `Semaphore::acquire_many` takes a `u32`, and a KiB grain keeps any
/// budget up to 4 TiB representable.
pub const UNIT: u64 = 1024;

/// How long a render waits for room in the budget before it is refused: room comes back as
/// other renders finish (tenths of a second) and downloads are taken.
pub const RENDER_WAIT: Duration = Duration::from_secs(5);

/// `Retry-After` of a render refused for want of budget: as a download refused for it.
pub const RENDER_BUSY_RETRY_SECS: u64 = 5;

/// Bytes of the budget held by renders in this process (all servers), for tests and metrics.
static RENDERING_BYTES: AtomicU64 = AtomicU64::new(0);

/// The most of any budget in this process found in use at once (bytes), by the budget's own
/// count, since the start or [`reset_peak`].
static PEAK_IN_USE: AtomicU64 = AtomicU64::new(0);

/// Bytes of the download budget held by renders now.
pub fn rendering_bytes() -> u64 {
    RENDERING_BYTES.load(Ordering::Relaxed)
}

/// The most of a download budget in use at once, in bytes (renders and downloads together).
pub fn peak_in_use() -> u64 {
    PEAK_IN_USE.load(Ordering::Relaxed)
}

/// Start [`peak_in_use`] afresh.
pub fn reset_peak() {
    PEAK_IN_USE.store(0, Ordering::Relaxed);
}

/// `bytes` in budget units, at least one.
pub fn units(bytes: u64) -> u64 {
    bytes.div_ceil(UNIT).max(1)
}

/// The server's download budget: one per server, shared by its connections and renders.
#[derive(Clone, Debug)]
pub struct DownloadMemory {
    permits: Arc<Semaphore>,
    units: u64,
    /// Units held by renders now.
    rendering: Arc<AtomicU64>,
    /// Renders waiting for room now.
    waiting: Arc<AtomicU64>,
}

impl DownloadMemory {
    /// A budget of `bytes` (at least 1 KiB).
    pub fn new(bytes: u64) -> DownloadMemory {
        let units = units(bytes).min(Semaphore::MAX_PERMITS as u64);
        DownloadMemory {
            permits: Arc::new(Semaphore::new(units as usize)),
            units,
            rendering: Arc::new(AtomicU64::new(0)),
            waiting: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Its size in units.
    pub fn units(&self) -> u64 {
        self.units
    }

    /// Units free now.
    pub fn available(&self) -> u64 {
        self.permits.available_permits() as u64
    }

    /// Units renders hold now.
    pub fn rendering(&self) -> u64 {
        self.rendering.load(Ordering::Relaxed)
    }

    /// Whether renders hold part of the budget or wait for it. What they hold comes back
    /// within a render's time, so a download that finds the budget short then may wait for it
    /// (downloads waiting for their clients may hold theirs for the whole write deadline),
    /// and must: the units a render waits for are handed to it as they come free.
    pub fn renders_active(&self) -> bool {
        self.rendering() > 0 || self.waiting.load(Ordering::Relaxed) > 0
    }

    /// Take `units` (at most the whole budget) now, or `None` if they are not free.
    pub fn try_take(&self, units: u64) -> Option<OwnedSemaphorePermit> {
        let want = units.min(self.units) as u32;
        let permit = self.permits.clone().try_acquire_many_owned(want).ok()?;
        self.note_in_use();
        Some(permit)
    }

    /// Take `units` (at most the whole budget), waiting at most `wait` for them.
    pub async fn take(&self, units: u64, wait: Duration) -> Option<OwnedSemaphorePermit> {
        let want = units.min(self.units) as u32;
        let acquired = tokio::time::timeout(wait, self.permits.clone().acquire_many_owned(want));
        let permit = acquired.await.ok()?.ok()?;
        self.note_in_use();
        Some(permit)
    }

    fn note_in_use(&self) {
        let in_use = self.units.saturating_sub(self.available()) * UNIT;
        PEAK_IN_USE.fetch_max(in_use, Ordering::Relaxed);
    }

    /// Hold `bytes` for a render (a render larger than the budget takes all of it, so it runs
    /// alone and is never refused forever), waiting at most `wait`.
    pub async fn hold(&self, bytes: u64, wait: Duration) -> Result<RenderHold, JobError> {
        let mut hold = RenderHold {
            memory: self.clone(),
            permit: None,
            units: 0,
        };
        hold.fit(bytes, wait).await?;
        Ok(hold)
    }

    fn busy(&self, bytes: u64) -> JobError {
        JobError::DownloadsBusy {
            retry_after_secs: RENDER_BUSY_RETRY_SECS,
            wanted: bytes,
            budget: self.units * UNIT,
        }
    }
}

/// A render's hold on the download budget, given back on drop.
#[derive(Debug)]
pub struct RenderHold {
    memory: DownloadMemory,
    permit: Option<OwnedSemaphorePermit>,
    units: u64,
}

impl RenderHold {
    /// Hold `bytes` from now on (at most the whole budget): more is taken, waiting at most
    /// `wait` (refused: [`JobError::DownloadsBusy`], and the hold keeps what it had), less is
    /// given back at once.
    pub async fn fit(&mut self, bytes: u64, wait: Duration) -> Result<(), JobError> {
        let want = units(bytes).min(self.memory.units);
        if want > self.units {
            let waiting = Waiting::new(&self.memory.waiting);
            let more = self.memory.take(want - self.units, wait).await;
            drop(waiting);
            let more = more.ok_or_else(|| self.memory.busy(bytes))?;
            match &mut self.permit {
                Some(p) => p.merge(more),
                None => self.permit = Some(more),
            }
            RENDERING_BYTES.fetch_add((want - self.units) * UNIT, Ordering::Relaxed);
            self.memory
                .rendering
                .fetch_add(want - self.units, Ordering::Relaxed);
        } else if want < self.units {
            // Counted off before the units go back: a download that takes them the moment
            // they are free must never be seen beside a render still counting them (the
            // render-budget test once read 256 KiB held + the whole budget rendering).
            RENDERING_BYTES.fetch_sub((self.units - want) * UNIT, Ordering::Relaxed);
            self.memory
                .rendering
                .fetch_sub(self.units - want, Ordering::Relaxed);
            if let Some(p) = &mut self.permit {
                drop(p.split((self.units - want) as usize));
            }
        } else {
            return Ok(());
        }
        self.units = want;
        Ok(())
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.units * UNIT
    }
}

impl Drop for RenderHold {
    fn drop(&mut self) {
        RENDERING_BYTES.fetch_sub(self.units * UNIT, Ordering::Relaxed);
        self.memory
            .rendering
            .fetch_sub(self.units, Ordering::Relaxed);
    }
}

/// One render counted as waiting while it lives (a wait cut short by its request going away
/// counts off too).
struct Waiting<'a>(&'a AtomicU64);

impl<'a> Waiting<'a> {
    fn new(count: &'a AtomicU64) -> Waiting<'a> {
        count.fetch_add(1, Ordering::Relaxed);
        Waiting(count)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// What rendering a mesh holds at its peak, estimated before it starts from what the job
/// records: the input file as read (`input_bytes`); the asset read from it, which keeps the
/// file's text or buffers to edit (about the file again); the output, which the writers
/// reserve at the input's size and a quarter (`willow::mesh::io::text`); the positions given to
/// the writer and the asset's own (f64 xyz: 48 B a vertex); the faces (3 × u32). The hold is
/// fitted to the output's real length once it exists.
pub fn render_estimate(input_bytes: u64, vertices: usize, faces: usize) -> u64 {
    let file = input_bytes;
    let asset = input_bytes;
    let output = input_bytes.saturating_add(input_bytes / 4);
    let geometry = (vertices as u64)
        .saturating_mul(48)
        .saturating_add((faces as u64).saturating_mul(12));
    file.saturating_add(asset)
        .saturating_add(output)
        .saturating_add(geometry)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_adds_the_file_the_asset_the_output_and_the_geometry() {
        // 1000 B file: 1000 + 1000 + 1250; 10 vertices × 48 + 16 faces × 12.
        assert_eq!(render_estimate(1000, 10, 16), 3250 + 480 + 192);
        assert_eq!(render_estimate(u64::MAX, 1, 1), u64::MAX);
    }

    #[tokio::test]
    async fn a_hold_grows_waits_shrinks_and_gives_back() {
        let memory = DownloadMemory::new(10 * UNIT);
        let mut a = memory.hold(4 * UNIT, RENDER_WAIT).await.expect("room");
        assert_eq!(memory.available(), 6);
        a.fit(8 * UNIT, RENDER_WAIT)
            .await
            .expect("grows into free room");
        assert_eq!(memory.available(), 2);
        // No room for another 4 KiB: refused after the wait, naming what it wanted.
        let refused = memory.hold(4 * UNIT, Duration::from_millis(20)).await;
        match refused {
            Err(JobError::DownloadsBusy {
                wanted,
                budget,
                retry_after_secs,
            }) => {
                assert_eq!((wanted, budget), (4 * UNIT, 10 * UNIT));
                assert_eq!(retry_after_secs, RENDER_BUSY_RETRY_SECS);
            }
            other => panic!("expected DownloadsBusy, got {other:?}"),
        }
        // Fitted to a smaller output, the rest is free at once.
        a.fit(3 * UNIT, RENDER_WAIT).await.expect("shrinks");
        assert_eq!(memory.available(), 7);
        // A waiting render gets its room when another lets go.
        let waiter = {
            let memory = memory.clone();
            tokio::spawn(async move { memory.hold(9 * UNIT, RENDER_WAIT).await })
        };
        tokio::time::sleep(Duration::from_millis(20)).await;
        drop(a);
        let b = waiter.await.expect("joined").expect("room once `a` let go");
        assert_eq!(memory.available(), 1);
        drop(b);
        // Larger than the budget: takes all of it.
        let all = memory.hold(100 * UNIT, RENDER_WAIT).await.expect("alone");
        assert_eq!((memory.available(), all.bytes()), (0, 10 * UNIT));
        drop(all);
        assert_eq!((memory.available(), memory.rendering()), (10, 0));
    }
}
