//! The mapper's stages on the Vulkan device (`gpu/`), each the kernel twin of a CPU
//! reference in [`super::render`] / [`super::adam`] with the same name and buffer order:
//!
//! | stage | kernel | CPU reference |
//! |---|---|---|
//! | projection | `project_forward.project_forward` | `project_gaussians` |
//! | tile counts prefix sum | `prefix_sum.*` (via `vulkan::ops`) | `exclusive_scan` |
//! | tile binning | `map_gaussian_to_intersects` | `emit_intersections` |
//! | depth/tile key sort | `radix_sort.*` (via `vulkan::ops`) | `radix_sort_pairs` |
//! | tile ranges, index maps | `tile_ranges.{tile_ranges, gather_sorted, invert_permutation}` | `tile_ranges`, `gather_sorted_gaussians`, `invert_permutation` |
//! | rasterise forward with the medium | `rasterize.rasterize` | `rasterize_forward` |
//! | rasterise backward, per-Gaussian sums | `rasterize_backward.{rasterize_backward, rasterize_backward_atomic, reduce_isect_grads}` | `rasterize_backward`, `reduce_isect_grads` |
//! | projection backward | `project_backward.project_backward` | `project_backward` |
//! | Adam | `adam.adam_step` | `AdamGroup::step` |
//! | losses and their gradients ([`loss`]) | `loss.*` | `total_loss` |
//! | Adam over the whole map ([`optimiser`]) | `adam_map.{check_grads, map_step}` | `AdamGroup::step` per group |
//! | medium MLP forward and backward ([`medium`]) | `medium.*` | `MediumWorkspace::{forward, backward}` |
//! | pruning: keep flags, compaction ([`compact`]) | `compact.{keep_flags, scatter}` | the prune rule of `densify_and_prune`, `retain_strided` |
//!
//! [`GpuProjection`], [`GpuBinning`], [`GpuRasterForward`], [`GpuRasterBackward`] and
//! [`GpuProjectBackward`] own their buffers, allocated once from the arena for a fixed
//! capacity; [`GpuForwardRenderer`] runs the forward stages as `RasterWorkspace::forward`
//! does, [`GpuRenderer`] the forward and the backward as `RasterWorkspace::{forward,
//! backward}` do (one submission for the backward). The backward writes one gradient per
//! intersection and sums them per Gaussian. Within a tile, a subgroup's sums are added to the
//! intersection's gradient with float atomics (`rasterize_backward_atomic`) by default; in
//! deterministic mode ([`duv_gpu::GpuOptions::deterministic`], and on devices without
//! float atomics) through workgroup memory in subgroup order (`rasterize_backward`), so
//! results are bit-identical from run to run on one device. No other kernel adds floats with
//! atomics.
//! [`RenderBackend`] is what the mapper renders with: these stages, or the CPU reference
//! ([`MapperDevice`] chooses; no Vulkan device at all falls back with one warning).
//!
//! A mapper step on Vulkan ([`RenderBackend::forward_for_loss`],
//! [`RenderBackend::loss_and_backward`], [`RenderBackend::adam_step`]): the map is resident
//! on the device between densification steps ([`GpuRenderer::make_resident`]), the forward
//! leaves its images on the device, the loss kernels write the backward's upstream gradients
//! in place, Adam updates the device map, and only the loss sums, the medium gradients and
//! the updated parameters come back to the host. The medium network and densification
//! (clone, split) still run on the host: the medium planes go up and their gradients come
//! back every step, and at each densify/prune step the map, its statistics and moments come
//! back ([`GpuRenderer::release`]) and go up again at the next step.

pub mod compact;
pub mod kernels;
pub mod loss;
pub mod medium;
pub mod ops;
pub mod optimiser;
mod project;
mod bin;
mod raster_fwd;
mod raster_bwd;
mod project_bwd;
mod adam;
mod renderer;

pub use kernels::{Kernel, KERNELS};

pub use project::*;
pub use bin::*;
pub use raster_fwd::*;
pub use raster_bwd::*;
pub use project_bwd::*;
pub use adam::*;
pub use renderer::*;
