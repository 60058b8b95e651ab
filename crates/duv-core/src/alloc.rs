//! A counting global allocator: allocation counts for the zero-allocation tests (house habit 7)
//! and live / peak heap bytes for the host-memory budget.
//!
//! A binary opts in with
//! ```ignore
//! #[global_allocator]
//! static GLOBAL: duv_core::alloc::CountingAllocator = duv_core::alloc::CountingAllocator;
//! ```
//! Without that, [`is_installed`] is false and the byte figures stay zero.
//!
//! Counting is armed only inside [`count_allocations`]; the byte figures are always kept.
//! Allocations are counted on every thread ([`CountScope::AllThreads`], so rayon workers are
//! seen) or only on threads that called [`mark_current_thread`] ([`CountScope::MarkedThreads`],
//! for tests whose test harness runs other tests beside them).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};

/// The system allocator with counters in front.
pub struct CountingAllocator;

static INSTALLED: AtomicBool = AtomicBool::new(false);
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);
static LIVE_BYTES: AtomicUsize = AtomicUsize::new(0);
static PEAK_BYTES: AtomicUsize = AtomicUsize::new(0);
/// Allocations of at least [`PREFAULT_MIN_BYTES`] are paged in when made.
static PREFAULT_LARGE: AtomicBool = AtomicBool::new(false);
/// 0: not counting, 1: all threads, 2: marked threads only.
static ARMED: AtomicU8 = AtomicU8::new(0);

thread_local! {
    static MARKED: Cell<bool> = const { Cell::new(false) };
    static ROLE: Cell<u8> = const { Cell::new(0) };
}

/// What a thread does, for the per-role allocation counts ([`label_current_thread`],
/// [`role_allocations`]): the pipeline's stage threads and the tracker's workers label
/// themselves, so health telemetry and tests see which stage allocates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ThreadRole {
    Capture = 1,
    /// The tracking thread and the tracker's worker threads.
    Tracking = 2,
    Mapping = 3,
    Logging = 4,
}

const ROLES: usize = 5;
static ROLE_ALLOCATIONS: [AtomicUsize; ROLES] = [const { AtomicUsize::new(0) }; ROLES];

/// Counts this thread's allocations from now on under `role` (always on, armed or not).
pub fn label_current_thread(role: ThreadRole) {
    ROLE.with(|c| c.set(role as u8));
}

/// Allocations (and reallocations) made so far by threads labelled `role`.
pub fn role_allocations(role: ThreadRole) -> usize {
    ROLE_ALLOCATIONS[role as usize].load(Ordering::Relaxed)
}

/// Which threads [`count_allocations`] sees.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CountScope {
    AllThreads,
    MarkedThreads,
}

#[inline]
fn note_allocation(bytes: usize) {
    let role = ROLE.try_with(|c| c.get()).unwrap_or(0) as usize;
    if role != 0 {
        ROLE_ALLOCATIONS[role % ROLES].fetch_add(1, Ordering::Relaxed);
    }
    match ARMED.load(Ordering::Relaxed) {
        0 => {}
        1 => {
            ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        }
        _ => {
            if MARKED.try_with(|c| c.get()).unwrap_or(false) {
                ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    let live = LIVE_BYTES.fetch_add(bytes, Ordering::Relaxed) + bytes;
    PEAK_BYTES.fetch_max(live, Ordering::Relaxed);
}

/// Allocations this large or larger are paged in when made, once
/// [`prefault_large_allocations`] is on.
pub const PREFAULT_MIN_BYTES: usize = 256 << 10;

/// Turns paging-in of large allocations on or off for the whole process (`duv` turns it on).
///
/// The fixed-capacity stores (Gaussians, optimiser moments, raster and tracker workspaces,
/// keyframe slots) are allocated once at start-up, but the operating system backs an
/// allocation with memory only when a page is first written: the resident set then creeps up
/// for minutes as the stores fill, which reads as a leak on a vehicle's memory watchdog, and
/// each first touch is a page fault in a frame's time. With this on, every allocation of at
/// least [`PREFAULT_MIN_BYTES`] has each page written once when it is made (zeros: the memory
/// is zeroed or uninitialised, so nothing changes), so the resident set matches the live heap
/// from start-up and a steady state that allocates nothing keeps it flat.
///
/// On glibc it also fixes malloc's mmap threshold at [`PREFAULT_MIN_BYTES`] (glibc raises it
/// as large blocks are freed, after which large buffers come from the heap and their memory is
/// kept after they are freed) and caps malloc at 4 arenas: every large allocation is then a
/// mapping of its own, returned to the system when freed, so transient buffers (a map
/// checkpoint being written, a chunk of the log) do not leave the resident set higher.
pub fn prefault_large_allocations(on: bool) {
    PREFAULT_LARGE.store(on, Ordering::Relaxed);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if on {
        use std::ffi::c_int;
        extern "C" {
            fn mallopt(param: c_int, value: c_int) -> c_int;
        }
        const M_MMAP_THRESHOLD: c_int = -3;
        const M_ARENA_MAX: c_int = -8;
        // SAFETY: glibc's mallopt takes two ints and only changes malloc's tunables; it is
        // safe to call at any time (it takes malloc's lock).
        unsafe {
            mallopt(M_MMAP_THRESHOLD, PREFAULT_MIN_BYTES as c_int);
            mallopt(M_ARENA_MAX, 4);
        }
    }
}

/// Writes a zero into every page of a fresh allocation of `size` bytes at `p`.
///
/// SAFETY (caller): `p` is a live allocation of at least `size` bytes whose contents are
/// zero or uninitialised.
#[inline]
unsafe fn touch_pages(p: *mut u8, size: usize) {
    if size >= PREFAULT_MIN_BYTES && PREFAULT_LARGE.load(Ordering::Relaxed) {
        let mut off = 0;
        while off < size {
            // SAFETY: `off < size`, inside the allocation; a zero byte is what a zeroed
            // allocation holds and any value is fine in an uninitialised one.
            unsafe { std::ptr::write_volatile(p.add(off), 0u8) };
            off += 4096;
        }
    }
}

#[inline]
fn note_free(bytes: usize) {
    LIVE_BYTES.fetch_sub(bytes, Ordering::Relaxed);
}

// SAFETY: every call forwards to `System` with the caller's arguments unchanged; the counters
// are atomics and thread-locals with const initialisers, which never allocate.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        INSTALLED.store(true, Ordering::Relaxed);
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            note_allocation(layout.size());
            // SAFETY: a fresh, uninitialised allocation of `layout.size()` bytes.
            unsafe { touch_pages(p, layout.size()) };
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        INSTALLED.store(true, Ordering::Relaxed);
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            note_allocation(layout.size());
            // SAFETY: a fresh, zeroed allocation of `layout.size()` bytes.
            unsafe { touch_pages(p, layout.size()) };
        }
        p
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note_free(layout.size());
            note_allocation(new_size);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        note_free(layout.size());
    }
}

/// Writes every page of `buf` once, so that the operating system backs it now: a buffer from
/// `vec![0; n]` is mapped lazily (zero pages appear in the resident set only when first
/// written), which would make a fixed-capacity store look like a leak as it fills.
pub fn prefault<T: Copy>(buf: &mut [T]) {
    let step = (4096 / std::mem::size_of::<T>().max(1)).max(1);
    for i in (0..buf.len()).step_by(step) {
        let p: *mut T = &mut buf[i];
        // SAFETY: `p` comes from a live `&mut` element: valid, aligned and initialised. The
        // volatile write of its own value keeps the store from being optimised away.
        unsafe { std::ptr::write_volatile(p, std::ptr::read_volatile(p)) };
    }
}

/// Whether this binary's global allocator is [`CountingAllocator`].
pub fn is_installed() -> bool {
    INSTALLED.load(Ordering::Relaxed)
}

/// Marks (or unmarks) the calling thread for [`CountScope::MarkedThreads`].
pub fn mark_current_thread(on: bool) {
    MARKED.with(|c| c.set(on));
}

/// Allocations (and reallocations) made while `f` runs, on the threads `scope` names.
/// Not reentrant: one counting section at a time.
pub fn count_allocations(scope: CountScope, f: impl FnOnce()) -> usize {
    let before = ALLOCATIONS.load(Ordering::SeqCst);
    ARMED.store(if scope == CountScope::AllThreads { 1 } else { 2 }, Ordering::SeqCst);
    f();
    ARMED.store(0, Ordering::SeqCst);
    ALLOCATIONS.load(Ordering::SeqCst) - before
}

/// Allocations made by `f` on the calling thread only.
pub fn count_allocations_on_this_thread(f: impl FnOnce()) -> usize {
    let was = MARKED.with(|c| c.replace(true));
    let n = count_allocations(CountScope::MarkedThreads, f);
    MARKED.with(|c| c.set(was));
    n
}

/// Heap bytes allocated through the counting allocator and not yet freed.
pub fn live_bytes() -> usize {
    LIVE_BYTES.load(Ordering::Relaxed)
}

/// The most [`live_bytes`] seen since start or the last [`reset_peak_bytes`].
pub fn peak_bytes() -> usize {
    PEAK_BYTES.load(Ordering::Relaxed)
}

/// Starts a new peak window at the current live bytes.
pub fn reset_peak_bytes() {
    PEAK_BYTES.store(LIVE_BYTES.load(Ordering::Relaxed), Ordering::Relaxed);
}
