//! The Vulkan device: selection, the arena, every pipeline, recording, submission and the
//! per-kernel timestamp profile.
//!
//! Recording: [`GpuContext::begin`], then any number of [`GpuContext::dispatch`] /
//! [`GpuContext::fill`] / [`GpuContext::copy`], then [`GpuContext::submit_and_wait`]. A
//! command is ordered after the earlier ones by a full compute barrier where it reads what one
//! of them wrote or writes what one of them touched (byte ranges of the arena, see
//! [`Hazards`]); commands with no such overlap since the last barrier may run together.
//! Bindings are pushed with
//! `VK_KHR_push_descriptor` (no descriptor pools, no allocation per dispatch); small
//! parameters go in the kernel's immediate (push-constant) block.
//!
//! [`GpuContext`] lives here as a handful of parts, one per concern; each part is defined, with
//! its methods and the context's methods of that concern, in the concern's file: `select`
//! (`Selected`: opening a device), `pipelines` (`Pipelines`), `transfer` (`Transfers`: host
//! reads and writes, the staging buffer), `record` (`Recorder`: dispatches and barriers),
//! `submit` (`Submission`: fences, submissions in flight) and `profile` (`Profiler`:
//! timestamps and host counters); the arena's memory is `ArenaMemory` in `crate::arena`.

use std::cell::{Cell, RefCell};
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard, OnceLock};
use std::time::Instant;

use ash::vk;
use bytemuck::Pod;

use super::arena::{Arena, ArenaMemory, GpuBuffer, GpuRange};

mod pipelines;
mod profile;
mod record;
mod select;
mod submit;
mod transfer;

pub use profile::{HostStats, KernelProfile};
pub use record::Hazards;

use pipelines::{Pipeline, Pipelines};
use profile::Profiler;
use record::Recorder;
use select::Selected;
use submit::Submission;
use transfer::{Prefetched, Transfers};

use super::kernels::{BindingKind, KernelId, KernelInfo, MAX_KERNELS};
use super::GpuError;

/// Environment variable that picks a device: an index into the enumeration order or a
/// case-insensitive substring of the device name.
pub const DEVICE_ENV: &str = "DUV_VULKAN_DEVICE";
/// Dispatches one submission can time (two timestamps each).
pub const MAX_DISPATCHES: usize = 1024;
const MAX_BINDINGS: usize = 16;

/// How to open the device.
#[derive(Clone, Debug)]
pub struct GpuOptions {
    /// Size of the one GPU arena, bytes (the board's `budgets.gpu_mb`).
    pub arena_bytes: u64,
    /// Device choice (index or name substring); `None` reads [`DEVICE_ENV`].
    pub device: Option<String>,
    /// Folder of the on-disk pipeline cache; `None` disables it.
    pub pipeline_cache_dir: Option<PathBuf>,
    /// Deterministic mode: reductions instead of float atomics, so two runs on one device
    /// give bit-identical results (hardware-in-loop regression). Off by default, and forced
    /// on where the device has no float atomics.
    pub deterministic: bool,
    /// Host transfers through a staging buffer of this many bytes even where the arena is
    /// host-visible and cached. `None` (the default) decides by memory type: the arena is
    /// mapped where device-local memory is also host-cached (lavapipe, unified-memory boards),
    /// and staged through [`STAGING_BYTES`] of host-cached memory on a discrete GPU, whose
    /// host-visible device memory is uncached (reading a map back through it cost 5 MB/s-class
    /// bandwidth on an H100).
    pub host_staging: Option<u64>,
}

/// Staging buffer of a discrete GPU's host transfers (host memory, outside the GPU budget);
/// larger transfers go in chunks of this size.
pub const STAGING_BYTES: u64 = 64 << 20;
/// Staged transfers: writes of at most this many bytes wait in the staging buffer and are
/// copied at the start of the next submission instead of being submitted on their own.
pub const DEFERRED_WRITE_BYTES: usize = 64 << 10;
/// Deferred writes held at once; one more makes them go to the device first.
const MAX_DEFERRED_WRITES: usize = 64;
/// Prefetched ranges per submission; more are read the ordinary way.
const MAX_PREFETCHES: usize = 16;

impl GpuOptions {
    /// An arena of `gpu_mb` MiB, the device from [`DEVICE_ENV`], the pipeline cache in
    /// `$XDG_CACHE_HOME/duv` (or `~/.cache/duv`) when a home exists.
    pub fn with_budget_mb(gpu_mb: u32) -> Self {
        let cache = std::env::var_os("XDG_CACHE_HOME")
            .map(PathBuf::from)
            .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
            .map(|d| d.join("duv"));
        GpuOptions { arena_bytes: gpu_mb as u64 * 1024 * 1024, device: None, pipeline_cache_dir: cache, deterministic: false, host_staging: None }
    }
}

/// What was selected, for logs and reports.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    pub name: String,
    pub device_type: String,
    pub vendor_id: u32,
    pub device_id: u32,
    pub driver_version: u32,
    /// `driverName driverInfo` (Vulkan 1.2 driver properties), empty when not reported.
    pub driver: String,
    pub api_version: (u32, u32, u32),
    /// Nanoseconds per timestamp tick; `None` when the queue has no timestamps.
    pub timestamp_period_ns: Option<f32>,
    pub subgroup_size: u32,
    /// Float atomic add on storage buffers (VK_EXT_shader_atomic_float) is enabled.
    pub float_atomics: bool,
    /// Where the pipeline cache lives, when enabled.
    pub pipeline_cache_file: Option<PathBuf>,
    /// How the host reaches the arena: `mapped` (the arena's memory is host-visible and
    /// cached) or `staged` (device-local arena, copies through a host-cached staging buffer).
    pub host_transfers: &'static str,
}

impl DeviceInfo {
    /// A device that runs on the CPU (lavapipe): some kernels have a variant for it.
    pub fn is_cpu(&self) -> bool {
        self.device_type == select::type_name(vk::PhysicalDeviceType::CPU)
    }
}

impl std::fmt::Display for DeviceInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (a, b, c) = self.api_version;
        let atomics = if self.float_atomics { "float atomics" } else { "no float atomics" };
        write!(
            f,
            "{} ({}, Vulkan {a}.{b}.{c}, driver {}, subgroup {}, {atomics}, {} host transfers)",
            self.name, self.device_type, self.driver, self.subgroup_size, self.host_transfers
        )
    }
}

/// Command buffers and fences: one recording, up to two submissions running.
const SLOTS: usize = 3;

/// The open device with its arena and pipelines. One per mapper; not shared between threads.
///
/// Its state is split by concern, one part per file of `device/`; a method borrows the parts
/// it works on (destructuring `self` where it needs several), so what touches what is written
/// in the code and checked by the borrow checker:
///
/// - `Selected` (`select`): loader, instance, device, queue, what was learned of the device
///   (`DeviceInfo`, workgroup limits) and the deterministic mode;
/// - `Pipelines` (`pipelines`): the kernel table, the pipeline cache, a pipeline per kernel;
/// - `ArenaMemory` (`arena`): the arena's buffer, memory and mapping, and its allocator;
/// - `Transfers` (`transfer`): the staging buffer of staged transfers, the deferred small
///   writes and the prefetched copies in it;
/// - `Recorder` (`record`): command pool and buffers, the slot being recorded, what was
///   recorded into it and its hazards;
/// - `Submission` (`submit`): a fence per slot, the submissions in flight and what they
///   hold, waiting;
/// - `Profiler` (`profile`): the timestamp query pool, the kernel profile and timeline, the
///   host counters.
///
/// Destruction ([`Drop`]): every Vulkan object of the other parts first (after
/// `vkDeviceWaitIdle`), then the device, then the instance, all of it under the process-wide
/// lifecycle lock; the loader (`ash::Entry`) is never unloaded.
pub struct GpuContext {
    selected: Selected,
    pipelines: Pipelines,
    memory: ArenaMemory,
    transfers: Transfers,
    recorder: Recorder,
    submission: Submission,
    profiler: Profiler,
}

// SAFETY: the context owns its Vulkan objects and the arena mapping; every use goes through
// `&mut self` (recording, submission, writes) or `&self` reads while the queue is idle, so
// moving it to another thread (the mapping thread) is sound. It is not `Sync`.
unsafe impl Send for GpuContext {}

fn vk_err(call: &'static str) -> impl Fn(vk::Result) -> GpuError {
    move |result| GpuError::Vulkan { call, result }
}

/// The Vulkan loader, loaded once per process and never unloaded. Loading and unloading
/// `libvulkan` (and with it the ICDs and implicit layers) per context raced with contexts being
/// created on other threads: the parallel GPU test binaries crashed with SIGSEGV on lavapipe.
///
/// A failed load is kept as its text: `ash::LoadingError` is not `Clone` (nor is
/// [`GpuError`], which holds an `io::Error`), and every call after the first must return an
/// error of its own; the text becomes the typed [`GpuError::NoLoader`] here, at the seam.
fn loader() -> Result<&'static ash::Entry, GpuError> {
    static ENTRY: OnceLock<Result<ash::Entry, String>> = OnceLock::new();
    ENTRY
        .get_or_init(|| unsafe { ash::Entry::load() }.map_err(|e| e.to_string()))
        .as_ref()
        .map_err(|reason| GpuError::NoLoader { reason: reason.clone() })
}

/// Serialises `vkCreateInstance`/`vkCreateDevice` and `vkDestroyDevice`/`vkDestroyInstance`
/// across threads. The spec only asks external synchronisation per object, but loaders,
/// implicit layers (Mesa's device-select) and drivers have process-wide state there that races
/// when two contexts open or close at once. Work on an open context is not serialised.
fn lifecycle_lock() -> MutexGuard<'static, ()> {
    static LIFECYCLE: Mutex<()> = Mutex::new(());
    // A panic while holding it leaves nothing half-done that a later context depends on.
    LIFECYCLE.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl GpuContext {
    /// Deterministic mode: the kernels that would add with float atomics use reductions in a
    /// fixed order instead. Always true on a device without float atomics.
    pub fn deterministic(&self) -> bool {
        self.selected.deterministic
    }

    /// Switches deterministic mode (see [`GpuOptions::deterministic`]); returns the mode in
    /// effect, which stays deterministic on a device without float atomics.
    pub fn set_deterministic(&mut self, on: bool) -> bool {
        self.selected.set_deterministic(on)
    }

    pub fn info(&self) -> &DeviceInfo {
        &self.selected.info
    }

    /// Allocates `len` elements from the arena (start-up only: the arena never grows).
    pub fn alloc<T: Pod>(&mut self, what: &'static str, len: usize) -> Result<GpuBuffer<T>, GpuError> {
        self.memory.arena.alloc(what, len)
    }
    /// Bytes of the arena in use, the peak so far and the capacity (the budget).
    pub fn arena_used_bytes(&self) -> u64 {
        self.memory.arena.used()
    }
    pub fn arena_peak_bytes(&self) -> u64 {
        self.memory.arena.peak()
    }
    pub fn arena_capacity_bytes(&self) -> u64 {
        self.memory.arena.capacity()
    }
    /// Frees every buffer allocated after `mark` (an earlier [`GpuContext::arena_used_bytes`]).
    pub fn arena_reset_to(&mut self, mark: u64) {
        self.memory.arena.reset_to(mark)
    }

    /// Destroys every Vulkan object of the parts, then the device (not the instance: [`Drop`],
    /// or the caller of a failed [`GpuContext::open`], destroys it after). Runs once: on drop, or
    /// on a failed start-up before the context is forgotten. Objects never created are null
    /// handles, which Vulkan's destroy and free calls ignore.
    fn destroy_device_objects(&mut self) {
        let GpuContext { selected, pipelines, memory, transfers, recorder, submission, profiler } = self;
        let d = &selected.device;
        // SAFETY: after `vkDeviceWaitIdle` no command uses these objects; each part destroys
        // only its own, children of `d`, and the device goes last.
        unsafe {
            let _ = d.device_wait_idle();
            pipelines.destroy(d);
            transfers.destroy(d);
            memory.destroy(d);
            profiler.destroy(d);
            submission.destroy(d);
            recorder.destroy(d);
            d.destroy_device(None);
        }
    }
}

impl Drop for GpuContext {
    /// The pipeline cache to disk, then, under the lifecycle lock: every part's Vulkan objects,
    /// the device (`destroy_device_objects`), the instance. The Rust fields drop
    /// after (host memory only; the loader they reference stays loaded).
    fn drop(&mut self) {
        if let Err(e) = self.save_pipeline_cache() {
            tracing::warn!("gpu: {e}");
        }
        let _lifecycle = lifecycle_lock();
        self.destroy_device_objects();
        unsafe { self.selected.instance.destroy_instance(None) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use super::record::MAX_HAZARD_RANGES;

    fn r(offset: u64, size: u64) -> GpuRange {
        GpuRange { offset, size }
    }

    #[test]
    fn hazards_order_only_what_overlaps() {
        let mut h = Hazards::default();
        // Two kernels on disjoint ranges: no barrier between them.
        assert!(!h.needs_barrier(&[(r(0, 64), false), (r(64, 64), true)]));
        h.record(&[(r(0, 64), false), (r(64, 64), true)]);
        assert!(!h.needs_barrier(&[(r(0, 64), false), (r(256, 64), true)]), "two reads of one range need no barrier");
        h.record(&[(r(0, 64), false), (r(256, 64), true)]);
        // Read after write (the last byte of a written range), write after write, write after read.
        assert!(h.needs_barrier(&[(r(127, 4), false)]));
        assert!(h.needs_barrier(&[(r(300, 8), true)]));
        assert!(h.needs_barrier(&[(r(60, 8), true)]));
        // Adjacent, not overlapping.
        assert!(!h.needs_barrier(&[(r(128, 128), true)]));
        h.clear();
        assert!(!h.needs_barrier(&[(r(64, 64), false), (r(0, 64), true)]));
    }

    #[test]
    fn hazards_barrier_when_full() {
        let mut h = Hazards::default();
        for i in 0..MAX_HAZARD_RANGES as u64 {
            assert!(!h.needs_barrier(&[(r(i * 16, 8), true)]));
            h.record(&[(r(i * 16, 8), true)]);
        }
        assert!(h.needs_barrier(&[(r(1 << 20, 8), true)]), "one range more than it remembers");
        assert!(!h.needs_barrier(&[(r(1 << 20, 8), false)]), "reads are remembered apart");
    }
}
