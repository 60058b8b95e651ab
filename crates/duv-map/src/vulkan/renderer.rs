//! The whole forward ([`GpuForwardRenderer`]) and a whole mapper step ([`GpuRenderer`]):
//! forward, loss, backward, Adam and the medium network, with the map resident on the device.

use super::*;
use duv_gpu::{GpuContext, GpuError};
use crate::adam::{AdamGroup, StepConstants};
use crate::medium::{C_MED, MEDIUM_CHANNELS};
use crate::gaussians::{GaussianGrads, Gaussians, ParamGroup};
use duv_core::{PinholeCamera, Se3};
use crate::render::{
    check_backward_inputs, check_output, check_rgb, check_size, validate_gaussians, DepthMode, MediumPlanes, ProjectionSetup,
    RasterCapacity, RenderConfig, RenderError, RenderOutput, RenderStats, RenderUpstream, TileGrid,
};

/// Why a GPU render failed: bad input or a full buffer (the same [`RenderError`] the CPU
/// reference reports), or the device.
#[derive(Debug, thiserror::Error)]
pub enum VulkanRenderError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Gpu(#[from] GpuError),
    #[error(transparent)]
    Loss(#[from] crate::loss::LossError),
    #[error(transparent)]
    Medium(#[from] medium::GpuMediumError),
}

/// The medium of a mapper step evaluated on the device: the network, the view's pose (the
/// node directions), the single-coefficient tie.
#[derive(Clone, Copy)]
pub struct DeviceMediumStep<'a> {
    pub net: &'a crate::medium::MediumNet,
    pub world_from_cam: &'a Se3,
    pub single_coefficient: bool,
}

/// The medium's backward of a mapper step on the device: the prior and the tie applied to the
/// plane gradients (`medium_prior.medium_upstream`), then the network's backward; its
/// parameter gradient is written into `param_grads` (overwritten).
pub struct DeviceMediumBackward<'a> {
    pub prior: Option<&'a crate::medium_estimate::MediumPrior>,
    pub single_coefficient: bool,
    pub param_grads: &'a mut [f32],
}

/// Where a forward render takes the medium planes from.
#[derive(Clone, Copy)]
pub enum MediumSource<'a> {
    /// Planes computed on the host, uploaded.
    Host(&'a MediumPlanes),
    /// The medium network on the device ([`medium::GpuMedium`], its parameters and view
    /// written), evaluated into the rasteriser's planes before the projection; with
    /// `single_coefficient`, `sigma_bs` is a copy of `sigma_att`.
    Device { medium: &'a medium::GpuMedium, single_coefficient: bool },
}

/// The forward render on the GPU, every buffer allocated once for a [`RasterCapacity`]:
/// projection + tile-count scan (one submission; the total is read back, as the CPU reference
/// checks it before emitting), then binning, sort, ranges and rasterisation (a second one).
pub struct GpuForwardRenderer {
    pub capacity: RasterCapacity,
    pub projection: GpuProjection,
    pub binning: GpuBinning,
    pub raster: GpuRasterForward,
    /// The view whose geometry (projection, binning, sort, tile ranges) of the device map
    /// [`Self::submit_geometry_ahead`] submitted; the next deferred forward of the device map
    /// for the same view skips it. Any other forward, or a change to the device map
    /// ([`GpuRenderer`] clears it), forgets it.
    ahead: Option<AheadView>,
    /// Geometries submitted ahead, and forwards that used one (a benchmark's and a test's
    /// check that the overlap happens).
    pub ahead_submitted: u64,
    pub ahead_used: u64,
}

/// The view a geometry pass was submitted ahead for ([`GpuForwardRenderer::submit_geometry_ahead`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct AheadView {
    camera: PinholeCamera,
    cam_from_world: Se3,
    config: RenderConfig,
    n: usize,
}

impl GpuForwardRenderer {
    pub fn new(ctx: &mut GpuContext, capacity: RasterCapacity) -> Result<Self, GpuError> {
        let grid = TileGrid::new(capacity.width, capacity.height);
        Ok(GpuForwardRenderer {
            capacity,
            projection: GpuProjection::new(ctx, capacity.max_gaussians)?,
            binning: GpuBinning::new(ctx, capacity.max_intersections, grid.num_tiles())?,
            raster: GpuRasterForward::new(ctx, capacity.width * capacity.height)?,
            ahead: None,
            ahead_submitted: 0,
            ahead_used: 0,
        })
    }

    /// Records and submits, left running ([`GpuContext::submit`]), the geometry of the next
    /// forward of the device map (in [`GpuProjection::params`], `n` Gaussians) from
    /// `cam_from_world`: projection, tile counts and their scan, binning, sort and tile
    /// ranges, so that the device runs it while the host finishes a step. The next
    /// [`Self::forward_on_device`] of the device map with `defer` and the same view records
    /// only the medium and the rasterisation after it (the same commands as in one
    /// submission, so the same results). A tile overflow shows with that forward's count.
    pub fn submit_geometry_ahead(&mut self, ctx: &mut GpuContext, n: usize, camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig) -> Result<(), VulkanRenderError> {
        self.ahead = None;
        if camera.width == 0 || camera.height == 0 || camera.width > self.capacity.width || camera.height > self.capacity.height {
            return Err(RenderError::CapacityExceeded { what: "image pixels", requested: camera.width * camera.height, capacity: self.capacity.width * self.capacity.height }.into());
        }
        if n > self.capacity.max_gaussians {
            return Err(RenderError::CapacityExceeded { what: "Gaussians", requested: n, capacity: self.capacity.max_gaussians }.into());
        }
        let setup = ProjectionSetup::<f32>::new(camera, cam_from_world, config)?;
        let grid = TileGrid::new(camera.width, camera.height);
        self.projection.write_setup(ctx, &setup, &grid, n)?;
        ctx.begin()?;
        self.projection.record(ctx, n, self.capacity.max_intersections)?;
        self.binning.record(ctx, &self.projection, &grid, n)?;
        ctx.submit()?;
        self.ahead = Some(AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n });
        self.ahead_submitted += 1;
        Ok(())
    }

    /// Forgets a geometry submitted ahead (the device map or its buffers changed).
    pub fn forget_geometry_ahead(&mut self) {
        self.ahead = None;
    }

    /// Renders `gaussians` seen from `cam_from_world` through `medium` into `out`, as
    /// [`crate::render::RasterWorkspace::forward`] does on the CPU (same validation,
    /// same errors; [`RenderError::TileOverflow`] reports the size needed).
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.forward_impl(ctx, gaussians, camera, cam_from_world, MediumSource::Host(medium), config, Some(out), false, false)
    }

    /// [`Self::forward`] that leaves the rendered images on the device (in [`Self::raster`]),
    /// for the loss kernels; nothing but the intersection count is read back (so
    /// [`RenderStats::visible`] is 0: not counted).
    /// With `params_on_device` the map already in [`GpuProjection::params`] is rendered
    /// (`gaussians`, the host's copy, only gives the count: the device map is the optimiser's).
    /// With `defer` the submission is left running ([`GpuContext::submit`]) and the stats are
    /// zeros: the intersection count, and a tile overflow, are the next submission's to read
    /// ([`GpuRenderer::loss_and_backward`]).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_on_device(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: MediumSource,
        config: &RenderConfig,
        params_on_device: bool,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.forward_impl(ctx, gaussians, camera, cam_from_world, medium, config, None, params_on_device, defer)
    }

    #[allow(clippy::too_many_arguments)]
    fn forward_impl(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: MediumSource,
        config: &RenderConfig,
        mut out: Option<&mut RenderOutput>,
        params_on_device: bool,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        let _span = tracing::debug_span!("map.gpu_forward", gaussians = gaussians.len()).entered();
        if camera.width == 0 || camera.height == 0 {
            return Err(RenderError::EmptyImage { width: camera.width, height: camera.height }.into());
        }
        let setup = ProjectionSetup::<f32>::new(camera, cam_from_world, config)?;
        let grid = TileGrid::new(camera.width, camera.height);
        if camera.width > self.capacity.width || camera.height > self.capacity.height {
            return Err(RenderError::CapacityExceeded {
                what: "image pixels",
                requested: camera.width * camera.height,
                capacity: self.capacity.width * self.capacity.height,
            }
            .into());
        }
        let n = gaussians.len();
        if n > self.capacity.max_gaussians {
            return Err(RenderError::CapacityExceeded { what: "Gaussians", requested: n, capacity: self.capacity.max_gaussians }.into());
        }
        if let MediumSource::Host(medium) = medium {
            check_size("medium planes", medium.width(), medium.height(), &grid)?;
            for (_, plane) in medium.planes() {
                check_size("medium planes", plane.width, plane.height, &grid)?;
            }
        }
        if let Some(out) = out.as_deref() {
            check_output(out, &grid)?;
        }
        // The device's own map was checked when it went there; Adam there refuses a
        // non-finite gradient, so it stays finite (the host copy may be behind it).
        if !params_on_device {
            validate_gaussians(gaussians)?;
        }
        if let MediumSource::Host(medium) = medium {
            for (what, plane) in medium.planes() {
                check_rgb(what, plane, what != "c_med")?;
            }
        }

        // The geometry submitted ahead for this view, if it is the one wanted.
        let view = AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n };
        let ahead = self.ahead.take();
        let geometry_done = params_on_device && defer && out.is_none() && ahead == Some(view);
        self.ahead_used += geometry_done as u64;
        if !params_on_device {
            self.projection.upload(ctx, gaussians)?;
        }
        if !geometry_done {
            self.projection.write_setup(ctx, &setup, &grid, n)?;
        }
        if let MediumSource::Host(medium) = medium {
            self.raster.upload_medium(ctx, medium)?;
        }
        ctx.begin()?;
        if let MediumSource::Device { medium, single_coefficient } = medium {
            match medium.grid() {
                Some(g) if (g.width, g.height) == (camera.width, camera.height) => {}
                _ => return Err(RenderError::NoForward { why: "the device medium's view is not this camera's (GpuMedium::write_view)" }.into()),
            }
            let r = &self.raster;
            medium.record_forward(ctx, &r.c_med, &r.sigma_att, &r.sigma_bs)?;
            if single_coefficient {
                let px = camera.width * camera.height;
                ctx.copy(r.sigma_att.slice_range(0, 3 * px)?, r.sigma_bs.slice_range(0, 3 * px)?)?;
            }
        }
        // One submission: the intersection count stays on the device (the binning's kernels
        // are dispatched from it); the host reads it afterwards. An overflow renders no
        // intersection and is an error here.
        if !geometry_done {
            self.projection.record(ctx, n, self.capacity.max_intersections)?;
            self.binning.record(ctx, &self.projection, &grid, n)?;
        }
        let intrinsics = [camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32];
        self.raster.record(ctx, &self.projection.splats, &self.binning, &grid, intrinsics, config.depth_mode)?;
        self.projection.scan.prefetch_result(ctx)?;
        if defer && out.is_none() {
            ctx.submit()?;
            return Ok(RenderStats { visible: 0, intersections: 0 });
        }
        ctx.submit_and_wait()?;
        let n_isects = if n == 0 {
            0
        } else {
            match self.projection.scan.result(ctx)? {
                Ok(total) => total as usize,
                Err(needed) => return Err(RenderError::TileOverflow { needed, capacity: self.capacity.max_intersections }.into()),
            }
        };
        if let Some(out) = out.as_deref_mut() {
            self.raster.read(ctx, out)?;
        }
        let mut visible = 0;
        // Counted only with the images (an optimisation step's forward would read every
        // Gaussian's offset back for a statistic nothing uses).
        if n > 0 && out.is_some() {
            // Visible Gaussians: those with a non-empty tile range in the offsets.
            let mut offsets = std::mem::take(&mut self.projection.staging_offsets);
            ctx.read(&self.projection.isect_offsets, &mut offsets[..n + 1])?;
            visible = offsets[..n + 1].windows(2).filter(|p| p[1] > p[0]).count();
            self.projection.staging_offsets = offsets;
        }
        Ok(RenderStats { visible, intersections: n_isects })
    }
}

/// What [`GpuRenderer::backward`] needs of the last forward pass.
#[derive(Clone, Copy, Debug)]
struct GpuForwardState {
    grid: TileGrid,
    intrinsics: [f32; 4],
    depth_mode: DepthMode,
    n_gaussians: usize,
    n_isects: usize,
}

/// Forward and backward render on the GPU, every buffer allocated once for a
/// [`RasterCapacity`]: the twin of [`crate::render::RasterWorkspace`]. The backward
/// differentiates the last forward with what that forward left on the device (the map, the
/// medium, the projected splats, the sorted intersections, depth, variance, alpha, final T and
/// isect end), so the caller passes the same map and medium again, as it must to the CPU
/// reference.
pub struct GpuRenderer {
    pub fwd: GpuForwardRenderer,
    pub raster_backward: GpuRasterBackward,
    pub project_backward: GpuProjectBackward,
    /// The loss kernels, for [`Self::loss_and_backward`].
    pub loss: loss::GpuLoss,
    /// Adam over the map, for [`Self::adam_step`].
    pub adam: optimiser::GpuMapAdam,
    /// The medium network on the device ([`Self::enable_medium`]); `None`: planes from the host.
    pub medium: Option<medium::GpuMedium>,
    /// `Some(n)` while the device holds the optimiser's map of `n` Gaussians (parameters,
    /// gradients and densification statistics, Adam moments): see [`Self::make_resident`].
    resident: Option<usize>,
    /// The device map's parameters changed since the host last had them ([`Self::adam_step`]
    /// reads nothing back; [`Self::sync`] does).
    params_stale: bool,
    /// The host's copy of the resident map (parameters, gradients and densification
    /// statistics, Adam moments) equals the device's: nothing ran on it since it was uploaded
    /// or last read back. [`Self::sync`] then reads nothing (a checkpoint syncs once per copy
    /// it makes: the second read the same map again).
    host_synced: bool,
    /// [`Self::arm_adam_step`] was called: the next [`Self::loss_and_backward`] ends with the
    /// Adam step, whose outcome (`Some(taken)`) waits in `fused_adam` for [`Self::adam_step`].
    adam_armed: bool,
    fused_adam: Option<bool>,
    /// The view of the next step ([`Self::plan_next_view`]): the next
    /// [`Self::loss_and_backward`] submits its geometry after the step's Adam.
    next_view: Option<AheadView>,
    last: Option<GpuForwardState>,
    /// The last forward was deferred: its intersection count is read after the loss's
    /// submission.
    count_pending: bool,
    /// Host staging of the loss's dL/dc_med (allocated once).
    staging_c_med: Vec<f32>,
}

impl GpuRenderer {
    /// Intersections of the last forward, if one ran since the geometry last changed.
    pub fn last_intersections(&self) -> Option<usize> {
        self.last.map(|l| l.n_isects)
    }

    /// Whether the rasterisers take two pixels per thread ([`PIXEL_PAIRS_BELOW_SUBGROUP`]).
    pub fn pixel_pairs(&self) -> bool {
        self.fwd.raster.pixel_pairs
    }

    /// Switches [`Self::pixel_pairs`] in the forward and the backward; returns the previous setting.
    pub fn set_pixel_pairs(&mut self, on: bool) -> bool {
        self.raster_backward.pixel_pairs = on;
        std::mem::replace(&mut self.fwd.raster.pixel_pairs, on)
    }

    pub fn new(ctx: &mut GpuContext, capacity: RasterCapacity) -> Result<Self, GpuError> {
        Ok(GpuRenderer {
            fwd: GpuForwardRenderer::new(ctx, capacity)?,
            raster_backward: GpuRasterBackward::new(
                ctx,
                capacity.width * capacity.height,
                capacity.max_intersections,
                capacity.max_gaussians,
            )?,
            project_backward: GpuProjectBackward::new(ctx, capacity.max_gaussians)?,
            loss: loss::GpuLoss::new(ctx, capacity.width, capacity.height)?,
            adam: optimiser::GpuMapAdam::new(ctx, capacity.max_gaussians)?,
            medium: None,
            resident: None,
            params_stale: false,
            host_synced: false,
            adam_armed: false,
            fused_adam: None,
            next_view: None,
            last: None,
            count_pending: false,
            staging_c_med: vec![0.0; 3 * capacity.width * capacity.height],
        })
    }

    /// [`GpuForwardRenderer::forward_on_device`], remembered for [`Self::loss_and_backward`].
    /// With `defer` its submission is left running while the host records the loss and
    /// backward ([`GpuContext::submit`]); the stats are then zeros and the intersection count,
    /// or a [`RenderError::TileOverflow`], comes with [`Self::loss_and_backward`] (whose Adam
    /// step is not taken after an overflow).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_on_device(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        device_medium: Option<&DeviceMediumStep>,
        config: &RenderConfig,
        defer: bool,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.last = None;
        self.count_pending = false;
        // A plan made before a step that failed is not this step's.
        self.next_view = None;
        let on_device = self.check_resident(gaussians.len())?;
        let source = match (device_medium, self.medium.as_mut()) {
            (Some(step), Some(gm)) => {
                gm.upload_params(ctx, step.net)?;
                gm.write_view(ctx, camera, step.world_from_cam)?;
                MediumSource::Device { medium: gm, single_coefficient: step.single_coefficient }
            }
            (Some(_), None) => return Err(RenderError::NoForward { why: "no device medium (GpuRenderer::enable_medium)" }.into()),
            (None, _) => MediumSource::Host(medium),
        };
        let stats = self.fwd.forward_on_device(ctx, gaussians, camera, cam_from_world, source, config, on_device, defer)?;
        self.remember(camera, config, gaussians.len(), stats.intersections);
        self.count_pending = defer;
        Ok(stats)
    }

    /// Allocates the medium network's buffers ([`medium::GpuMedium`]) for this renderer's
    /// largest view, nodes every `step` pixels and networks of `layout`, once; a second call
    /// with the same arguments does nothing, with others it is an error (the arena never
    /// frees).
    pub fn enable_medium(&mut self, ctx: &mut GpuContext, step: usize, layout: crate::medium::MediumLayout) -> Result<(), VulkanRenderError> {
        if let Some(m) = &self.medium {
            if m.step() == step && m.layout() == layout {
                return Ok(());
            }
            return Err(RenderError::NoForward { why: "the device medium was sized for another grid step or network" }.into());
        }
        let cap = self.fwd.capacity;
        self.medium = Some(medium::GpuMedium::new(ctx, cap.width, cap.height, step, layout)?);
        Ok(())
    }

    /// Whether the device holds the map; an error when it holds another size than the host's.
    fn check_resident(&self, n: usize) -> Result<bool, RenderError> {
        match self.resident {
            Some(r) if r != n => Err(RenderError::NoForward { why: "the device map and the host map differ in size (release the device map before changing the host's)" }),
            Some(_) => Ok(true),
            None => Ok(false),
        }
    }

    /// Hands the map to the device optimiser: uploads the parameters, the gradients with the
    /// densification statistics (which then accumulate on the device) and the Adam moments
    /// of `adam` (one group per [`ParamGroup`]). From here until [`Self::release`] the device
    /// copy is the map: [`Self::forward_on_device`] and [`Self::forward`] render it without an
    /// upload, [`Self::loss_and_backward`] zeroes the parameter gradients on the device and
    /// reads none back, and [`Self::adam_step`] updates it and reads nothing back (the host's
    /// parameters are behind until [`Self::sync`]).
    pub fn make_resident(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians, grads: &GaussianGrads, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        let n = gaussians.len();
        if grads.len() != n {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: n }.into());
        }
        validate_gaussians(gaussians)?;
        self.resident = None;
        self.fwd.forget_geometry_ahead();
        self.fwd.projection.upload(ctx, gaussians)?;
        self.project_backward.upload(ctx, grads)?;
        self.adam.upload_moments(ctx, adam, n)?;
        self.resident = Some(n);
        self.params_stale = false;
        self.host_synced = true;
        self.disarm_adam();
        Ok(())
    }

    /// Whether the device holds the optimiser's map ([`Self::make_resident`]).
    pub fn is_resident(&self) -> bool {
        self.resident.is_some()
    }

    /// Whether the host's parameters are behind the resident device map's (steps since the
    /// last [`Self::sync`]).
    pub fn host_params_stale(&self) -> bool {
        self.resident.is_some() && self.params_stale
    }

    /// Reads the device map's parameters into `gaussians` (when they changed since the host
    /// last had them), its gradients, densification statistics and Adam moments into `grads`
    /// and `adam`; the map stays resident. Nothing to do when it is not resident or nothing
    /// ran on it since the last read (the host's copy is the map). Returns whether it read.
    pub fn sync(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        let Some(n) = self.resident else { return Ok(false) };
        if grads.len() != n || gaussians.len() != n {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: n }.into());
        }
        if self.host_synced {
            return Ok(false);
        }
        if self.params_stale {
            self.fwd.projection.read_params(ctx, gaussians)?;
            self.params_stale = false;
        }
        self.project_backward.read(ctx, grads)?;
        self.adam.read_moments(ctx, adam, n)?;
        self.host_synced = true;
        Ok(true)
    }

    /// [`Self::sync`], then the host copy is the map again (before the host changes it:
    /// densification, pruning, new keyframes). Returns whether it read.
    pub fn release(&mut self, ctx: &GpuContext, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        let read = self.sync(ctx, gaussians, grads, adam)?;
        self.resident = None;
        self.fwd.forget_geometry_ahead();
        self.disarm_adam();
        Ok(read)
    }

    /// Forgets the device map without reading it (the host replaced the whole map).
    pub fn drop_resident(&mut self) {
        self.resident = None;
        self.params_stale = false;
        self.fwd.forget_geometry_ahead();
        self.disarm_adam();
    }

    fn disarm_adam(&mut self) {
        self.adam_armed = false;
        self.fused_adam = None;
    }

    /// The view the step after the next [`Self::loss_and_backward`] renders, if known
    /// (`Mapper::iterate` draws its keyframe ahead): that call then submits the view's geometry
    /// after the step's Adam ([`GpuForwardRenderer::submit_geometry_ahead`]; with the Adam step
    /// armed and the device medium only), and the device runs it while the host finishes the
    /// step. The next deferred forward of that view skips it; any other is rendered as always.
    pub fn plan_next_view(&mut self, camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig, n: usize) {
        self.next_view = Some(AheadView { camera: *camera, cam_from_world: *cam_from_world, config: *config, n });
    }

    /// The constants of each group's next step (one group per [`ParamGroup`]).
    fn write_next_step_constants(&self, ctx: &mut GpuContext, adam: &[AdamGroup]) -> Result<(), GpuError> {
        let consts: [StepConstants; 6] = std::array::from_fn(|k| adam[k].next_step_constants());
        self.adam.write_constants(ctx, &consts)
    }

    /// Makes the next [`Self::loss_and_backward`] end with the Adam step of the resident map
    /// (its constants from `adam` written now), in the same submission, so that
    /// [`Self::adam_step`] then only counts it (or reports it refused) instead of submitting
    /// it. A loss that is not finite is still an error after that step was taken (or refused
    /// for a non-finite gradient).
    pub fn arm_adam_step(&mut self, ctx: &mut GpuContext, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        if self.resident.is_none() || adam.len() != ParamGroup::ALL.len() {
            return Err(RenderError::NoForward { why: "the map is not on the device (make_resident)" }.into());
        }
        self.write_next_step_constants(ctx, adam)?;
        self.adam_armed = true;
        self.fused_adam = None;
        Ok(())
    }

    /// One Adam step of every parameter group on the device map with the gradients of the
    /// last [`Self::loss_and_backward`]; each group's step is counted, nothing is read back
    /// (the host's copy of the map, `gaussians`, only sized, is behind until [`Self::sync`]).
    /// Returns `false`, changing nothing, when a gradient is not finite (as `AdamGroup::step`
    /// refuses it).
    pub fn adam_step(&mut self, ctx: &mut GpuContext, gaussians: &Gaussians, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        let Some(n) = self.resident else {
            return Err(RenderError::NoForward { why: "the map is not on the device (make_resident)" }.into());
        };
        if gaussians.len() != n || adam.len() != ParamGroup::ALL.len() {
            return Err(RenderError::NoForward { why: "the device map and the host map differ in size" }.into());
        }
        if let Some(taken) = self.fused_adam.take() {
            // Already run, at the end of the loss's submission (`arm_adam_step`).
            if taken {
                adam.iter_mut().for_each(AdamGroup::count_step);
                self.params_stale = true;
            }
            return Ok(taken);
        }
        // A step of its own changes the map a geometry submitted ahead projected.
        self.fwd.forget_geometry_ahead();
        self.host_synced = false;
        self.write_next_step_constants(ctx, adam)?;
        ctx.begin()?;
        self.adam.record_step(ctx, &self.fwd.projection.params, &self.project_backward.grads, self.fwd.projection.scan.status.range(), n)?;
        ctx.submit_and_wait()?;
        if self.adam.step_refused(ctx)? {
            return Ok(false);
        }
        adam.iter_mut().for_each(AdamGroup::count_step);
        self.params_stale = true;
        Ok(true)
    }

    /// Reads the gradients of the last backward into `grads` (e.g. to name a non-finite one).
    pub fn read_grads(&mut self, ctx: &GpuContext, grads: &mut GaussianGrads) -> Result<(), VulkanRenderError> {
        Ok(self.project_backward.read(ctx, grads)?)
    }

    fn remember(&mut self, camera: &PinholeCamera, config: &RenderConfig, n_gaussians: usize, n_isects: usize) {
        self.last = Some(GpuForwardState {
            grid: TileGrid::new(camera.width, camera.height),
            intrinsics: [camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32],
            depth_mode: config.depth_mode,
            n_gaussians,
            n_isects,
        });
    }

    /// The loss of the last forward against `target` and its backward, on the device with no
    /// image crossing to the host: `loss.wgsl` writes the upstream gradients where
    /// `rasterize_backward` reads them, one submission from the loss to `project_backward`.
    /// **Adds** the parameter gradients and densification statistics into `grads`,
    /// **overwrites** `medium_grads` (the renderer's) and `d_medium_loss` (the loss's own
    /// dL/dmedium, the medium prior on `c_med`). Returns the loss terms and the PSNR (dB).
    /// CPU twin: `total_loss` then `RasterWorkspace::backward` ([`RenderBackend::loss_and_backward`]).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_and_backward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        target: &crate::loss::TargetView,
        target_key: Option<loss::TargetKey>,
        loss_config: &crate::loss::LossConfig,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
        d_medium_loss: &mut crate::medium::MediumPlanes,
        device_medium: Option<&mut DeviceMediumBackward>,
    ) -> Result<(crate::loss::LossTerms, f64), VulkanRenderError> {
        // The resident map's gradients (and, armed, its parameters and moments) change.
        self.host_synced = false;
        let last = self.last.ok_or(RenderError::NoForward { why: "no successful forward pass in this renderer" })?;
        let grid = last.grid;
        if gaussians.len() != last.n_gaussians {
            return Err(RenderError::NoForward { why: "the map changed size since the forward pass" }.into());
        }
        if grads.len() != gaussians.len() {
            return Err(RenderError::GradLenMismatch { grads: grads.len(), gaussians: gaussians.len() }.into());
        }
        for (_, plane) in medium_grads.planes() {
            check_size("medium planes", plane.width, plane.height, &grid)?;
        }
        check_size("loss dL/dmedium", d_medium_loss.width, d_medium_loss.height, &grid)?;
        let _span = tracing::debug_span!("map.gpu_loss_backward", intersections = last.n_isects).entered();
        let (w, h) = (grid.width, grid.height);
        self.loss.upload_target(ctx, target, target_key)?;
        let n = last.n_gaussians;
        let resident = self.check_resident(n)?;
        let fuse_adam = std::mem::take(&mut self.adam_armed) && resident;
        self.fused_adam = None;
        if !resident {
            self.project_backward.upload(ctx, grads)?;
        }
        ctx.begin()?;
        if resident {
            self.project_backward.record_zero_params(ctx, n)?;
        }
        let fwd = &self.fwd;
        let bufs = loss::LossBuffers {
            colour: &fwd.raster.colour,
            scalars: &fwd.raster.scalars,
            c_med: Some(&fwd.raster.c_med),
            up_colour: &self.raster_backward.up_colour,
            up_scalars: &self.raster_backward.up_scalars,
        };
        self.loss.record(ctx, &bufs, w, h, loss_config)?;
        ctx.fill(self.raster_backward.up_restored.range(), 0)?;
        self.raster_backward.record(
            ctx,
            &fwd.projection.splats,
            &fwd.projection.isect_offsets,
            &fwd.binning,
            &fwd.raster,
            &grid,
            last.intrinsics,
            last.depth_mode,
            n,
        )?;
        self.project_backward.record(ctx, &fwd.projection, &self.raster_backward, n)?;
        let device_medium = match (device_medium, self.medium.as_ref()) {
            (Some(step), Some(gm)) => {
                let (r, rb) = (&fwd.raster, &self.raster_backward);
                let planes = medium::MediumPlaneBuffers {
                    c_med: &r.c_med,
                    sigma_att: &r.sigma_att,
                    sigma_bs: &r.sigma_bs,
                    grad_c_med: &rb.grad_c_med,
                    grad_sigma_att: &rb.grad_sigma_att,
                    grad_sigma_bs: &rb.grad_sigma_bs,
                    loss_d_c_med: &self.loss.d_c_med,
                };
                medium::record_medium_upstream(ctx, &planes, w * h, step.prior, step.single_coefficient)?;
                gm.record_zero_grads(ctx)?;
                gm.record_backward(ctx, &rb.grad_c_med, &rb.grad_sigma_att, &rb.grad_sigma_bs)?;
                Some((step, gm))
            }
            (Some(_), None) => return Err(RenderError::NoForward { why: "no device medium (GpuRenderer::enable_medium)" }.into()),
            (None, _) => None,
        };
        if fuse_adam {
            self.adam.record_step(ctx, &fwd.projection.params, &self.project_backward.grads, fwd.projection.scan.status.range(), n)?;
            self.adam.prefetch_refused(ctx)?;
        }
        self.loss.prefetch_terms(ctx)?;
        if let Some((_, gm)) = device_medium.as_ref() {
            gm.prefetch_grads(ctx)?;
        }
        match self.next_view.take() {
            // The next step's geometry runs on the device while the host reads this step's
            // results (copied for it in this submission) and finishes the step.
            Some(v) if fuse_adam && device_medium.is_some() && v.n == n => {
                ctx.submit()?;
                self.fwd.submit_geometry_ahead(ctx, n, &v.camera, &v.cam_from_world, &v.config)?;
            }
            _ => ctx.submit_and_wait()?,
        }
        if std::mem::take(&mut self.count_pending) {
            // The deferred forward's count: after an overflow nothing of this step counts
            // (its render had no intersection, Adam did not step).
            let total = match n {
                0 => 0,
                _ => match self.fwd.projection.scan.result(ctx)? {
                    Ok(total) => total as usize,
                    Err(needed) => {
                        self.last = None;
                        return Err(RenderError::TileOverflow { needed, capacity: self.fwd.capacity.max_intersections }.into());
                    }
                },
            };
            if let Some(l) = self.last.as_mut() {
                l.n_isects = total;
            }
        }
        if fuse_adam {
            self.fused_adam = Some(!self.adam.step_refused(ctx)?);
        }
        let terms = self.loss.read_terms(ctx)?;
        if !resident {
            self.project_backward.read(ctx, grads)?;
        }
        if let Some((step, gm)) = device_medium {
            // The medium's parameter gradient is all that comes back of it.
            gm.read_grads(ctx, step.param_grads)?;
            return Ok((terms, self.loss.last_psnr_db()));
        }
        ctx.read(&self.raster_backward.grad_c_med, &mut medium_grads.c_med.data)?;
        ctx.read(&self.raster_backward.grad_sigma_att, &mut medium_grads.sigma_att.data)?;
        ctx.read(&self.raster_backward.grad_sigma_bs, &mut medium_grads.sigma_bs.data)?;
        // The loss's dL/dmedium has only the c_med channels (the medium prior).
        let staging = &mut self.staging_c_med[..3 * w * h];
        ctx.read(&self.loss.d_c_med, staging)?;
        for (px, d) in d_medium_loss.data.chunks_exact_mut(MEDIUM_CHANNELS).zip(staging.chunks_exact(3)) {
            px.fill(0.0);
            px[C_MED..C_MED + 3].copy_from_slice(d);
        }
        Ok((terms, self.loss.last_psnr_db()))
    }

    /// [`GpuForwardRenderer::forward`], remembered for [`Self::backward`].
    #[allow(clippy::too_many_arguments)]
    pub fn forward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        self.last = None;
        // A resident map is rendered as the device holds it (the host's may be behind).
        let on_device = self.check_resident(gaussians.len())?;
        let stats = self.fwd.forward_impl(ctx, gaussians, camera, cam_from_world, MediumSource::Host(medium), config, Some(out), on_device, false)?;
        self.remember(camera, config, gaussians.len(), stats.intersections);
        Ok(stats)
    }

    /// Differentiates the last [`Self::forward`] for the upstream gradients, as
    /// [`crate::render::RasterWorkspace::backward`] does on the CPU (same checks, same
    /// errors): **adds** the parameter gradients and densification statistics into `grads`
    /// and **overwrites** `medium_grads`. One submission: `rasterize_backward`,
    /// `reduce_isect_grads`, `project_backward`.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &mut self,
        ctx: &mut GpuContext,
        gaussians: &Gaussians,
        medium: &MediumPlanes,
        out: &RenderOutput,
        upstream: &RenderUpstream,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
    ) -> Result<(), VulkanRenderError> {
        self.host_synced = false;
        let last = self.last.ok_or(RenderError::NoForward { why: "no successful forward pass in this renderer" })?;
        if self.fwd.ahead.is_some() {
            return Err(RenderError::NoForward { why: "the next step's geometry, submitted ahead, replaced this forward's (plan_next_view)" }.into());
        }
        let grid = last.grid;
        check_backward_inputs(last.n_gaussians, &grid, gaussians, medium, out, upstream, grads, medium_grads)?;

        let _span = tracing::debug_span!("map.gpu_backward", intersections = last.n_isects).entered();
        let n = last.n_gaussians;
        self.raster_backward.upload_upstream(ctx, upstream)?;
        self.project_backward.upload(ctx, grads)?;
        ctx.begin()?;
        let fwd = &self.fwd;
        self.raster_backward.record(
            ctx,
            &fwd.projection.splats,
            &fwd.projection.isect_offsets,
            &fwd.binning,
            &fwd.raster,
            &grid,
            last.intrinsics,
            last.depth_mode,
            n,
        )?;
        self.project_backward.record(ctx, &fwd.projection, &self.raster_backward, n)?;
        ctx.submit_and_wait()?;
        self.project_backward.read(ctx, grads)?;
        ctx.read(&self.raster_backward.grad_c_med, &mut medium_grads.c_med.data)?;
        ctx.read(&self.raster_backward.grad_sigma_att, &mut medium_grads.sigma_att.data)?;
        ctx.read(&self.raster_backward.grad_sigma_bs, &mut medium_grads.sigma_bs.data)?;
        Ok(())
    }
}
