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

use std::path::PathBuf;
use std::time::Instant;
use std::sync::{Mutex, MutexGuard, OnceLock};

use ash::vk;
use bytemuck::Pod;

use super::arena::{Arena, GpuBuffer, GpuRange};
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

/// Arena ranges [`Hazards`] remembers between barriers; one more is a barrier.
const MAX_HAZARD_RANGES: usize = 48;

/// The arena ranges the commands recorded since the last barrier wrote and read, to decide
/// whether the next command needs one: it does when it reads or writes a range written since
/// (read after write, write after write) or writes a range read since (write after read).
/// Bindings declared `read_write` count as written.
#[derive(Clone, Debug)]
pub struct Hazards {
    writes: [GpuRange; MAX_HAZARD_RANGES],
    n_writes: usize,
    reads: [GpuRange; MAX_HAZARD_RANGES],
    n_reads: usize,
}

impl Default for Hazards {
    fn default() -> Self {
        let none = GpuRange { offset: 0, size: 0 };
        Hazards { writes: [none; MAX_HAZARD_RANGES], n_writes: 0, reads: [none; MAX_HAZARD_RANGES], n_reads: 0 }
    }
}

fn overlaps(a: &GpuRange, b: &GpuRange) -> bool {
    a.offset < b.offset + b.size && b.offset < a.offset + a.size
}

impl Hazards {
    /// Whether a command touching `accesses` (`(range, written)`) must wait for the commands
    /// since the last barrier: it overlaps what they wrote, writes what they read, or would
    /// overflow what is remembered.
    pub fn needs_barrier(&self, accesses: &[(GpuRange, bool)]) -> bool {
        let (w, r) = (&self.writes[..self.n_writes], &self.reads[..self.n_reads]);
        let added_w = accesses.iter().filter(|a| a.1).count();
        if self.n_writes + added_w > MAX_HAZARD_RANGES || self.n_reads + accesses.len() - added_w > MAX_HAZARD_RANGES {
            return true;
        }
        accesses.iter().any(|(range, written)| w.iter().any(|x| overlaps(x, range)) || (*written && r.iter().any(|x| overlaps(x, range))))
    }
    /// Remembers a command's accesses (after [`Self::needs_barrier`] said no, or a barrier).
    pub fn record(&mut self, accesses: &[(GpuRange, bool)]) {
        for &(range, written) in accesses {
            if written && self.n_writes < MAX_HAZARD_RANGES {
                self.writes[self.n_writes] = range;
                self.n_writes += 1;
            } else if !written && self.n_reads < MAX_HAZARD_RANGES {
                self.reads[self.n_reads] = range;
                self.n_reads += 1;
            }
        }
    }
    /// A barrier was recorded: everything before it is ordered.
    pub fn clear(&mut self) {
        self.n_writes = 0;
        self.n_reads = 0;
    }
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

/// Host-side cost of driving the device, summed since start or [`GpuContext::reset_profile`]:
/// what the kernel timestamps do not show (submission latency, transfers, host copies).
#[derive(Clone, Copy, Debug, Default)]
pub struct HostStats {
    /// Kernel submissions ([`GpuContext::submit_and_wait`], [`GpuContext::submit`]) and the
    /// wall time from submit to the fence (GPU time included), summed per submission: one left
    /// running overlaps the next, so the sum can exceed the wall time.
    pub submits: u64,
    pub submit_wait_ns: u64,
    /// Host reads and writes of the arena (a staged one is one submission per chunk), bytes
    /// and wall time.
    pub reads: u64,
    pub read_bytes: u64,
    pub read_ns: u64,
    pub writes: u64,
    pub write_bytes: u64,
    pub write_ns: u64,
    /// Of `reads`, those served from a copy the last submission made
    /// ([`GpuContext::prefetch`]; no submission of their own).
    pub prefetched_reads: u64,
    /// Pipeline barriers recorded inside submissions: one only where a command touches what
    /// another since the last barrier wrote (or writes what one read), see [`Hazards`].
    pub barriers: u64,
    /// Host time recording submissions (from [`GpuContext::begin`] to the submit), and of it
    /// the time recorded with no submission running (the device waits for the host then).
    pub record_ns: u64,
    pub record_idle_ns: u64,
    /// Host time from a wait that left the queue idle ([`GpuContext::submit_and_wait`]) to the
    /// next kernel submission: all the device waits for the host between submissions (the
    /// host's own work, recording, transfers), `record_idle_ns` included.
    pub idle_ns: u64,
    /// The stretches in `idle_ns`.
    pub idle_gaps: u64,
}

impl HostStats {
    /// The counts since `earlier` (an earlier [`GpuContext::host_stats`]).
    pub fn since(&self, earlier: &HostStats) -> HostStats {
        HostStats {
            submits: self.submits - earlier.submits,
            submit_wait_ns: self.submit_wait_ns - earlier.submit_wait_ns,
            reads: self.reads - earlier.reads,
            read_bytes: self.read_bytes - earlier.read_bytes,
            read_ns: self.read_ns - earlier.read_ns,
            writes: self.writes - earlier.writes,
            write_bytes: self.write_bytes - earlier.write_bytes,
            write_ns: self.write_ns - earlier.write_ns,
            prefetched_reads: self.prefetched_reads - earlier.prefetched_reads,
            barriers: self.barriers - earlier.barriers,
            record_ns: self.record_ns - earlier.record_ns,
            record_idle_ns: self.record_idle_ns - earlier.record_idle_ns,
            idle_ns: self.idle_ns - earlier.idle_ns,
            idle_gaps: self.idle_gaps - earlier.idle_gaps,
        }
    }
    /// One line per `per` steps: submissions, reads, writes, their bytes and milliseconds.
    pub fn describe_per(&self, per: u64) -> String {
        let p = per.max(1) as f64;
        format!(
            "{:.1} submissions ({:.3} ms submit to fence, {:.1} barriers; recorded in {:.3} ms, {:.3} ms of it with none running; {:.1} times an idle queue's fence to the next submission, {:.3} ms each), {:.1} reads ({:.1} prefetched; {:.2} MB, {:.3} ms), {:.1} writes ({:.2} MB, {:.3} ms)",
            self.submits as f64 / p,
            self.submit_wait_ns as f64 * 1e-6 / p,
            self.barriers as f64 / p,
            self.record_ns as f64 * 1e-6 / p,
            self.record_idle_ns as f64 * 1e-6 / p,
            self.idle_gaps as f64 / p,
            self.idle_ns as f64 * 1e-6 / self.idle_gaps.max(1) as f64,
            self.reads as f64 / p,
            self.prefetched_reads as f64 / p,
            self.read_bytes as f64 * 1e-6 / p,
            self.read_ns as f64 * 1e-6 / p,
            self.writes as f64 / p,
            self.write_bytes as f64 * 1e-6 / p,
            self.write_ns as f64 * 1e-6 / p
        )
    }
}

/// Time per kernel from the timestamp queries, summed over submissions.
#[derive(Clone, Debug)]
pub struct KernelProfile {
    /// The kernel table the counts are indexed by.
    pub kernels: &'static [KernelInfo],
    pub dispatches: [u64; MAX_KERNELS],
    pub total_ns: [f64; MAX_KERNELS],
    /// From the first dispatch's start to the last one's end of every timed stretch of the
    /// queue (the submissions between two idle points: a mapper step's two), summed: the
    /// kernels plus the gaps between them (barriers, a submission waiting for the next).
    pub span_ns: f64,
    /// The timed stretches in `span_ns`.
    pub spans: u64,
}

impl Default for KernelProfile {
    fn default() -> Self {
        KernelProfile::new(&[])
    }
}

impl KernelProfile {
    /// An empty profile of the kernels of `kernels`.
    pub fn new(kernels: &'static [KernelInfo]) -> Self {
        KernelProfile { kernels, dispatches: [0; MAX_KERNELS], total_ns: [0.0; MAX_KERNELS], span_ns: 0.0, spans: 0 }
    }

    /// `(kernel, dispatches, total ms)` of every kernel that ran.
    pub fn rows(&self) -> impl Iterator<Item = (&'static KernelInfo, u64, f64)> + '_ {
        self.kernels.iter().enumerate().filter(|(k, _)| self.dispatches[*k] > 0).map(|(k, info)| (info, self.dispatches[k], self.total_ns[k] * 1e-6))
    }
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
    /// Opens the device, allocates the arena and builds a pipeline for every kernel of
    /// `kernels` (the caller's kernel table; [`KernelId`] indexes it).
    pub fn new(options: &GpuOptions, kernels: &'static [KernelInfo]) -> Result<Self, GpuError> {
        if kernels.len() > MAX_KERNELS {
            return Err(GpuError::TooManyKernels { kernels: kernels.len(), max: MAX_KERNELS });
        }
        let entry = loader()?.clone();
        // Instance and device creation (and pipeline builds) one context at a time.
        let _lifecycle = lifecycle_lock();
        let app = vk::ApplicationInfo::default()
            .application_name(c"duv")
            .engine_name(c"duv")
            .api_version(vk::API_VERSION_1_2);
        let instance = match unsafe { entry.create_instance(&vk::InstanceCreateInfo::default().application_info(&app), None) } {
            Ok(i) => i,
            Err(vk::Result::ERROR_INCOMPATIBLE_DRIVER) => return Err(GpuError::NoDevice { seen: String::new() }),
            Err(result) => return Err(GpuError::Vulkan { call: "vkCreateInstance", result }),
        };
        // From here on a failure must destroy the instance.
        match Self::open(entry, instance, options, kernels) {
            Ok(ctx) => Ok(ctx),
            Err((instance, e)) => {
                unsafe { instance.destroy_instance(None) };
                Err(e)
            }
        }
    }

    fn pick(instance: &ash::Instance, wanted: Option<&str>) -> Result<Candidate, GpuError> {
        let physicals = unsafe { instance.enumerate_physical_devices() }.map_err(vk_err("vkEnumeratePhysicalDevices"))?;
        let mut seen = Vec::new();
        let mut usable = Vec::new();
        for (index, &physical) in physicals.iter().enumerate() {
            let props = unsafe { instance.get_physical_device_properties(physical) };
            let name = props.device_name_as_c_str().map(|c| c.to_string_lossy().into_owned()).unwrap_or_default();
            seen.push(format!("{index}: {name} ({})", type_name(props.device_type)));
            if props.api_version < vk::API_VERSION_1_1 {
                continue;
            }
            let exts = unsafe { instance.enumerate_device_extension_properties(physical) }.unwrap_or_default();
            let has_push = exts.iter().any(|e| e.extension_name_as_c_str() == Ok(ash::khr::push_descriptor::NAME));
            if !has_push {
                continue;
            }
            // The rasterisers share splats within a subgroup (shuffle) and leave a loop when
            // every lane is done (vote), in compute shaders.
            let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
            let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut subgroup);
            unsafe { instance.get_physical_device_properties2(physical, &mut props2) };
            let needed_ops = vk::SubgroupFeatureFlags::BASIC | vk::SubgroupFeatureFlags::VOTE | vk::SubgroupFeatureFlags::SHUFFLE | vk::SubgroupFeatureFlags::ARITHMETIC;
            if !subgroup.supported_stages.contains(vk::ShaderStageFlags::COMPUTE) || !subgroup.supported_operations.contains(needed_ops) {
                seen.last_mut().expect("pushed above").push_str(" without compute subgroup basic/vote/shuffle/arithmetic");
                continue;
            }
            let float_atomics = exts.iter().any(|e| e.extension_name_as_c_str() == Ok(ash::ext::shader_atomic_float::NAME)) && {
                let mut atomic = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
                let mut features2 = vk::PhysicalDeviceFeatures2::default().push_next(&mut atomic);
                unsafe { instance.get_physical_device_features2(physical, &mut features2) };
                atomic.shader_buffer_float32_atomic_add == vk::TRUE
            };
            let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
            // Prefer a compute-only queue family, else any with compute.
            let family = families
                .iter()
                .enumerate()
                .filter(|(_, f)| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
                .min_by_key(|(_, f)| f.queue_flags.contains(vk::QueueFlags::GRAPHICS) as u32);
            if let Some((qf, f)) = family {
                usable.push(Candidate {
                    index,
                    physical,
                    name,
                    rank: type_rank(props.device_type),
                    queue_family: qf as u32,
                    timestamp_bits: f.timestamp_valid_bits,
                    float_atomics,
                });
            }
        }
        let seen = seen.join("; ");
        match wanted {
            Some(w) => {
                let found = match w.trim().parse::<usize>() {
                    Ok(i) => usable.into_iter().find(|c| c.index == i),
                    Err(_) => {
                        let w_lower = w.to_lowercase();
                        usable.into_iter().find(|c| c.name.to_lowercase().contains(&w_lower))
                    }
                };
                found.ok_or(GpuError::NoMatchingDevice { env: DEVICE_ENV, wanted: w.to_owned(), seen })
            }
            None => usable.into_iter().min_by_key(|c| (c.rank, c.index)).ok_or(GpuError::NoDevice { seen }),
        }
    }

    #[allow(clippy::result_large_err)]
    fn open(entry: ash::Entry, instance: ash::Instance, options: &GpuOptions, kernels: &'static [KernelInfo]) -> Result<Self, (ash::Instance, GpuError)> {
        let wanted = options.device.clone().or_else(|| std::env::var(DEVICE_ENV).ok().filter(|s| !s.trim().is_empty()));
        let cand = match Self::pick(&instance, wanted.as_deref()) {
            Ok(c) => c,
            Err(e) => return Err((instance, e)),
        };
        let queue_priorities = [1.0f32];
        let queue_info = [vk::DeviceQueueCreateInfo::default().queue_family_index(cand.queue_family).queue_priorities(&queue_priorities)];
        let ext_names = [ash::khr::push_descriptor::NAME.as_ptr(), ash::ext::shader_atomic_float::NAME.as_ptr()];
        let mut atomic = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default().shader_buffer_float32_atomic_add(true);
        let mut device_info =
            vk::DeviceCreateInfo::default().queue_create_infos(&queue_info).enabled_extension_names(&ext_names[..1 + cand.float_atomics as usize]);
        if cand.float_atomics {
            device_info = device_info.push_next(&mut atomic);
        }
        let device = match unsafe { instance.create_device(cand.physical, &device_info, None) } {
            Ok(d) => d,
            Err(result) => return Err((instance, GpuError::Vulkan { call: "vkCreateDevice", result })),
        };
        let mut ctx = GpuContext::skeleton(entry, instance, device, &cand, options.arena_bytes, kernels);
        // Drop now cleans up whatever exists.
        match ctx.init(&cand, options) {
            Ok(()) => Ok(ctx),
            Err(e) => {
                // Destroy everything but the instance, which the caller destroys.
                let instance = ctx.instance.clone();
                ctx.destroy_device_objects();
                std::mem::forget(ctx);
                Err((instance, e))
            }
        }
    }

    fn skeleton(entry: ash::Entry, instance: ash::Instance, device: ash::Device, cand: &Candidate, arena_bytes: u64, kernels: &'static [KernelInfo]) -> Self {
        let push_descriptor = ash::khr::push_descriptor::Device::new(&instance, &device);
        let queue = unsafe { device.get_device_queue(cand.queue_family, 0) };
        GpuContext {
            _entry: entry,
            instance,
            device,
            push_descriptor,
            queue,
            command_pool: vk::CommandPool::null(),
            command_buffer: vk::CommandBuffer::null(),
            fence: vk::Fence::null(),
            slots: [(vk::CommandBuffer::null(), vk::Fence::null()); SLOTS],
            current: 0,
            in_flight: std::cell::Cell::new([None; SLOTS - 1]),
            recording_since: None,
            idle_since: std::cell::Cell::new(None),
            spin_wait: false,
            untimed: false,
            submitted: 0,
            prefetch_submitted: (0, 0),
            query_pool: None,
            memory: vk::DeviceMemory::null(),
            buffer: vk::Buffer::null(),
            mapped: std::ptr::null_mut(),
            staging_memory: vk::DeviceMemory::null(),
            staging_buffer: vk::Buffer::null(),
            staging_mapped: std::ptr::null_mut(),
            staging_bytes: 0,
            deferred_at: 0,
            deferred_bytes: 0,
            deferred: std::cell::RefCell::new(Vec::with_capacity(MAX_DEFERRED_WRITES)),
            deferred_used: std::cell::Cell::new(0),
            prefetch_at: 0,
            prefetch_bytes: 0,
            prefetched: std::cell::RefCell::new(Vec::with_capacity(MAX_PREFETCHES)),
            prefetch_used: 0,
            prefetch_done: std::cell::Cell::new(0),
            arena: Arena::new(arena_bytes, 256),
            pipeline_cache: vk::PipelineCache::null(),
            pipelines: Vec::with_capacity(kernels.len()),
            max_groups: [0; 3],
            info: DeviceInfo {
                name: cand.name.clone(),
                device_type: String::new(),
                vendor_id: 0,
                device_id: 0,
                driver_version: 0,
                driver: String::new(),
                api_version: (0, 0, 0),
                timestamp_period_ns: None,
                subgroup_size: 0,
                float_atomics: cand.float_atomics,
                pipeline_cache_file: None,
                host_transfers: "mapped",
            },
            deterministic: !cand.float_atomics,
            recording: false,
            recorded: 0,
            hazards: Hazards::default(),
            timestamps_wanted: true,
            timing: false,
            kernels,
            recorded_kernels: [KernelId::default(); MAX_DISPATCHES],
            timeline: Box::new([(0, [(KernelId::default(), 0, 0); MAX_DISPATCHES]); 2]),
            timestamps: Box::new([0; 2 * MAX_DISPATCHES]),
            profile: KernelProfile::new(kernels),
            host: std::cell::Cell::new(HostStats::default()),
            last_kernel: None,
        }
    }

    fn init(&mut self, cand: &Candidate, options: &GpuOptions) -> Result<(), GpuError> {
        let (instance, device) = (&self.instance, &self.device);
        // Properties (1.1 subgroup, 1.2 driver).
        let mut driver_props = vk::PhysicalDeviceDriverProperties::default();
        let mut subgroup_props = vk::PhysicalDeviceSubgroupProperties::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut driver_props).push_next(&mut subgroup_props);
        unsafe { instance.get_physical_device_properties2(cand.physical, &mut props2) };
        let props = props2.properties;
        let limits = props.limits;
        let driver = format!(
            "{} {}",
            driver_props.driver_name_as_c_str().map(|c| c.to_string_lossy().into_owned()).unwrap_or_default(),
            driver_props.driver_info_as_c_str().map(|c| c.to_string_lossy().into_owned()).unwrap_or_default()
        )
        .trim()
        .to_owned();
        self.info.device_type = type_name(props.device_type).to_owned();
        self.info.vendor_id = props.vendor_id;
        self.info.device_id = props.device_id;
        self.info.driver_version = props.driver_version;
        self.info.driver = driver;
        self.info.api_version =
            (vk::api_version_major(props.api_version), vk::api_version_minor(props.api_version), vk::api_version_patch(props.api_version));
        self.info.subgroup_size = subgroup_props.subgroup_size;
        let timestamps = cand.timestamp_bits > 0 && limits.timestamp_period > 0.0;
        self.info.timestamp_period_ns = timestamps.then_some(limits.timestamp_period);
        self.max_groups = limits.max_compute_work_group_count;
        self.arena = Arena::new(self.arena.capacity(), limits.min_storage_buffer_offset_alignment.max(256));

        // Command pool, buffer, fence, queries.
        self.command_pool = unsafe {
            device.create_command_pool(
                &vk::CommandPoolCreateInfo::default()
                    .queue_family_index(cand.queue_family)
                    .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER),
                None,
            )
        }
        .map_err(vk_err("vkCreateCommandPool"))?;
        let cbs = unsafe {
            device.allocate_command_buffers(
                &vk::CommandBufferAllocateInfo::default()
                    .command_pool(self.command_pool)
                    .level(vk::CommandBufferLevel::PRIMARY)
                    .command_buffer_count(SLOTS as u32),
            )
        }
        .map_err(vk_err("vkAllocateCommandBuffers"))?;
        for (slot, cb) in self.slots.iter_mut().zip(cbs) {
            *slot = (cb, unsafe { device.create_fence(&vk::FenceCreateInfo::default(), None) }.map_err(vk_err("vkCreateFence"))?);
        }
        self.current = 0;
        (self.command_buffer, self.fence) = self.slots[0];
        if timestamps {
            self.query_pool = Some(
                unsafe {
                    device.create_query_pool(
                        &vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(2 * MAX_DISPATCHES as u32),
                        None,
                    )
                }
                .map_err(vk_err("vkCreateQueryPool"))?,
            );
        }

        // The arena: one buffer, one allocation, mapped once.
        let capacity = self.arena.capacity();
        if capacity > limits.max_storage_buffer_range as u64 * 16 {
            return Err(GpuError::ArenaTooLarge { requested: capacity, limit: limits.max_storage_buffer_range as u64 * 16 });
        }
        self.buffer = unsafe {
            device.create_buffer(
                &vk::BufferCreateInfo::default()
                    .size(capacity.max(256))
                    .usage(vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::UNIFORM_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST | vk::BufferUsageFlags::INDIRECT_BUFFER)
                    .sharing_mode(vk::SharingMode::EXCLUSIVE),
                None,
            )
        }
        .map_err(vk_err("vkCreateBuffer (arena)"))?;
        let req = unsafe { device.get_buffer_memory_requirements(self.buffer) };
        let mem_props = unsafe { instance.get_physical_device_memory_properties(cand.physical) };
        let find = |bits: u32, size: u64, flags: vk::MemoryPropertyFlags| {
            (0..mem_props.memory_type_count).find(|&i| {
                bits & (1 << i) != 0 && mem_props.memory_types[i as usize].property_flags.contains(flags) && {
                    let heap = mem_props.memory_types[i as usize].heap_index as usize;
                    mem_props.memory_heaps[heap].size >= size
                }
            })
        };
        type F = vk::MemoryPropertyFlags;
        let host = F::HOST_VISIBLE | F::HOST_COHERENT;
        // Mapped where device memory is also host-cached (reads and writes at memory speed);
        // else a device-local arena with staged copies; else (no device-local type big enough)
        // whatever host-visible memory there is, mapped.
        let mapped_type = find(req.memory_type_bits, req.size, host | F::HOST_CACHED | F::DEVICE_LOCAL).filter(|_| options.host_staging.is_none());
        let (type_index, staged) = match mapped_type {
            Some(t) => (t, false),
            None => match find(req.memory_type_bits, req.size, F::DEVICE_LOCAL) {
                Some(t) => (t, true),
                None => {
                    let t = find(req.memory_type_bits, req.size, host).ok_or(GpuError::NoMemoryType)?;
                    (t, options.host_staging.is_some())
                }
            },
        };
        self.memory = unsafe {
            device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(type_index), None)
        }
        .map_err(vk_err("vkAllocateMemory (arena)"))?;
        unsafe { device.bind_buffer_memory(self.buffer, self.memory, 0) }.map_err(vk_err("vkBindBufferMemory (arena)"))?;
        if staged {
            let bytes = options.host_staging.unwrap_or(STAGING_BYTES).min(capacity.max(256)).max(256);
            self.staging_buffer = unsafe {
                device.create_buffer(
                    &vk::BufferCreateInfo::default()
                        .size(bytes)
                        .usage(vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST)
                        .sharing_mode(vk::SharingMode::EXCLUSIVE),
                    None,
                )
            }
            .map_err(vk_err("vkCreateBuffer (staging)"))?;
            let sreq = unsafe { device.get_buffer_memory_requirements(self.staging_buffer) };
            let stype = find(sreq.memory_type_bits, sreq.size, host | F::HOST_CACHED)
                .or_else(|| find(sreq.memory_type_bits, sreq.size, host))
                .ok_or(GpuError::NoMemoryType)?;
            self.staging_memory = unsafe {
                device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(sreq.size).memory_type_index(stype), None)
            }
            .map_err(vk_err("vkAllocateMemory (staging)"))?;
            unsafe { device.bind_buffer_memory(self.staging_buffer, self.staging_memory, 0) }.map_err(vk_err("vkBindBufferMemory (staging)"))?;
            self.staging_mapped = unsafe { device.map_memory(self.staging_memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }
                .map_err(vk_err("vkMapMemory (staging)"))? as *mut u8;
            // The last eighth (at most 2 MiB): half for deferred small writes, half for
            // prefetched reads; the rest for chunks.
            let tail = (bytes / 8).min(2 << 20) & !7;
            self.deferred_bytes = tail / 2;
            self.prefetch_bytes = tail - self.deferred_bytes;
            self.staging_bytes = bytes - tail;
            self.deferred_at = self.staging_bytes;
            self.prefetch_at = self.deferred_at + self.deferred_bytes;
            self.info.host_transfers = "staged";
        } else {
            self.mapped = unsafe { device.map_memory(self.memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }
                .map_err(vk_err("vkMapMemory (arena)"))? as *mut u8;
            self.info.host_transfers = "mapped";
        }

        // Pipeline cache keyed by vendor, device, driver version and the cache UUID.
        let uuid: String = props.pipeline_cache_uuid.iter().map(|b| format!("{b:02x}")).collect();
        let cache_file = options.pipeline_cache_dir.as_ref().map(|d| {
            d.join(format!("pipelines-{:04x}-{:04x}-{:08x}-{uuid}.bin", props.vendor_id, props.device_id, props.driver_version))
        });
        let initial = cache_file.as_ref().and_then(|f| std::fs::read(f).ok()).unwrap_or_default();
        let cache_info = vk::PipelineCacheCreateInfo::default().initial_data(&initial);
        self.pipeline_cache = match unsafe { device.create_pipeline_cache(&cache_info, None) } {
            Ok(c) => c,
            // A corrupt or foreign cache file: start empty.
            Err(_) => unsafe { device.create_pipeline_cache(&vk::PipelineCacheCreateInfo::default(), None) }
                .map_err(vk_err("vkCreatePipelineCache"))?,
        };
        self.info.pipeline_cache_file = cache_file;

        self.deterministic = options.deterministic || !self.info.float_atomics;
        for info in self.kernels {
            // A kernel with float atomics has no pipeline on a device without them (a null
            // pipeline; dispatching it is an error).
            let p = if info.float_atomics && !self.info.float_atomics {
                Pipeline { set_layout: vk::DescriptorSetLayout::null(), layout: vk::PipelineLayout::null(), pipeline: vk::Pipeline::null() }
            } else {
                self.build_pipeline(info)?
            };
            self.pipelines.push(p);
        }
        // A cache that cannot be written costs start-up time only: warn, go on.
        if let Err(e) = self.save_pipeline_cache() {
            tracing::warn!("gpu: {e}");
        }
        tracing::info!(device = %self.info, arena_mb = capacity / (1024 * 1024), "gpu: device open");
        Ok(())
    }

    fn build_pipeline(&self, info: &'static KernelInfo) -> Result<Pipeline, GpuError> {
        let name = info.name;
        let kerr = |call: &'static str| move |result| GpuError::Kernel { kernel: name, call, result };
        let device = &self.device;
        let mut bindings = [vk::DescriptorSetLayoutBinding::default(); MAX_BINDINGS];
        assert!(info.bindings.len() <= MAX_BINDINGS, "{name}: more than {MAX_BINDINGS} bindings");
        for (slot, b) in bindings.iter_mut().zip(info.bindings) {
            *slot = vk::DescriptorSetLayoutBinding::default()
                .binding(b.binding)
                .descriptor_type(match b.kind {
                    BindingKind::Uniform => vk::DescriptorType::UNIFORM_BUFFER,
                    _ => vk::DescriptorType::STORAGE_BUFFER,
                })
                .descriptor_count(1)
                .stage_flags(vk::ShaderStageFlags::COMPUTE);
        }
        let set_layout = unsafe {
            device.create_descriptor_set_layout(
                &vk::DescriptorSetLayoutCreateInfo::default()
                    .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
                    .bindings(&bindings[..info.bindings.len()]),
                None,
            )
        }
        .map_err(kerr("vkCreateDescriptorSetLayout"))?;
        let ranges = [vk::PushConstantRange::default().stage_flags(vk::ShaderStageFlags::COMPUTE).offset(0).size(info.immediate_bytes)];
        let set_layouts = [set_layout];
        let mut layout_info = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
        if info.immediate_bytes > 0 {
            layout_info = layout_info.push_constant_ranges(&ranges);
        }
        let layout = unsafe { device.create_pipeline_layout(&layout_info, None) }.map_err(kerr("vkCreatePipelineLayout"))?;
        let code = ash::util::read_spv(&mut std::io::Cursor::new(info.spirv)).map_err(|_| GpuError::Kernel {
            kernel: name,
            call: "read SPIR-V",
            result: vk::Result::ERROR_INVALID_SHADER_NV,
        })?;
        let module = unsafe { device.create_shader_module(&vk::ShaderModuleCreateInfo::default().code(&code), None) }
            .map_err(kerr("vkCreateShaderModule"))?;
        let entry = std::ffi::CString::new(info.entry).expect("entry point name");
        let stage = vk::PipelineShaderStageCreateInfo::default().stage(vk::ShaderStageFlags::COMPUTE).module(module).name(entry.as_c_str());
        let create = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(layout)];
        let result = unsafe { device.create_compute_pipelines(self.pipeline_cache, &create, None) };
        unsafe { device.destroy_shader_module(module, None) };
        let pipeline = result.map_err(|(_, r)| GpuError::Kernel { kernel: name, call: "vkCreateComputePipelines", result: r })?[0];
        Ok(Pipeline { set_layout, layout, pipeline })
    }

    /// Writes the pipeline cache to disk (unique temp file, then rename).
    pub fn save_pipeline_cache(&self) -> Result<(), GpuError> {
        let Some(file) = &self.info.pipeline_cache_file else { return Ok(()) };
        let data = unsafe { self.device.get_pipeline_cache_data(self.pipeline_cache) }.map_err(vk_err("vkGetPipelineCacheData"))?;
        let io = |source| GpuError::PipelineCacheIo { path: file.display().to_string(), source };
        if let Some(dir) = file.parent() {
            std::fs::create_dir_all(dir).map_err(io)?;
        }
        // Unique temporary name: several contexts (test threads, processes) may save at once.
        static SAVES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let seq = SAVES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = file.with_extension(format!("tmp.{}.{seq}", std::process::id()));
        std::fs::write(&tmp, &data).map_err(io)?;
        std::fs::rename(&tmp, file).map_err(io)
    }

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

    fn check_idle(&self, what: &'static str) -> Result<(), GpuError> {
        if self.recording {
            return Err(GpuError::NotRecording { what });
        }
        Ok(())
    }

    /// Copies `data` into the start of `buf` (host-visible memory; the queue must be idle,
    /// which it is outside `begin()`/`submit_and_wait()`).
    pub fn write<T: Pod>(&mut self, buf: &GpuBuffer<T>, data: &[T]) -> Result<(), GpuError> {
        self.check_idle("write")?;
        if data.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: data.len(), len: buf.len });
        }
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let t0 = Instant::now();
        // What the last submission copied for the host of this range is no longer the arena's.
        self.forget_prefetched(buf.offset, buf.offset + bytes.len() as u64);
        let deferred = self.mapped.is_null() && bytes.len() <= DEFERRED_WRITE_BYTES && (bytes.len() as u64) <= self.deferred_bytes;
        if !deferred {
            // In place or by a transfer: not while a submission may still read the arena. (A
            // deferred write goes after what a running submission copies from the staging
            // tail, and reaches the arena in the next submission, after it.)
            self.wait_in_flight()?;
        }
        if deferred {
            // Into the staging tail; copied at the start of the next submission (or transfer).
            let used = self.deferred_used.get();
            if used + bytes.len() as u64 > self.deferred_bytes || self.deferred.borrow().len() == MAX_DEFERRED_WRITES {
                self.flush_deferred()?;
            }
            let used = self.deferred_used.get();
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.staging_mapped.add((self.deferred_at + used) as usize), bytes.len()) };
            self.deferred.borrow_mut().push(vk::BufferCopy { src_offset: self.deferred_at + used, dst_offset: buf.offset, size: bytes.len() as u64 });
            // Each write from a 4-byte boundary.
            self.deferred_used.set((used + bytes.len() as u64).next_multiple_of(4));
        } else if self.mapped.is_null() {
            self.staged_transfer(buf.offset, Staged::Write(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.mapped.add(buf.offset as usize), bytes.len()) };
        }
        let mut h = self.host.get();
        h.writes += 1;
        h.write_bytes += bytes.len() as u64;
        h.write_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// Copies the first `out.len()` elements of `buf` to `out`.
    pub fn read<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.check_idle("read")?;
        self.wait_in_flight()?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let t0 = Instant::now();
        let len = bytes.len();
        let (start, end) = (buf.offset, buf.offset + len as u64);
        // The newest copy of the range (a chain of submissions can hold older ones).
        let copied = self.prefetched.borrow().iter().rev().find_map(|p| p.holds(start, end).filter(|_| !p.overwritten));
        if let Some(at) = copied {
            unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped.add(at as usize), bytes.as_mut_ptr(), len) };
            let mut h = self.host.get();
            h.prefetched_reads += 1;
            self.host.set(h);
        } else if self.mapped.is_null() {
            self.staged_transfer(buf.offset, Staged::Read(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(self.mapped.add(buf.offset as usize), bytes.as_mut_ptr(), len) };
        }
        let mut h = self.host.get();
        h.reads += 1;
        h.read_bytes += len as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// The first `out.len()` elements of `buf` as the newest prefetch of them took them
    /// ([`Self::prefetch`]), waiting only for the submissions up to the one that made it, not
    /// for later ones still running (which may write `buf` again: a step's results read while
    /// the next step's work runs); with no such copy, as [`Self::read`].
    pub fn read_prefetched<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.check_idle("read")?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let (start, end) = (buf.offset, buf.offset + bytes.len() as u64);
        // The newest copy of the range; waited for (only the submissions up to the one that
        // made it) when it is not done yet.
        let newest = self.prefetched.borrow().iter().enumerate().rev().find_map(|(i, p)| p.holds(start, end).map(|at| (i, at)));
        let Some((index, at)) = newest else {
            return self.read(buf, bytemuck::cast_slice_mut(bytes));
        };
        while index >= self.prefetch_done.get() {
            if !self.wait_oldest()? {
                // Recorded but not submitted: not a copy yet.
                return self.read(buf, bytemuck::cast_slice_mut(bytes));
            }
        }
        let t0 = Instant::now();
        unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped.add(at as usize), bytes.as_mut_ptr(), bytes.len()) };
        let mut h = self.host.get();
        h.reads += 1;
        h.prefetched_reads += 1;
        h.read_bytes += bytes.len() as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// Drops the prefetched copies that overlap arena bytes `start..end` (no longer the
    /// arena's, or not the newest), keeping the counts of finished and submitted ones right.
    fn forget_prefetched(&mut self, start: u64, end: u64) {
        let list = self.prefetched.get_mut();
        let (mut done, mut submitted) = (self.prefetch_done.get(), self.prefetch_submitted.0);
        let mut flights = self.in_flight.get();
        let mut i = 0;
        while i < list.len() {
            let c = list[i].copy;
            if c.src_offset + c.size <= start || end <= c.src_offset {
                i += 1;
                continue;
            }
            let _ = list.remove(i);
            if i < done {
                done -= 1;
            }
            if i < submitted {
                submitted -= 1;
            }
            for f in flights.iter_mut().flatten() {
                if i < f.prefetch_len {
                    f.prefetch_len -= 1;
                }
            }
        }
        self.prefetch_done.set(done);
        self.prefetch_submitted.0 = submitted;
        self.in_flight.set(flights);
    }

    /// Records the copies of the deferred small writes (in the order written) and forgets them.
    fn record_deferred(&self, cb: vk::CommandBuffer) {
        let mut pending = self.deferred.borrow_mut();
        if pending.is_empty() {
            return;
        }
        unsafe { self.device.cmd_copy_buffer(cb, self.staging_buffer, self.buffer, &pending) };
        pending.clear();
        // The copied bytes stay reserved until the copies ran (`release_deferred`).
    }

    /// The staging tail is free again once the queue is idle and no write waits in it.
    fn release_deferred(&self) {
        if self.in_flight.get()[0].is_none() && self.deferred.borrow().is_empty() {
            self.deferred_used.set(0);
        }
    }

    /// Waits for `fence`: in the driver, or polling it ([`Self::set_spin_wait`]).
    unsafe fn wait_fence(&self, fence: vk::Fence) -> Result<(), vk::Result> {
        if self.spin_wait {
            loop {
                match unsafe { self.device.get_fence_status(fence) } {
                    Ok(true) => return Ok(()),
                    Ok(false) => std::hint::spin_loop(),
                    Err(e) => return Err(e),
                }
            }
        }
        unsafe { self.device.wait_for_fences(&[fence], true, u64::MAX) }
    }

    /// Leaves the time from the last wait to the next submission out of
    /// [`HostStats::idle_ns`] (a caller that did other work in between: a benchmark's blocks).
    pub fn forget_idle(&self) {
        self.idle_since.set(None);
    }

    /// Waits poll the fence (`on`) instead of sleeping in the driver (the default): the
    /// thread spins a core for the whole wait, but sees the fence without the driver's wake-up
    /// latency. Returns the previous setting.
    pub fn set_spin_wait(&mut self, on: bool) -> bool {
        std::mem::replace(&mut self.spin_wait, on)
    }

    /// Waits for the submissions [`Self::submit`] left running, if any.
    fn wait_in_flight(&self) -> Result<(), GpuError> {
        while self.wait_oldest()? {}
        Ok(())
    }

    /// Waits for the oldest submission left running; `false` when there was none.
    fn wait_oldest(&self) -> Result<bool, GpuError> {
        let mut flights = self.in_flight.get();
        let Some(f) = flights[0] else { return Ok(false) };
        let d = &self.device;
        let fence = self.slots[f.slot].1;
        unsafe {
            self.wait_fence(fence).map_err(vk_err("vkWaitForFences (submission left running)"))?;
            d.reset_fences(&[fence]).map_err(vk_err("vkResetFences"))?;
        }
        flights.rotate_left(1);
        flights[SLOTS - 2] = None;
        self.in_flight.set(flights);
        self.prefetch_done.set(f.prefetch_len.max(self.prefetch_done.get()));
        let mut h = self.host.get();
        h.submit_wait_ns += f.since.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(true)
    }

    /// The deferred small writes to the device now, in a submission of their own.
    fn flush_deferred(&self) -> Result<(), GpuError> {
        if self.deferred.borrow().is_empty() {
            return Ok(());
        }
        self.staged_transfer(0, Staged::Write(&[]))
    }

    /// A staged host transfer at arena offset `offset`, in chunks of the staging buffer: one
    /// submission per chunk on the idle queue, waited for; the deferred small writes are
    /// copied first, in the first one (an empty transfer submits only them).
    fn staged_transfer(&self, offset: u64, mut transfer: Staged<'_>) -> Result<(), GpuError> {
        let (upload, len) = match &transfer {
            Staged::Write(b) => (true, b.len()),
            Staged::Read(b) => (false, b.len()),
        };
        self.wait_in_flight()?;
        let d = &self.device;
        let cb = self.command_buffer;
        let what = if upload { "write (staged)" } else { "read (staged)" };
        let terr = |call: &'static str| move |result| GpuError::Kernel { kernel: what, call, result };
        let chunk = self.staging_bytes as usize;
        let mut at = 0;
        let mut first = true;
        while at < len || first {
            let n = chunk.min(len - at);
            if let Staged::Write(b) = &transfer {
                unsafe { std::ptr::copy_nonoverlapping(b.as_ptr().add(at), self.staging_mapped, n) };
            }
            let (src, dst, src_off, dst_off) = match upload {
                true => (self.staging_buffer, self.buffer, 0, offset + at as u64),
                false => (self.buffer, self.staging_buffer, offset + at as u64, 0),
            };
            unsafe {
                d.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()).map_err(terr("vkResetCommandBuffer"))?;
                d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                    .map_err(terr("vkBeginCommandBuffer"))?;
                // Earlier kernels' writes before the copy, the copy before later kernels and
                // before the host reads the staging buffer.
                self.barrier();
                if first {
                    self.record_deferred(cb);
                    self.barrier();
                }
                if n > 0 {
                    d.cmd_copy_buffer(cb, src, dst, &[vk::BufferCopy { src_offset: src_off, dst_offset: dst_off, size: n as u64 }]);
                }
                self.barrier();
                let to_host = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
                d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
                d.end_command_buffer(cb).map_err(terr("vkEndCommandBuffer"))?;
                let cbs = [cb];
                d.queue_submit(self.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], self.fence).map_err(terr("vkQueueSubmit"))?;
                d.wait_for_fences(&[self.fence], true, u64::MAX).map_err(terr("vkWaitForFences"))?;
                d.reset_fences(&[self.fence]).map_err(terr("vkResetFences"))?;
            }
            if let Staged::Read(b) = &mut transfer {
                unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped, b.as_mut_ptr().add(at), n) };
            }
            at += n;
            first = false;
        }
        self.release_deferred();
        Ok(())
    }

    /// Starts recording a submission.
    pub fn begin(&mut self) -> Result<(), GpuError> {
        let mut running = self.in_flight.get()[0].is_some();
        if running && (2 * self.submitted > MAX_DISPATCHES || 4 * self.prefetch_submitted.1 > 3 * self.prefetch_bytes) {
            // A chain of submissions, each left running while the next was recorded, has used
            // half of the timestamp queries (a recording past them all is an error) or three
            // quarters of the room for copies to the host (past it, reads wait for the
            // device): this one starts on an idle queue, where they start over.
            self.wait_in_flight()?;
            running = false;
        }
        self.recording_since = Some((Instant::now(), running));
        if !running {
            self.collect_timestamps()?;
        }
        let d = &self.device;
        unsafe {
            d.reset_command_buffer(self.command_buffer, vk::CommandBufferResetFlags::empty()).map_err(vk_err("vkResetCommandBuffer"))?;
            d.begin_command_buffer(
                self.command_buffer,
                &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT),
            )
            .map_err(vk_err("vkBeginCommandBuffer"))?;
        }
        if running {
            // After a submission still running: its queries, prefetched copies and deferred
            // copies are kept (what a recording abandoned since added is dropped), and this one
            // starts with a barrier that orders it after that one's commands.
            self.recorded = self.submitted;
            let (len, used) = self.prefetch_submitted;
            self.prefetched.get_mut().truncate(len);
            self.prefetch_done.set(self.prefetch_done.get().min(len));
            self.prefetch_used = used;
            if let (Some(q), true) = (self.query_pool, self.timing) {
                let first = 2 * self.recorded as u32;
                unsafe { d.cmd_reset_query_pool(self.command_buffer, q, first, 2 * MAX_DISPATCHES as u32 - first) };
            }
            self.barrier();
        } else {
            self.timing = self.timestamps_wanted && self.query_pool.is_some();
            if let (Some(q), true) = (self.query_pool, self.timing) {
                unsafe { d.cmd_reset_query_pool(self.command_buffer, q, 0, 2 * MAX_DISPATCHES as u32) };
            }
            self.prefetched.get_mut().clear();
            self.prefetch_done.set(0);
            self.prefetch_used = 0;
            self.recorded = 0;
            self.submitted = 0;
        }
        self.hazards.clear();
        if !self.deferred.borrow().is_empty() {
            self.record_deferred(self.command_buffer);
            self.barrier();
        }
        self.recording = true;
        self.last_kernel = None;
        Ok(())
    }

    /// Adds the timestamps of the submissions since the last collection to the profile (the
    /// queue is idle).
    fn collect_timestamps(&mut self) -> Result<(), GpuError> {
        if !std::mem::take(&mut self.untimed) {
            return Ok(());
        }
        if let (Some(q), Some(period), true) = (self.query_pool, self.info.timestamp_period_ns, self.timing) {
            let n = self.submitted;
            if n > 0 {
                let ts = &mut self.timestamps[..2 * n];
                unsafe { self.device.get_query_pool_results(q, 0, ts, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }
                    .map_err(vk_err("vkGetQueryPoolResults"))?;
                for i in 0..n {
                    let k = self.recorded_kernels[i].index();
                    let ticks = self.timestamps[2 * i + 1].wrapping_sub(self.timestamps[2 * i]);
                    self.profile.dispatches[k] += 1;
                    self.profile.total_ns[k] += ticks as f64 * period as f64;
                }
                let first = self.timestamps[..2 * n].iter().step_by(2).min().copied().unwrap_or(0);
                let last = self.timestamps[..2 * n].iter().skip(1).step_by(2).max().copied().unwrap_or(0);
                self.profile.span_ns += last.saturating_sub(first) as f64 * period as f64;
                self.profile.spans += 1;
                // The last two stretches for `last_timeline` (a mapper step's two).
                self.timeline.swap(0, 1);
                for i in 0..n {
                    self.timeline[1].1[i] = (self.recorded_kernels[i], self.timestamps[2 * i], self.timestamps[2 * i + 1]);
                }
                self.timeline[1].0 = n;
            }
        }
        Ok(())
    }

    /// Orders a command touching `accesses` (`(range, written)`) after the earlier commands
    /// of the submission where it must ([`Hazards`]), then remembers its accesses.
    fn order(&mut self, accesses: &[(GpuRange, bool)]) {
        if self.hazards.needs_barrier(accesses) {
            self.barrier();
            self.hazards.clear();
            let mut h = self.host.get();
            h.barriers += 1;
            self.host.set(h);
        }
        self.hazards.record(accesses);
        // A copy for the host taken before this command no longer is the arena's where it
        // writes.
        for (range, written) in accesses {
            if *written {
                let (start, end) = (range.offset, range.offset + range.size);
                for p in self.prefetched.get_mut().iter_mut() {
                    let c = &p.copy;
                    if start < c.src_offset + c.size && c.src_offset < end {
                        p.overwritten = true;
                    }
                }
            }
        }
    }

    /// Timestamp queries around every dispatch from the next [`Self::begin`] on (`on`, the
    /// default) or none (they cost the device a little per dispatch, and the host a read per
    /// submission). Returns whether the device can take them at all.
    pub fn set_timestamps(&mut self, on: bool) -> bool {
        self.timestamps_wanted = on;
        self.query_pool.is_some()
    }

    fn barrier(&self) {
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(
                vk::AccessFlags::SHADER_READ
                    | vk::AccessFlags::SHADER_WRITE
                    | vk::AccessFlags::TRANSFER_READ
                    | vk::AccessFlags::TRANSFER_WRITE
                    | vk::AccessFlags::INDIRECT_COMMAND_READ,
            )];
        let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
        let dst = stages | vk::PipelineStageFlags::DRAW_INDIRECT;
        unsafe { self.device.cmd_pipeline_barrier(self.command_buffer, stages, dst, vk::DependencyFlags::empty(), &mb, &[], &[]) };
    }

    /// Records `kernel` over `groups` workgroups with `buffers` bound in the order of the
    /// kernel's bindings and `immediates` (its `var<immediate>` block, exactly its size).
    pub fn dispatch(&mut self, kernel: impl Into<KernelId>, buffers: &[GpuRange], immediates: &[u8], groups: [u32; 3]) -> Result<(), GpuError> {
        self.record_dispatch(kernel.into(), buffers, immediates, Launch::Groups(groups))
    }

    /// [`Self::dispatch`] with the workgroup counts read by the device from `args` (three
    /// u32, written by an earlier kernel of the submission: `vkCmdDispatchIndirect`), so a
    /// size computed on the device needs no round trip to the host. Counts beyond the
    /// device's limits are the writer's to prevent (the host cannot check them).
    pub fn dispatch_indirect(&mut self, kernel: impl Into<KernelId>, buffers: &[GpuRange], immediates: &[u8], args: GpuRange) -> Result<(), GpuError> {
        if args.size < 12 || args.offset % 4 != 0 {
            return Err(GpuError::OutOfRange { what: "indirect dispatch arguments (3 u32)", requested: 12, len: args.size as usize });
        }
        self.record_dispatch(kernel.into(), buffers, immediates, Launch::Indirect(args))
    }

    /// The table entry of `kernel`.
    pub fn kernel_info(&self, kernel: impl Into<KernelId>) -> Result<&'static KernelInfo, GpuError> {
        let kernel = kernel.into();
        self.kernels.get(kernel.index()).ok_or(GpuError::UnknownKernel { index: kernel.index(), table: self.kernels.len() })
    }

    fn record_dispatch(&mut self, kernel: KernelId, buffers: &[GpuRange], immediates: &[u8], launch: Launch) -> Result<(), GpuError> {
        let info = self.kernel_info(kernel)?;
        let name = info.name;
        if !self.recording {
            return Err(GpuError::NotRecording { what: name });
        }
        if buffers.len() != info.bindings.len() {
            return Err(GpuError::BindingCount { kernel: name, expected: info.bindings.len(), got: buffers.len() });
        }
        if immediates.len() != info.immediate_bytes as usize {
            return Err(GpuError::Immediates { kernel: name, expected: info.immediate_bytes, got: immediates.len() });
        }
        if let Launch::Groups(groups) = launch {
            for (g, max) in groups.iter().zip(self.max_groups) {
                if *g > max {
                    return Err(GpuError::TooManyWorkgroups { kernel: name, groups: *g, max });
                }
            }
        }
        if self.recorded >= MAX_DISPATCHES {
            return Err(GpuError::TooManyDispatches { kernel: name, capacity: MAX_DISPATCHES });
        }
        if matches!(launch, Launch::Groups(g) if g.contains(&0)) {
            return Ok(());
        }
        let mut infos = [vk::DescriptorBufferInfo::default(); MAX_BINDINGS];
        let mut accesses = [(GpuRange { offset: 0, size: 0 }, false); MAX_BINDINGS + 1];
        for (((slot, access), range), b) in infos.iter_mut().zip(accesses.iter_mut()).zip(buffers).zip(info.bindings) {
            if range.size == 0 {
                return Err(GpuError::EmptyBinding { kernel: name, binding: b.binding, name: b.name });
            }
            *slot = vk::DescriptorBufferInfo { buffer: self.buffer, offset: range.offset, range: range.size };
            *access = (*range, b.kind == BindingKind::StorageReadWrite);
        }
        let mut writes = [vk::WriteDescriptorSet::default(); MAX_BINDINGS];
        for (i, (w, b)) in writes.iter_mut().zip(info.bindings).enumerate() {
            *w = vk::WriteDescriptorSet::default()
                .dst_binding(b.binding)
                .descriptor_type(match b.kind {
                    BindingKind::Uniform => vk::DescriptorType::UNIFORM_BUFFER,
                    _ => vk::DescriptorType::STORAGE_BUFFER,
                })
                .buffer_info(std::slice::from_ref(&infos[i]));
        }
        if self.pipelines[kernel.index()].pipeline == vk::Pipeline::null() {
            return Err(GpuError::NoFloatAtomics { kernel: name });
        }
        let mut n_access = info.bindings.len();
        if let Launch::Indirect(args) = launch {
            accesses[n_access] = (GpuRange { offset: args.offset, size: 12 }, false);
            n_access += 1;
        }
        self.order(&accesses[..n_access]);
        let p = &self.pipelines[kernel.index()];
        let cb = self.command_buffer;
        let slot = self.recorded as u32;
        let timing = self.query_pool.filter(|_| self.timing);
        unsafe {
            if let Some(q) = timing {
                self.device.cmd_write_timestamp(cb, vk::PipelineStageFlags::TOP_OF_PIPE, q, 2 * slot);
            }
            self.device.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, p.pipeline);
            self.push_descriptor.cmd_push_descriptor_set(cb, vk::PipelineBindPoint::COMPUTE, p.layout, 0, &writes[..info.bindings.len()]);
            if !immediates.is_empty() {
                self.device.cmd_push_constants(cb, p.layout, vk::ShaderStageFlags::COMPUTE, 0, immediates);
            }
            match launch {
                Launch::Groups(g) => self.device.cmd_dispatch(cb, g[0], g[1], g[2]),
                Launch::Indirect(args) => self.device.cmd_dispatch_indirect(cb, self.buffer, args.offset),
            }
            if let Some(q) = timing {
                self.device.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, q, 2 * slot + 1);
            }
        }
        self.recorded_kernels[self.recorded] = kernel;
        self.recorded += 1;
        self.last_kernel = Some(kernel);
        Ok(())
    }

    /// [`Self::dispatch`] with the buffers looked up by the WGSL names of the kernel's
    /// bindings (`lookup(name)`), so the caller writes no binding list by hand; a binding
    /// `lookup` does not know is [`GpuError::UnknownBinding`].
    pub fn dispatch_named(&mut self, kernel: impl Into<KernelId>, lookup: impl Fn(&str) -> Option<GpuRange>, immediates: &[u8], groups: [u32; 3]) -> Result<(), GpuError> {
        let kernel = kernel.into();
        let info = self.kernel_info(kernel)?;
        let mut ranges = [GpuRange { offset: 0, size: 0 }; MAX_BINDINGS];
        for (slot, b) in ranges.iter_mut().zip(info.bindings) {
            *slot = lookup(b.name).ok_or(GpuError::UnknownBinding { kernel: info.name, name: b.name })?;
        }
        self.dispatch(kernel, &ranges[..info.bindings.len().min(MAX_BINDINGS)], immediates, groups)
    }

    /// Records filling `range` with the u32 `value` (size a multiple of 4).
    pub fn fill(&mut self, range: GpuRange, value: u32) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "fill" });
        }
        self.order(&[(range, true)]);
        unsafe { self.device.cmd_fill_buffer(self.command_buffer, self.buffer, range.offset, range.size, value) };
        Ok(())
    }

    /// Records a copy of `range` for the host at this point of the submission: after
    /// [`Self::submit_and_wait`] a [`Self::read`] within it takes the copy instead of a
    /// submission of its own (until the next [`Self::begin`] or [`Self::write`]). Staged
    /// transfers only (a mapped arena is read in place); a range that does not fit what is
    /// left of the prefetch space is read the ordinary way.
    pub fn prefetch(&mut self, range: GpuRange) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "prefetch" });
        }
        let size = range.size.next_multiple_of(4);
        if !self.mapped.is_null() || size == 0 {
            return Ok(());
        }
        if self.prefetch_used + size > self.prefetch_bytes || self.prefetched.get_mut().len() == MAX_PREFETCHES {
            // No room: a read takes the range from the arena, not from an older copy.
            self.forget_prefetched(range.offset, range.offset + range.size);
            return Ok(());
        }
        let copy = vk::BufferCopy { src_offset: range.offset, dst_offset: self.prefetch_at + self.prefetch_used, size: range.size };
        self.order(&[(range, false)]);
        let d = &self.device;
        let cb = self.command_buffer;
        unsafe {
            d.cmd_copy_buffer(cb, self.buffer, self.staging_buffer, &[copy]);
            let to_host = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
        }
        self.prefetch_used += size;
        self.prefetched.get_mut().push(Prefetched { copy, overwritten: false });
        Ok(())
    }

    /// Records a copy of `src` into `dst` (the smaller of the two sizes).
    pub fn copy(&mut self, src: GpuRange, dst: GpuRange) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "copy" });
        }
        let size = src.size.min(dst.size);
        let region = [vk::BufferCopy { src_offset: src.offset, dst_offset: dst.offset, size }];
        self.order(&[(GpuRange { offset: src.offset, size }, false), (GpuRange { offset: dst.offset, size }, true)]);
        unsafe { self.device.cmd_copy_buffer(self.command_buffer, self.buffer, self.buffer, &region) };
        Ok(())
    }

    /// Ends the recording: the host-visibility barrier, `vkEndCommandBuffer`, `vkQueueSubmit`
    /// with `self.fence`.
    fn end_and_submit(&mut self) -> Result<Instant, GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit" });
        }
        self.recording = false;
        let name = self.last_kernel.and_then(|k| self.kernels.get(k.index())).map_or("(no kernel)", |i| i.name);
        let d = &self.device;
        unsafe {
            // What the kernels wrote, visible to the host (a mapped arena is read in place).
            let to_host = [vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::HOST_READ)];
            let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
            d.cmd_pipeline_barrier(self.command_buffer, stages, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
            d.end_command_buffer(self.command_buffer).map_err(vk_err("vkEndCommandBuffer"))?;
            let cbs = [self.command_buffer];
            let submit = [vk::SubmitInfo::default().command_buffers(&cbs)];
            let t0 = Instant::now();
            if let Some((since, running)) = self.recording_since.take() {
                let mut h = self.host.get();
                let ns = t0.duration_since(since).as_nanos() as u64;
                h.record_ns += ns;
                // Recorded while nothing ran, or the one running finished meanwhile (unknown
                // here: counted as running).
                if !running {
                    h.record_idle_ns += ns;
                }
                self.host.set(h);
            }
            d.queue_submit(self.queue, &submit, self.fence).map_err(|result| GpuError::Kernel { kernel: name, call: "vkQueueSubmit", result })?;
            if let Some(since) = self.idle_since.take() {
                let mut h = self.host.get();
                h.idle_ns += since.elapsed().as_nanos() as u64;
                h.idle_gaps += 1;
                self.host.set(h);
            }
            self.submitted = self.recorded;
            self.prefetch_submitted = (self.prefetched.get_mut().len(), self.prefetch_used);
            self.untimed = true;
            let mut h = self.host.get();
            h.submits += 1;
            self.host.set(h);
            Ok(t0)
        }
    }

    /// Submits what was recorded and returns without waiting: the device runs it while the
    /// host records the next submission, which [`Self::begin`] orders after it. Reads and
    /// writes that are not deferred wait for it ([`Self::read_prefetched`] only for the
    /// submission that made its copy); [`Self::submit_and_wait`] waits for all. Two
    /// submissions run this way at a time: a third waits for the oldest first, so the device
    /// has the next one queued behind the one the host waits for.
    pub fn submit(&mut self) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit" });
        }
        if self.in_flight.get()[SLOTS - 2].is_some() {
            self.wait_oldest()?;
        }
        let since = self.end_and_submit()?;
        let mut flights = self.in_flight.get();
        let flight = Flight { slot: self.current, since, prefetch_len: self.prefetch_submitted.0 };
        *flights.iter_mut().find(|f| f.is_none()).expect("a free place: the oldest was waited for") = Some(flight);
        self.in_flight.set(flights);
        // The next recording takes the slot no running submission holds.
        self.current = (0..SLOTS).find(|s| flights.iter().flatten().all(|f| f.slot != *s)).expect("one slot more than can run");
        (self.command_buffer, self.fence) = self.slots[self.current];
        Ok(())
    }

    /// Submits what was recorded, waits for it (and for a submission [`Self::submit`] left
    /// running) and adds the dispatch times to the profile.
    pub fn submit_and_wait(&mut self) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit_and_wait" });
        }
        let name = self.last_kernel.and_then(|k| self.kernels.get(k.index())).map_or("(no kernel)", |i| i.name);
        let t0 = self.end_and_submit()?;
        let d = &self.device;
        unsafe {
            self.wait_fence(self.fence).map_err(|result| GpuError::Kernel { kernel: name, call: "vkWaitForFences (last kernel recorded)", result })?;
            d.reset_fences(&[self.fence]).map_err(vk_err("vkResetFences"))?;
        }
        let mut h = self.host.get();
        h.submit_wait_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        self.wait_in_flight()?;
        self.prefetch_done.set(self.prefetched.get_mut().len());
        self.idle_since.set(Some(Instant::now()));
        self.collect_timestamps()?;
        self.release_deferred();
        Ok(())
    }

    /// Waits for every submission left running and adds their dispatch times to the profile
    /// (a chain of submissions, each left running while the next is recorded, reaches an idle
    /// queue only now and then).
    pub fn finish(&mut self) -> Result<(), GpuError> {
        if self.recording {
            return Err(GpuError::NotRecording { what: "finish (a recording is open)" });
        }
        self.wait_in_flight()?;
        self.collect_timestamps()?;
        self.release_deferred();
        Ok(())
    }

    /// Per-kernel times so far.
    pub fn profile(&self) -> &KernelProfile {
        &self.profile
    }

    /// The dispatches of the last two timed stretches of the queue (see
    /// [`KernelProfile::span_ns`]; a mapper step's two submissions) in recording order:
    /// `(kernel, start ms, end ms)` from the earliest dispatch's start. Empty without
    /// timestamps.
    pub fn last_timeline(&self) -> impl Iterator<Item = (&'static KernelInfo, f64, f64)> + '_ {
        let entries = || self.timeline.iter().flat_map(|(n, e)| e[..*n].iter());
        let first = entries().map(|e| e.1).min().unwrap_or(0);
        let period = self.info.timestamp_period_ns.unwrap_or(0.0) as f64 * 1e-6;
        let kernels = self.kernels;
        entries().map(move |&(k, start, end)| (&kernels[k.index()], start.wrapping_sub(first) as f64 * period, end.wrapping_sub(first) as f64 * period))
    }
    pub fn reset_profile(&mut self) {
        self.profile = KernelProfile::new(self.kernels);
        self.host.set(HostStats::default());
    }
    /// Host-side counters so far ([`HostStats`]).
    pub fn host_stats(&self) -> HostStats {
        self.host.get()
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
