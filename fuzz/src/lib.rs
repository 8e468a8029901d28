//! Shared by the fuzz targets: an allocator that refuses any single allocation above a limit.
//!
//! libFuzzer's `-malloc_limit_mb` needs the malloc hooks of a sanitizer runtime; the targets
//! are built with `--sanitizer none` (the code under test is safe Rust, and without ASan the
//! build is several times faster and the runs about twice as fast), so the limit is enforced
//! here instead. An infallible allocation above the limit aborts the process (Rust's
//! allocation-failure handler), which libFuzzer reports as a crash with the input that caused
//! it; a fallible one (`try_reserve`) sees an error, as it would on a machine without the
//! memory. The limit is `WILLOW_FUZZ_MALLOC_LIMIT_MB` (default 1024 MiB), read once.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The system allocator, refusing allocations larger than the limit.
pub struct CappedAlloc;

/// The limit in bytes; 0 until first read from the environment.
static LIMIT: AtomicUsize = AtomicUsize::new(0);

fn limit() -> usize {
    let l = LIMIT.load(Ordering::Relaxed);
    if l != 0 {
        return l;
    }
    // Reading the environment may allocate: while it does, the limit is usize::MAX.
    LIMIT.store(usize::MAX, Ordering::Relaxed);
    let mb = std::env::var("WILLOW_FUZZ_MALLOC_LIMIT_MB")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|&mb| mb > 0)
        .unwrap_or(1024);
    let l = mb.saturating_mul(1 << 20);
    LIMIT.store(l, Ordering::Relaxed);
    l
}

// SAFETY: every call is forwarded to `System` unchanged, or refused with a null pointer,
// which the `GlobalAlloc` contract allows.
unsafe impl GlobalAlloc for CappedAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if layout.size() > limit() {
            return std::ptr::null_mut();
        }
        System.alloc(layout)
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if layout.size() > limit() {
            return std::ptr::null_mut();
        }
        System.alloc_zeroed(layout)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > limit() {
            return std::ptr::null_mut();
        }
        System.realloc(ptr, layout, new_size)
    }
}

/// Declares [`CappedAlloc`] as the global allocator of a fuzz target.
#[macro_export]
macro_rules! capped_allocator {
    () => {
        #[global_allocator]
        static ALLOC: $crate::CappedAlloc = $crate::CappedAlloc;
    };
}
