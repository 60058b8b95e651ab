//! Raw Vulkan compute on `ash`: the device layer the mapper's kernels run on. Knows nothing
//! of SLAM; `map/` is its only user.
//!
//! - [`kernels`]: what a kernel table holds (entry point, workgroup size, bindings,
//!   immediate-block size, SPIR-V). The table is the caller's data, handed to
//!   [`GpuContext::new`]: the mapper's is generated from `kernels/*.wgsl` by
//!   `crates/duv-map/build.rs`. This crate names no kernel.
//! - [`GpuContext`] ([`device`]): instance and device selection (discrete, then integrated,
//!   then virtual, then CPU devices such as lavapipe; `DUV_VULKAN_DEVICE` picks one by index
//!   or name substring), one compute queue, three command buffers and fences (one recording,
//!   up to two submissions running), every pipeline built once at start-up through an on-disk
//!   pipeline cache keyed by vendor, device, driver and cache UUID, push descriptors, host
//!   transfers (mapped, or staged through a host-cached buffer), timestamp queries per
//!   dispatch ([`KernelProfile`]). The context is a few parts, one per concern (selection,
//!   pipelines, arena memory, transfers, recording, submission, profiling), each defined in
//!   its file of `device/` with the methods that use it.
//! - [`arena`]: all GPU memory is one buffer allocated once at start-up from the board's
//!   budget (`budgets.gpu_mb`); [`GpuBuffer`]s are ranges of it; the peak used is reported
//!   and an allocation past the budget is an error, never a reallocation.
//!
//! Errors name the kernel that failed ([`GpuError`]). No Vulkan loader or device at all is
//! [`GpuError::NoLoader`] / [`GpuError::NoDevice`], which the mapper turns into a CPU
//! fallback with one warning.

pub mod arena;
pub mod device;
pub mod kernels;

pub use arena::{GpuBuffer, GpuRange};
pub use device::{DeviceInfo, GpuContext, GpuOptions, HostStats, KernelProfile, DEVICE_ENV, MAX_DISPATCHES, STAGING_BYTES};
pub use kernels::{BindingInfo, BindingKind, KernelId, KernelInfo, MAX_KERNELS};

use ash::vk;

/// Why a GPU operation failed. Every variant that concerns a kernel names it
/// (`file.entry_point`).
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no Vulkan loader (libvulkan.so.1): {reason}")]
    NoLoader { reason: String },
    #[error("no usable Vulkan device (compute queue, Vulkan 1.1, VK_KHR_push_descriptor, compute subgroups with vote, shuffle and arithmetic); devices seen: [{seen}]")]
    NoDevice { seen: String },
    #[error("{env}={wanted} matches no usable Vulkan device; devices: [{seen}]")]
    NoMatchingDevice { env: &'static str, wanted: String, seen: String },
    #[error("Vulkan {call} failed: {result}")]
    Vulkan { call: &'static str, result: vk::Result },
    #[error("kernel {kernel}: Vulkan {call} failed: {result}")]
    Kernel { kernel: &'static str, call: &'static str, result: vk::Result },
    #[error("kernel {kernel}: {got} buffers bound, the kernel has {expected} bindings")]
    BindingCount { kernel: &'static str, expected: usize, got: usize },
    #[error("kernel {kernel}: no buffer given for its binding {name}")]
    UnknownBinding { kernel: &'static str, name: &'static str },
    #[error("kernel {kernel}: binding {binding} ({name}) is an empty range")]
    EmptyBinding { kernel: &'static str, binding: u32, name: &'static str },
    #[error("kernel {kernel}: {got} immediate bytes given, the kernel declares {expected}")]
    Immediates { kernel: &'static str, expected: u32, got: usize },
    #[error("kernel {kernel}: {groups} workgroups in one dimension, the device allows {max}")]
    TooManyWorkgroups { kernel: &'static str, groups: u32, max: u32 },
    #[error("kernel {kernel}: more than {capacity} dispatches in one submission")]
    TooManyDispatches { kernel: &'static str, capacity: usize },
    #[error("GPU arena: {what} needs {requested} bytes, {free} of {capacity} free (budgets.gpu_mb)")]
    ArenaFull { what: &'static str, requested: u64, free: u64, capacity: u64 },
    #[error("GPU buffer {what}: {requested} elements accessed, it holds {len}")]
    OutOfRange { what: &'static str, requested: usize, len: usize },
    #[error("no host-visible memory type for the GPU arena")]
    NoMemoryType,
    #[error("GPU arena of {requested} bytes exceeds the device limit of {limit} bytes")]
    ArenaTooLarge { requested: u64, limit: u64 },
    #[error("{what} called outside begin()/submit_and_wait()")]
    NotRecording { what: &'static str },
    #[error("kernel {kernel} needs float atomics (VK_EXT_shader_atomic_float), which this device lacks; use deterministic mode")]
    NoFloatAtomics { kernel: &'static str },
    #[error("kernel #{index} is not in the kernel table ({table} kernels)")]
    UnknownKernel { index: usize, table: usize },
    #[error("{kernels} kernels in the table, at most {max} are supported")]
    TooManyKernels { kernels: usize, max: usize },
    #[error("pipeline cache {path}: {source}")]
    PipelineCacheIo { path: String, source: std::io::Error },
}

impl GpuError {
    /// True when no Vulkan is available at all (the caller falls back to the CPU reference).
    pub fn is_unavailable(&self) -> bool {
        matches!(self, GpuError::NoLoader { .. } | GpuError::NoDevice { .. })
    }
}
