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
//! [`GpuContext`] and its fields live here; its methods are in one file per concern:
//! `select` (opening a device), `pipelines`, `transfer` (host reads and writes), `record`
//! (dispatches and barriers), `submit` (submissions in flight) and `profile` (timestamps and
//! host counters).

use std::path::PathBuf;
use std::time::Instant;
use std::sync::{Mutex, MutexGuard, OnceLock};

use ash::vk;
use bytemuck::Pod;

use super::arena::{Arena, GpuBuffer, GpuRange};

mod pipelines;
mod profile;
mod record;
mod select;
mod submit;
mod transfer;

pub use profile::{HostStats, KernelProfile};
pub use record::Hazards;

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

/// What a staged transfer moves: host bytes to the arena, or arena bytes to the host.
enum Staged<'a> {
    Write(&'a [u8]),
    Read(&'a mut [u8]),
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
/// How a dispatch's workgroup count is given.
#[derive(Clone, Copy, Debug)]
enum Launch {
    Groups([u32; 3]),
    /// Three u32 in the arena, read by the device.
    Indirect(GpuRange),
}


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
        self.device_type == type_name(vk::PhysicalDeviceType::CPU)
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

/// One timed stretch of the queue: its dispatch count and `(kernel, start, end)` ticks.
type Stretch = (usize, [(KernelId, u64, u64); MAX_DISPATCHES]);

/// A copy for the host recorded by [`GpuContext::prefetch`].
#[derive(Clone, Copy, Debug)]
struct Prefetched {
    /// src_offset: arena, dst_offset: staging.
    copy: vk::BufferCopy,
    /// A later command writes the range: the copy is still what [`GpuContext::read_prefetched`]
    /// wants (that moment's values), no longer what [`GpuContext::read`] does (the arena's).
    overwritten: bool,
}

impl Prefetched {
    /// Where in the staging buffer arena bytes `start..end` are, if this copy holds them.
    fn holds(&self, start: u64, end: u64) -> Option<u64> {
        let c = &self.copy;
        (c.src_offset <= start && end <= c.src_offset + c.size).then(|| c.dst_offset + (start - c.src_offset))
    }
}

/// A submission left running ([`GpuContext::submit`]).
#[derive(Clone, Copy, Debug)]
struct Flight {
    /// Its command buffer and fence (`GpuContext::slots`).
    slot: usize,
    /// When it was submitted (host stats).
    since: Instant,
    /// The prefetched copies it and the earlier ones made (`GpuContext::prefetched`).
    prefetch_len: usize,
}


struct Pipeline {
    set_layout: vk::DescriptorSetLayout,
    layout: vk::PipelineLayout,
    pipeline: vk::Pipeline,
}

/// The open device with its arena and pipelines. One per mapper; not shared between threads.
pub struct GpuContext {
    _entry: ash::Entry,
    instance: ash::Instance,
    device: ash::Device,
    push_descriptor: ash::khr::push_descriptor::Device,
    queue: vk::Queue,
    command_pool: vk::CommandPool,
    /// The command buffer and fence being recorded next (`slots[current]`); the other slots
    /// belong to submissions [`GpuContext::submit`] left running (`in_flight`) or are free.
    command_buffer: vk::CommandBuffer,
    fence: vk::Fence,
    slots: [(vk::CommandBuffer, vk::Fence); SLOTS],
    current: usize,
    /// Submissions running that nothing waited for yet, oldest first (at most two: the
    /// device has the next one queued while the host waits for the older's results).
    in_flight: std::cell::Cell<[Option<Flight>; SLOTS - 1]>,
    /// When the open recording began and whether a submission was running then (HostStats).
    recording_since: Option<(Instant, bool)>,
    /// When a wait left the queue idle ([`HostStats::idle_ns`]).
    idle_since: std::cell::Cell<Option<Instant>>,
    /// Waits poll the fence instead of sleeping in the driver ([`Self::set_spin_wait`]).
    spin_wait: bool,
    /// The timestamps of the dispatches recorded so far are not yet in the profile.
    untimed: bool,
    /// Dispatches in submitted command buffers since the queue was last idle at a `begin`, and
    /// the prefetch list's length and bytes then (what a running submission will fill).
    submitted: usize,
    prefetch_submitted: (usize, u64),
    query_pool: Option<vk::QueryPool>,
    memory: vk::DeviceMemory,
    buffer: vk::Buffer,
    /// The arena's mapping, null when transfers are staged.
    mapped: *mut u8,
    /// Staged transfers: a host-visible, coherent (cached where the device has it) buffer of
    /// `staging_bytes`, mapped at `staging_mapped`; null handles when the arena is mapped.
    staging_memory: vk::DeviceMemory,
    staging_buffer: vk::Buffer,
    staging_mapped: *mut u8,
    staging_bytes: u64,
    /// Staged transfers: the tail of the staging buffer (from `deferred_at`, `deferred_bytes`
    /// long) holds small writes not yet copied; `deferred` lists their copies, recorded at
    /// the start of the next submission (see [`GpuContext::write`]).
    deferred_at: u64,
    deferred_bytes: u64,
    deferred: std::cell::RefCell<Vec<vk::BufferCopy>>,
    deferred_used: std::cell::Cell<u64>,
    /// Staged transfers: after the deferred writes, `prefetch_bytes` of the staging buffer
    /// from `prefetch_at` take the copies [`GpuContext::prefetch`] records into a submission;
    /// `prefetched` lists them (src_offset: arena, dst_offset: staging) until the next
    /// `begin` or write.
    prefetch_at: u64,
    prefetch_bytes: u64,
    prefetched: std::cell::RefCell<Vec<Prefetched>>,
    prefetch_used: u64,
    /// The first this many of `prefetched` were made by submissions that finished
    /// ([`GpuContext::read_prefetched`] serves them while a later one runs).
    prefetch_done: std::cell::Cell<usize>,
    arena: Arena,
    pipeline_cache: vk::PipelineCache,
    pipelines: Vec<Pipeline>,
    max_groups: [u32; 3],
    info: DeviceInfo,
    /// Reductions instead of float atomics ([`GpuOptions::deterministic`]).
    deterministic: bool,
    recording: bool,
    recorded: usize,
    /// The kernel table this context was built with ([`GpuContext::new`]).
    kernels: &'static [KernelInfo],
    recorded_kernels: [KernelId; MAX_DISPATCHES],
    /// The dispatches of the last two timed stretches ([`Self::last_timeline`]): count and
    /// `(kernel, start, end)` ticks.
    timeline: Box<[Stretch; 2]>,
    /// What the commands since the last barrier of the open submission touched.
    hazards: Hazards,
    /// Timestamp queries wanted ([`GpuContext::set_timestamps`]) and, latched at `begin`,
    /// taken in the open submission.
    timestamps_wanted: bool,
    timing: bool,
    timestamps: Box<[u64; 2 * MAX_DISPATCHES]>,
    profile: KernelProfile,
    /// Host-side counters; a `Cell` because reads take `&self`.
    host: std::cell::Cell<HostStats>,
    last_kernel: Option<KernelId>,
}

// SAFETY: the context owns its Vulkan objects and the arena mapping; every use goes through
// `&mut self` (recording, submission, writes) or `&self` reads while the queue is idle, so
// moving it to another thread (the mapping thread) is sound. It is not `Sync`.
unsafe impl Send for GpuContext {}

fn vk_err(call: &'static str) -> impl Fn(vk::Result) -> GpuError {
    move |result| GpuError::Vulkan { call, result }
}

fn type_rank(t: vk::PhysicalDeviceType) -> u32 {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

fn type_name(t: vk::PhysicalDeviceType) -> &'static str {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
        vk::PhysicalDeviceType::CPU => "CPU",
        _ => "other",
    }
}

struct Candidate {
    index: usize,
    physical: vk::PhysicalDevice,
    name: String,
    rank: u32,
    queue_family: u32,
    timestamp_bits: u32,
    /// VK_EXT_shader_atomic_float with `shaderBufferFloat32AtomicAdd`.
    float_atomics: bool,
}

/// The Vulkan loader, loaded once per process and never unloaded. Loading and unloading
/// `libvulkan` (and with it the ICDs and implicit layers) per context raced with contexts being
/// created on other threads: the parallel GPU test binaries crashed with SIGSEGV on lavapipe.
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
        self.deterministic
    }

    /// Switches deterministic mode (see [`GpuOptions::deterministic`]); returns the mode in
    /// effect, which stays deterministic on a device without float atomics.
    pub fn set_deterministic(&mut self, on: bool) -> bool {
        self.deterministic = on || !self.info.float_atomics;
        self.deterministic
    }


    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    /// Allocates `len` elements from the arena (start-up only: the arena never grows).
    pub fn alloc<T: Pod>(&mut self, what: &'static str, len: usize) -> Result<GpuBuffer<T>, GpuError> {
        self.arena.alloc(what, len)
    }
    /// Bytes of the arena in use, the peak so far and the capacity (the budget).
    pub fn arena_used_bytes(&self) -> u64 {
        self.arena.used()
    }
    pub fn arena_peak_bytes(&self) -> u64 {
        self.arena.peak()
    }
    pub fn arena_capacity_bytes(&self) -> u64 {
        self.arena.capacity()
    }
    /// Frees every buffer allocated after `mark` (an earlier [`GpuContext::arena_used_bytes`]).
    pub fn arena_reset_to(&mut self, mark: u64) {
        self.arena.reset_to(mark)
    }

    fn destroy_device_objects(&mut self) {
        unsafe {
            let d = &self.device;
            let _ = d.device_wait_idle();
            for p in self.pipelines.drain(..) {
                d.destroy_pipeline(p.pipeline, None);
                d.destroy_pipeline_layout(p.layout, None);
                d.destroy_descriptor_set_layout(p.set_layout, None);
            }
            d.destroy_pipeline_cache(self.pipeline_cache, None);
            if !self.mapped.is_null() {
                d.unmap_memory(self.memory);
            }
            if !self.staging_mapped.is_null() {
                d.unmap_memory(self.staging_memory);
            }
            d.destroy_buffer(self.staging_buffer, None);
            d.free_memory(self.staging_memory, None);
            d.destroy_buffer(self.buffer, None);
            d.free_memory(self.memory, None);
            if let Some(q) = self.query_pool.take() {
                d.destroy_query_pool(q, None);
            }
            for &(_, fence) in &self.slots {
                if fence != vk::Fence::null() {
                    d.destroy_fence(fence, None);
                }
            }
            d.destroy_command_pool(self.command_pool, None);
            d.destroy_device(None);
        }
    }
}

impl Drop for GpuContext {
    fn drop(&mut self) {
        if let Err(e) = self.save_pipeline_cache() {
            tracing::warn!("gpu: {e}");
        }
        let _lifecycle = lifecycle_lock();
        self.destroy_device_objects();
        unsafe { self.instance.destroy_instance(None) };
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
