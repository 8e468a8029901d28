//! What a job may store, known at submission (issue 42 item 1): its kept frames, its
//! checkpoint, its result and a metrics row per step, beside the input it came with.
//!
//! The tenant's `stored_bytes` quota counts the input and this plan from the moment the job
//! is accepted until it expires or is deleted, so a job that would pass the quota is refused
//! before it runs and a running one never stores past it: every blob a job writes is one of
//! the planned ones (frames are bounded by their count, overwritten when a resumed job
//! writes a step again). Renderings of downloads are counted when they are stored
//! ([`super::ports::JobStore::charge_rendered`]).
//!
//! The plan is an upper bound, not an estimate: a job that stops before its last step
//! (converged, a target reached) stored less, and its plan is brought down to what it kept
//! ([`kept_bytes`], `JobStore::settle_planned`); one that never started gets all of it back
//! when it ends. A job cancelled or failed while running keeps its plan until it expires or
//! is deleted.

use super::codec::{FRAME_ORIGIN_HEADER, MAX_METRICS_BYTES};
use super::JobSpec;

/// A metrics row's key and bookkeeping beside its blob (SQLite's `frames` row, a NATS stream
/// message's subject and headers): generous, the blob itself is ~200 bytes.
const ROW_OVERHEAD: u64 = 128;

/// The sizes of what a job on a mesh writes: `file_vertices` (a frame's positions, in the
/// file's order, f32) and `surface_vertices` (the welded mesh the flow runs on, f64).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JobSizes {
    pub file_vertices: usize,
    pub surface_vertices: usize,
}

impl JobSizes {
    /// One kept frame: the file-order f32 positions with their origin header, and the welded
    /// f64 positions the frame's mesh is written from (`worker::run`'s `emit`).
    pub fn frame_bytes(&self) -> u64 {
        let file = FRAME_ORIGIN_HEADER as u64 + 12 * self.file_vertices as u64;
        let welded = 24 * self.surface_vertices as u64;
        file + welded
    }

    /// The result (welded f64 positions) and the checkpoint (positions, a per-vertex f64 the
    /// flow carries, metrics and a few counters: `codec::encode_checkpoint`).
    pub fn fixed_bytes(&self) -> u64 {
        let result = 24 * self.surface_vertices as u64;
        let checkpoint = 32 * self.surface_vertices as u64 + MAX_METRICS_BYTES as u64 + 64;
        result + checkpoint
    }
}

/// How many of steps `0..=last` keep positions ([`JobSpec::keeps_positions`]): step 0, every
/// `frame_interval`-th, and the job's last step.
pub fn kept_frames(spec: &JobSpec, last: usize) -> u64 {
    if !spec.include_positions {
        return 0;
    }
    let interval = spec.frame_interval.max(1);
    let multiples = (last / interval) as u64 + 1;
    let final_step = u64::from(last == spec.steps && !last.is_multiple_of(interval));
    multiples + final_step
}

/// The most a job stores besides its input, were it to run all its steps.
pub fn planned_bytes(spec: &JobSpec, sizes: JobSizes) -> u64 {
    kept_bytes(spec, sizes, spec.steps)
}

/// What a job that reached step `last` has stored besides its input (at most).
pub fn kept_bytes(spec: &JobSpec, sizes: JobSizes, last: usize) -> u64 {
    let last = last.min(spec.steps);
    let frames = kept_frames(spec, last).saturating_mul(sizes.frame_bytes());
    let rows = (last as u64 + 1).saturating_mul(MAX_METRICS_BYTES as u64 + ROW_OVERHEAD);
    frames
        .saturating_add(rows)
        .saturating_add(sizes.fixed_bytes())
}

/// The smallest `frame_interval` whose plan, beside `input_bytes`, fits in `room` bytes, if
/// any does (a plan keeps at least step 0 and the last step).
pub fn interval_that_fits(
    spec: &JobSpec,
    sizes: JobSizes,
    input_bytes: u64,
    room: u64,
) -> Option<usize> {
    let fits = |interval: usize| {
        let mut s = spec.clone();
        s.frame_interval = interval;
        input_bytes.saturating_add(planned_bytes(&s, sizes)) <= room
    };
    let widest = spec.steps.max(1);
    if !fits(widest) {
        return None;
    }
    // The plan falls as the interval grows: the first that fits, by bisection.
    let (mut lo, mut hi) = (spec.frame_interval.max(1), widest);
    if fits(lo) {
        return Some(lo);
    }
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if fits(mid) {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Some(hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(steps: usize, frame_interval: usize) -> JobSpec {
        JobSpec {
            steps,
            frame_interval,
            ..JobSpec::default()
        }
    }

    #[test]
    fn kept_frames_count_step_zero_every_interval_and_the_last() {
        // The worker's own rule, step by step.
        for (steps, interval) in [(20, 1), (20, 3), (7, 7), (3000, 1), (10, 4), (5, 100)] {
            let s = spec(steps, interval);
            let counted = (0..=steps).filter(|&k| s.keeps_positions(k)).count() as u64;
            assert_eq!(
                kept_frames(&s, steps),
                counted,
                "{steps} steps every {interval}"
            );
            let halfway = steps / 2;
            let early = (0..=halfway).filter(|&k| s.keeps_positions(k)).count() as u64;
            assert_eq!(
                kept_frames(&s, halfway),
                early,
                "{steps}/{interval} at {halfway}"
            );
        }
        let mut none = spec(20, 1);
        none.include_positions = false;
        assert_eq!(kept_frames(&none, 20), 0);
    }

    #[test]
    fn a_frame_is_the_blobs_the_worker_writes() {
        let sizes = JobSizes {
            file_vertices: 1000,
            surface_vertices: 900,
        };
        let positions = vec![[0.25f32; 3]; 1000];
        let framed = super::super::codec::encode_frame_positions(&super::super::FramePositions {
            origin: [1e6, 0.0, 0.0],
            relative: positions,
        });
        let welded = 900 * 24;
        assert_eq!(sizes.frame_bytes(), (framed.len() + welded) as u64);
    }

    #[test]
    fn the_interval_that_fits_is_the_first_whose_plan_fits() {
        let sizes = JobSizes {
            file_vertices: 5000,
            surface_vertices: 5000,
        };
        let s = spec(3000, 1);
        let room = 4 << 20;
        let k = interval_that_fits(&s, sizes, 300_000, room).expect("a wide interval fits");
        let with = |i: usize| {
            let mut t = s.clone();
            t.frame_interval = i;
            300_000 + planned_bytes(&t, sizes)
        };
        assert!(with(k) <= room && with(k - 1) > room, "{k}");
        assert_eq!(interval_that_fits(&s, sizes, 300_000, 1000), None);
    }
}
