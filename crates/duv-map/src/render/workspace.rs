//! [`RasterWorkspace`]: every buffer of the renderer, allocated once from a
//! [`RasterCapacity`], and the stage sequence of the forward and backward passes. After the
//! first render nothing allocates (proven by `tests/render_alloc.rs`).

use rayon::prelude::*;

use super::bin::{emit_intersections, exclusive_scan, isect_key_bits, scan_blocks};
use super::project::{project_gaussians, ProjectedSplat, ProjectionSetup, TileRect};
use super::project_bwd::project_backward;
use super::raster_bwd::{rasterize_backward, reduce_isect_grads, SplatGrad};
use super::raster_fwd::{rasterize_forward, RasterInputs};
use super::sort::{radix_sort_pairs, sort_histogram_len};
use super::tiles::{gather_sorted_gaussians, invert_permutation, tile_ranges};
use super::{DepthMode, MediumPlanes, RasterCapacity, RenderConfig, RenderError, RenderOutput, RenderUpstream, TileGrid};
use duv_core::{Image, PinholeCamera, Se3};
use crate::gaussians::{GaussianGrads, Gaussians};

/// Counts of one forward pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderStats {
    /// Gaussians that reach at least one tile (0, not counted, from the Vulkan forward of an
    /// optimisation step, `GpuForwardRenderer::forward_on_device`).
    pub visible: usize,
    /// (tile, Gaussian) intersections.
    pub intersections: usize,
}

/// What the backward pass needs to know about the last forward pass.
#[derive(Clone, Copy, Debug)]
struct ForwardState {
    setup: ProjectionSetup<f32>,
    grid: TileGrid,
    n_gaussians: usize,
    n_isects: usize,
    depth_mode: DepthMode,
}

/// All buffers of the renderer at fixed capacity, and the state of the last forward pass
/// (which [`Self::backward`] differentiates).
///
/// Parallel stages use rayon. Called from a thread of the rayon pool (e.g. a mapping loop
/// inside `ThreadPool::install`), a warmed-up render allocates nothing; called from outside
/// the pool, each parallel stage goes through rayon's global injector queue, which allocates
/// one block per 63 injected jobs (about one small allocation every four renders).
pub struct RasterWorkspace {
    capacity: RasterCapacity,
    // Per Gaussian.
    splats: Vec<ProjectedSplat<f32>>,
    rects: Vec<TileRect>,
    tiles_touched: Vec<u32>,
    isect_offsets: Vec<u32>,
    scan_block_sums: Vec<u64>,
    splat_grads: Vec<SplatGrad<f32>>,
    // Per intersection.
    keys: Vec<u64>,
    keys_tmp: Vec<u64>,
    values: Vec<u32>,
    values_tmp: Vec<u32>,
    isect_gaussian: Vec<u32>,
    sorted_gaussian: Vec<u32>,
    slot_to_sorted: Vec<u32>,
    partials: Vec<SplatGrad<f32>>,
    sort_histograms: Vec<u32>,
    // Per tile.
    tile_offsets: Vec<u32>,
    last: Option<ForwardState>,
}

impl RasterWorkspace {
    /// Allocates every buffer. Memory: about 120 bytes per Gaussian and 88 bytes per
    /// intersection.
    pub fn new(capacity: RasterCapacity) -> Result<Self, RenderError> {
        if capacity.width == 0 || capacity.height == 0 {
            return Err(RenderError::EmptyImage { width: capacity.width, height: capacity.height });
        }
        if capacity.max_intersections > u32::MAX as usize || capacity.max_gaussians >= u32::MAX as usize {
            return Err(RenderError::CapacityExceeded {
                what: "intersection index (u32)",
                requested: capacity.max_intersections.max(capacity.max_gaussians),
                capacity: u32::MAX as usize,
            });
        }
        let (g, n) = (capacity.max_gaussians, capacity.max_intersections);
        let tiles = TileGrid::new(capacity.width, capacity.height).num_tiles();
        Ok(RasterWorkspace {
            capacity,
            splats: vec![ProjectedSplat::default(); g],
            rects: vec![TileRect::default(); g],
            tiles_touched: vec![0; g],
            isect_offsets: vec![0; g + 1],
            scan_block_sums: vec![0; scan_blocks(g)],
            splat_grads: vec![SplatGrad::default(); g],
            keys: vec![0; n],
            keys_tmp: vec![0; n],
            values: vec![0; n],
            values_tmp: vec![0; n],
            isect_gaussian: vec![0; n],
            sorted_gaussian: vec![0; n],
            slot_to_sorted: vec![0; n],
            partials: vec![SplatGrad::default(); n],
            sort_histograms: vec![0; sort_histogram_len(n)],
            tile_offsets: vec![0; tiles + 1],
            last: None,
        })
    }

    pub fn capacity(&self) -> RasterCapacity {
        self.capacity
    }

    /// The projected splats of the last forward pass (index = Gaussian index).
    pub fn splats(&self) -> &[ProjectedSplat<f32>] {
        &self.splats[..self.last.map_or(0, |l| l.n_gaussians)]
    }

    /// Tile count per Gaussian of the last forward pass (0: culled).
    pub fn tiles_touched(&self) -> &[u32] {
        &self.tiles_touched[..self.last.map_or(0, |l| l.n_gaussians)]
    }

    /// Renders `gaussians` seen from `cam_from_world` through `camera` into `out`, with the
    /// medium parameters of every pixel. On [`RenderError::TileOverflow`] nothing is
    /// rendered; the error carries the intersection count a larger workspace would need.
    pub fn forward(
        &mut self,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, RenderError> {
        self.last = None;
        if camera.width == 0 || camera.height == 0 {
            return Err(RenderError::EmptyImage { width: camera.width, height: camera.height });
        }
        let setup = ProjectionSetup::<f32>::new(camera, cam_from_world, config)?;
        let grid = TileGrid::new(camera.width, camera.height);
        if camera.width > self.capacity.width || camera.height > self.capacity.height {
            return Err(RenderError::CapacityExceeded {
                what: "image pixels",
                requested: camera.width * camera.height,
                capacity: self.capacity.width * self.capacity.height,
            });
        }
        let n = gaussians.len();
        if n > self.capacity.max_gaussians {
            return Err(RenderError::CapacityExceeded { what: "Gaussians", requested: n, capacity: self.capacity.max_gaussians });
        }
        check_size("medium planes", medium.width(), medium.height(), &grid)?;
        for (_, plane) in medium.planes() {
            check_size("medium planes", plane.width, plane.height, &grid)?;
        }
        check_output(out, &grid)?;
        validate_gaussians(gaussians)?;
        for (what, plane) in medium.planes() {
            check_rgb(what, plane, what != "c_med")?;
        }

        {
            let _span = tracing::debug_span!("map.project", gaussians = n).entered();
            project_gaussians(gaussians, &setup, &grid, &mut self.splats, &mut self.rects, &mut self.tiles_touched);
        }
        let n_isects = {
            let _span = tracing::debug_span!("map.bin").entered();
            let limit = self.capacity.max_intersections as u64;
            let total = exclusive_scan(&self.tiles_touched[..n], &mut self.isect_offsets[..n + 1], &mut self.scan_block_sums, limit)
                .map_err(|needed| RenderError::TileOverflow { needed, capacity: self.capacity.max_intersections })?
                as usize;
            emit_intersections(
                &self.splats[..n],
                &self.rects[..n],
                &self.isect_offsets[..n + 1],
                &grid,
                &mut self.keys,
                &mut self.values,
                &mut self.isect_gaussian,
            );
            total
        };
        {
            let _span = tracing::debug_span!("map.sort", intersections = n_isects).entered();
            let key_bits = isect_key_bits(grid.num_tiles());
            radix_sort_pairs(
                &mut self.keys[..n_isects],
                &mut self.values[..n_isects],
                &mut self.keys_tmp,
                &mut self.values_tmp,
                &mut self.sort_histograms,
                key_bits,
            );
        }
        {
            let _span = tracing::debug_span!("map.tiles").entered();
            tile_ranges(&self.keys[..n_isects], &mut self.tile_offsets[..grid.num_tiles() + 1]);
            gather_sorted_gaussians(&self.values[..n_isects], &self.isect_gaussian, &mut self.sorted_gaussian);
            invert_permutation(&self.values[..n_isects], &mut self.slot_to_sorted);
        }
        {
            let _span = tracing::debug_span!("map.raster_fwd", width = grid.width, height = grid.height).entered();
            let inp = raster_inputs(&self.splats[..n], &self.sorted_gaussian, &self.tile_offsets, &setup, &grid, config.depth_mode);
            rasterize_forward(&inp, medium, out);
        }
        let visible = self.tiles_touched[..n].par_iter().filter(|&&c| c > 0).count();
        tracing::trace!(gaussians = n, visible, intersections = n_isects, "map render");
        self.last = Some(ForwardState { setup, grid, n_gaussians: n, n_isects, depth_mode: config.depth_mode });
        Ok(RenderStats { visible, intersections: n_isects })
    }

    /// Differentiates the last [`Self::forward`] (same `gaussians`, `medium` and `out`) for the
    /// upstream gradients: **adds** the parameter gradients and densification statistics into
    /// `grads` (whose length must equal the map's) and **overwrites** `medium_grads` with the
    /// gradient with respect to every pixel's medium parameters.
    pub fn backward(
        &mut self,
        gaussians: &Gaussians,
        medium: &MediumPlanes,
        out: &RenderOutput,
        upstream: &RenderUpstream,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
    ) -> Result<(), RenderError> {
        let last = self.last.ok_or(RenderError::NoForward { why: "no successful forward pass in this workspace" })?;
        let grid = last.grid;
        check_backward_inputs(last.n_gaussians, &grid, gaussians, medium, out, upstream, grads, medium_grads)?;

        let n = last.n_gaussians;
        {
            let _span = tracing::debug_span!("map.raster_bwd", intersections = last.n_isects).entered();
            let inp = raster_inputs(&self.splats[..n], &self.sorted_gaussian, &self.tile_offsets, &last.setup, &grid, last.depth_mode);
            rasterize_backward(&inp, medium, out, upstream, &mut self.partials, medium_grads);
            reduce_isect_grads(&self.isect_offsets[..n + 1], &self.slot_to_sorted, &self.partials, &mut self.splat_grads);
        }
        {
            let _span = tracing::debug_span!("map.project_bwd", gaussians = n).entered();
            project_backward(gaussians, &last.setup, &self.splat_grads[..n], grads);
        }
        Ok(())
    }
}

fn raster_inputs<'a>(
    splats: &'a [ProjectedSplat<f32>],
    sorted_gaussian: &'a [u32],
    tile_offsets: &'a [u32],
    setup: &ProjectionSetup<f32>,
    grid: &TileGrid,
    depth_mode: DepthMode,
) -> RasterInputs<'a> {
    RasterInputs {
        splats,
        sorted_gaussian,
        tile_offsets: &tile_offsets[..grid.num_tiles() + 1],
        grid: *grid,
        intrinsics: [setup.fx, setup.fy, setup.cx, setup.cy],
        depth_mode,
    }
}

/// The checks of a backward pass, shared by the CPU workspace and the Vulkan renderer (same
/// errors): the map as the forward pass saw it (`n_forward` Gaussians), gradient buffers of its
/// length, every image and medium plane of the forward's size, finite upstream gradients.
#[allow(clippy::too_many_arguments)]
pub(crate) fn check_backward_inputs(
    n_forward: usize,
    grid: &TileGrid,
    gaussians: &Gaussians,
    medium: &MediumPlanes,
    out: &RenderOutput,
    upstream: &RenderUpstream,
    grads: &GaussianGrads,
    medium_grads: &MediumPlanes,
) -> Result<(), RenderError> {
    if gaussians.len() != n_forward {
        return Err(RenderError::NoForward { why: "the map changed size since the forward pass" });
    }
    if grads.len() != gaussians.len() {
        return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: gaussians.len() });
    }
    check_output(out, grid)?;
    check_size("upstream gradients", upstream.width(), upstream.height(), grid)?;
    for p in [&upstream.depth, &upstream.depth_var, &upstream.alpha] {
        check_size("upstream gradients", p.width, p.height, grid)?;
    }
    check_size("upstream gradients", upstream.restored.width, upstream.restored.height, grid)?;
    for (_, plane) in medium.planes().into_iter().chain(medium_grads.planes()) {
        check_size("medium planes", plane.width, plane.height, grid)?;
    }
    check_rgb("dL/dcolour", &upstream.colour, false)?;
    check_rgb("dL/drestored", &upstream.restored, false)?;
    check_rgb("dL/ddepth", &upstream.depth, false)?;
    check_rgb("dL/ddepth_var", &upstream.depth_var, false)?;
    check_rgb("dL/dalpha", &upstream.alpha, false)
}

pub(crate) fn check_size(what: &'static str, width: usize, height: usize, grid: &TileGrid) -> Result<(), RenderError> {
    if width != grid.width || height != grid.height {
        return Err(RenderError::SizeMismatch { what, width, height, expected_width: grid.width, expected_height: grid.height });
    }
    Ok(())
}

pub(crate) fn check_output(out: &RenderOutput, grid: &TileGrid) -> Result<(), RenderError> {
    check_size("render output", out.colour.width, out.colour.height, grid)?;
    check_size("render output", out.restored.width, out.restored.height, grid)?;
    for p in [&out.depth, &out.depth_var, &out.alpha, &out.final_t] {
        check_size("render output", p.width, p.height, grid)?;
    }
    if out.isect_end.len() != grid.width * grid.height || out.colour.data.len() != grid.width * grid.height * 3 {
        return Err(RenderError::SizeMismatch {
            what: "render output buffers",
            width: out.isect_end.len(),
            height: 1,
            expected_width: grid.width * grid.height,
            expected_height: 1,
        });
    }
    Ok(())
}

/// First non-finite (or, with `non_negative`, negative) value of an image, as an error naming
/// the pixel and channel.
pub(crate) fn check_rgb<const C: usize>(what: &'static str, img: &Image<f32, C>, non_negative: bool) -> Result<(), RenderError> {
    let bad = |v: f32| !v.is_finite() || (non_negative && v < 0.0);
    // Blocks first (vectorised, no early exit inside one); the index only when one is bad.
    // Rayon's per-element search for the first bad value took 4.9 ms per 640x480 RGB plane on
    // 2 threads, the blocks 0.13 ms (a forward+backward checks the equivalent of six).
    let any_bad = img.data.par_chunks(1 << 16).any(|c| c.iter().fold(false, |b, &v| b | bad(v)));
    if !any_bad {
        return Ok(());
    }
    if let Some(i) = img.data.par_iter().position_first(|&v| bad(v)) {
        let value = img.data[i];
        let pixel = i / C;
        let why = if value.is_finite() { "is negative" } else { "is not finite" };
        return Err(RenderError::BadPixel { what, x: pixel % img.width, y: pixel / img.width, channel: i % C, value, why });
    }
    Ok(())
}

pub(crate) fn validate_gaussians(gaussians: &Gaussians) -> Result<(), RenderError> {
    if let Some((index, group)) = gaussians.find_non_finite() {
        return Err(RenderError::NonFiniteGaussian { index, field: group.name() });
    }
    let rotation = gaussians.group(crate::gaussians::ParamGroup::Rotation);
    // Blocks first (vectorised, no early exit inside one); the index only when one is zero.
    let any_zero = rotation.par_chunks(4 << 14).any(|c| c.chunks_exact(4).fold(false, |z, q| z | (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] == 0.0)));
    let zero = match any_zero {
        true => rotation.par_chunks(4).position_first(|q| q.iter().map(|v| v * v).sum::<f32>() == 0.0),
        false => None,
    };
    if let Some(index) = zero {
        return Err(RenderError::ZeroRotation { index });
    }
    Ok(())
}
