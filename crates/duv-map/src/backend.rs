//! Which renderer the mapper runs on: the Vulkan kernels ([`crate::vulkan::GpuRenderer`]) or
//! the CPU reference ([`crate::render::RasterWorkspace`]), chosen once by
//! [`RenderBackend::open`] from a [`MapperDevice`]. Its own module so that the Vulkan twins
//! (`vulkan/`) and the mapper (`mapper.rs`) do not import each other.

use crate::vulkan::*;
use duv_gpu::{GpuContext, GpuError};
use crate::adam::AdamGroup;
use crate::gaussians::{GaussianGrads, Gaussians};
use duv_core::{PinholeCamera, Se3};
use crate::render::{MediumPlanes, RasterCapacity, RenderConfig, RenderError, RenderOutput, RenderStats, RenderUpstream};

/// Which renderer the mapper uses (`duv run --mapper`, `duv refine --mapper`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum MapperDevice {
    /// The Vulkan kernels on a GPU; the CPU reference when the only device is a CPU
    /// implementation such as lavapipe (no faster there than the reference in a whole run) unless
    /// `DUV_VULKAN_DEVICE` names it, or when there is no Vulkan at all (one warning).
    #[default]
    Auto,
    /// The Vulkan kernels on whatever device is chosen, lavapipe included; the CPU reference
    /// only when there is no Vulkan device at all (one warning).
    Vulkan,
    /// The CPU reference (`map::render::RasterWorkspace`).
    Cpu,
}

/// Where the mapper's forward and backward render runs: the Vulkan kernels
/// ([`GpuRenderer`]) or the CPU reference ([`crate::render::RasterWorkspace`]), chosen
/// once by [`RenderBackend::open`]; the same calls, the same checks and errors either way.
pub enum RenderBackend {
    Vulkan { ctx: Box<GpuContext>, renderer: Box<GpuRenderer> },
    Cpu { ws: Box<crate::render::RasterWorkspace>, why: String },
}

impl RenderBackend {
    /// The CPU reference, for `why` (shown by [`Self::describe`]).
    pub fn cpu(capacity: RasterCapacity, why: &str) -> Result<Self, RenderError> {
        Ok(RenderBackend::Cpu { ws: Box::new(crate::render::RasterWorkspace::new(capacity)?), why: why.to_string() })
    }

    /// Opens the renderer `choice` asks for with `options` (arena = the board's GPU budget)
    /// and allocates every buffer for `capacity`. No Vulkan loader or device gives the CPU
    /// reference with one warning; any other device failure (a `DUV_VULKAN_DEVICE` that
    /// matches nothing, the buffers not fitting the GPU budget) is an error.
    pub fn open(choice: MapperDevice, options: &duv_gpu::GpuOptions, capacity: RasterCapacity) -> Result<Self, VulkanRenderError> {
        match choice {
            MapperDevice::Cpu => Ok(Self::cpu(capacity, "--mapper cpu")?),
            MapperDevice::Vulkan => Self::from_open_result(GpuContext::new(options, &KERNELS), capacity),
            MapperDevice::Auto => {
                let picked = options.device.is_some() || std::env::var_os(duv_gpu::DEVICE_ENV).is_some();
                // Asked before the device is opened: a CPU device is not used, so its arena
                // limit (lavapipe's is smaller than some boards' GPU budgets) does not matter.
                if !picked {
                    if let Ok((name, "CPU")) = GpuContext::probe(options) {
                        let why = format!(
                            "the only Vulkan device, {name}, runs on the CPU, where the CPU reference maps as fast in a whole run (--mapper vulkan or {} selects it)",
                            duv_gpu::DEVICE_ENV
                        );
                        tracing::info!("map: {why}");
                        return Ok(Self::cpu(capacity, &why)?);
                    }
                }
                Self::from_open_result(GpuContext::new(options, &KERNELS), capacity)
            }
        }
    }

    /// The fallback policy of [`RenderBackend::open`], for a given outcome of opening the device.
    pub fn from_open_result(opened: Result<GpuContext, GpuError>, capacity: RasterCapacity) -> Result<Self, VulkanRenderError> {
        match opened {
            Ok(mut ctx) => {
                let renderer = GpuRenderer::new(&mut ctx, capacity)?;
                Ok(RenderBackend::Vulkan { ctx: Box::new(ctx), renderer: Box::new(renderer) })
            }
            Err(e) if e.is_unavailable() => {
                let why = format!("{e}; rendering on the CPU reference instead of Vulkan");
                tracing::warn!("map: {why}");
                Ok(Self::cpu(capacity, &why)?)
            }
            Err(e) => Err(e.into()),
        }
    }

    pub fn is_vulkan(&self) -> bool {
        matches!(self, RenderBackend::Vulkan { .. })
    }

    /// Geometries the Vulkan renderer submitted ahead and forwards that used one
    /// ([`GpuRenderer::plan_next_view`]); `None` on the CPU reference.
    pub fn geometry_ahead_counts(&self) -> Option<(u64, u64)> {
        match self {
            RenderBackend::Vulkan { renderer, .. } => Some((renderer.fwd.ahead_submitted, renderer.fwd.ahead_used)),
            RenderBackend::Cpu { .. } => None,
        }
    }

    /// [`GpuRenderer::plan_next_view`] on the Vulkan renderer; nothing on the CPU reference.
    pub fn plan_next_view(&mut self, camera: &PinholeCamera, cam_from_world: &Se3, config: &RenderConfig, n: usize) {
        if let RenderBackend::Vulkan { renderer, .. } = self {
            renderer.plan_next_view(camera, cam_from_world, config, n);
        }
    }

    /// The Vulkan renderer's kernels and device, to switch between kernel variants and
    /// device settings (benchmarks, tests); `None` on the CPU reference.
    pub fn renderer_mut(&mut self) -> Option<(&mut GpuRenderer, &mut GpuContext)> {
        match self {
            RenderBackend::Vulkan { renderer, ctx } => Some((renderer, ctx)),
            RenderBackend::Cpu { .. } => None,
        }
    }

    /// One line for the operator: the device, or the CPU reference and why.
    pub fn describe(&self) -> String {
        match self {
            RenderBackend::Vulkan { ctx, .. } => format!("Vulkan on {}", ctx.info()),
            RenderBackend::Cpu { why, .. } => format!("CPU reference ({why})"),
        }
    }

    /// The open device, when this is the Vulkan renderer (profile, arena figures).
    pub fn gpu(&self) -> Option<&GpuContext> {
        match self {
            RenderBackend::Vulkan { ctx, .. } => Some(ctx),
            RenderBackend::Cpu { .. } => None,
        }
    }

    /// The intersection count of the last render on the Vulkan renderer (after
    /// [`Self::loss_and_backward`] for a [`Self::forward_for_loss`], whose stats do not have
    /// it); `None` on the CPU reference, whose forward stats do.
    pub fn last_intersections(&self) -> Option<usize> {
        match self {
            RenderBackend::Vulkan { renderer, .. } => renderer.last_intersections(),
            RenderBackend::Cpu { .. } => None,
        }
    }

    /// Timestamp queries on the Vulkan renderer's dispatches on or off
    /// ([`GpuContext::set_timestamps`]); `false` when there are none to take (CPU reference,
    /// or a queue without timestamps).
    pub fn set_gpu_timestamps(&mut self, on: bool) -> bool {
        match self {
            RenderBackend::Vulkan { ctx, .. } => ctx.set_timestamps(on),
            RenderBackend::Cpu { .. } => false,
        }
    }

    /// One forward render ([`GpuRenderer::forward`] / `RasterWorkspace::forward`).
    pub fn forward(
        &mut self,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.forward(ctx, gaussians, camera, cam_from_world, medium, config, out),
            RenderBackend::Cpu { ws, .. } => Ok(ws.forward(gaussians, camera, cam_from_world, medium, config, out)?),
        }
    }

    /// Hands the map to the device optimiser ([`GpuRenderer::make_resident`]) unless it is
    /// there already; nothing on the CPU reference.
    pub fn ensure_resident(&mut self, gaussians: &Gaussians, grads: &GaussianGrads, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } if !renderer.is_resident() => renderer.make_resident(ctx, gaussians, grads, adam),
            _ => Ok(()),
        }
    }

    /// Whether the device holds the optimiser's map.
    pub fn is_resident(&self) -> bool {
        matches!(self, RenderBackend::Vulkan { renderer, .. } if renderer.is_resident())
    }

    /// Whether the host's copy of the map is behind the device's ([`GpuRenderer::host_params_stale`]).
    pub fn host_params_stale(&self) -> bool {
        matches!(self, RenderBackend::Vulkan { renderer, .. } if renderer.host_params_stale())
    }

    /// [`GpuRenderer::arm_adam_step`]: the next loss and backward end with the device map's
    /// Adam step; nothing on the CPU reference.
    pub fn arm_adam_step(&mut self, adam: &[AdamGroup]) -> Result<(), VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.arm_adam_step(ctx, adam),
            RenderBackend::Cpu { .. } => Ok(()),
        }
    }

    /// Target slots the device holds ([`loss::GpuLoss::reserve_target_slots`]): up to
    /// `wanted`; 0 on the CPU reference.
    pub fn reserve_target_slots(&mut self, wanted: usize) -> Result<usize, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => Ok(renderer.loss.reserve_target_slots(ctx, wanted)?),
            RenderBackend::Cpu { .. } => Ok(0),
        }
    }

    /// [`GpuRenderer::sync`]: the device's parameters, statistics and moments into
    /// `gaussians`, `grads` and `adam`.
    pub fn sync(&mut self, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.sync(ctx, gaussians, grads, adam),
            RenderBackend::Cpu { .. } => Ok(false),
        }
    }

    /// [`GpuRenderer::release`]: synced, and the host copy is the map again.
    pub fn release(&mut self, gaussians: &mut Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.release(ctx, gaussians, grads, adam),
            RenderBackend::Cpu { .. } => Ok(false),
        }
    }

    /// Forgets the device map without reading it (the host replaced the whole map).
    pub fn drop_resident(&mut self) {
        if let RenderBackend::Vulkan { renderer, .. } = self {
            renderer.drop_resident();
        }
    }

    /// [`GpuRenderer::adam_step`] on the resident map; on a refused step the gradients are
    /// read into `grads` so the caller can name the bad value.
    pub fn adam_step(&mut self, gaussians: &Gaussians, grads: &mut GaussianGrads, adam: &mut [AdamGroup]) -> Result<bool, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => {
                let taken = renderer.adam_step(ctx, gaussians, adam)?;
                if !taken {
                    renderer.read_grads(ctx, grads)?;
                }
                Ok(taken)
            }
            RenderBackend::Cpu { .. } => Err(RenderError::NoForward { why: "the CPU reference has no device map (AdamGroup::step on the host)" }.into()),
        }
    }

    /// The forward of an optimisation step: on Vulkan the images stay on the device for
    /// [`Self::loss_and_backward`] (`out` is not written) and the submission is left running
    /// while the loss and backward are recorded, so the stats are zeros and a tile overflow
    /// is [`Self::loss_and_backward`]'s error; on the CPU reference it is [`Self::forward`].
    pub fn forward_for_loss(
        &mut self,
        gaussians: &Gaussians,
        camera: &PinholeCamera,
        cam_from_world: &Se3,
        medium: &MediumPlanes,
        device_medium: Option<&DeviceMediumStep>,
        config: &RenderConfig,
        out: &mut RenderOutput,
    ) -> Result<RenderStats, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.forward_on_device(ctx, gaussians, camera, cam_from_world, medium, device_medium, config, true),
            RenderBackend::Cpu { ws, .. } => Ok(ws.forward(gaussians, camera, cam_from_world, medium, config, out)?),
        }
    }

    /// Evaluates the medium network on the device from now on ([`GpuRenderer::enable_medium`]);
    /// `false` on the CPU reference (nothing to do).
    pub fn enable_device_medium(&mut self, step: usize, layout: crate::medium::MediumLayout) -> Result<bool, VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.enable_medium(ctx, step, layout).map(|_| true),
            RenderBackend::Cpu { .. } => Ok(false),
        }
    }

    /// Whether the medium network runs on the device ([`Self::enable_device_medium`]).
    pub fn has_device_medium(&self) -> bool {
        matches!(self, RenderBackend::Vulkan { renderer, .. } if renderer.medium.is_some())
    }

    /// The loss of the last [`Self::forward_for_loss`] against `target` and the render's
    /// backward: on Vulkan [`GpuRenderer::loss_and_backward`] (loss kernels, no image on the
    /// host); on the CPU `total_loss` on `out`, its gradients copied into `upstream`, then
    /// `RasterWorkspace::backward`. Either way **adds** into `grads`, **overwrites**
    /// `medium_grads` and `d_medium_loss` (the loss's own dL/dmedium, 9 channels) and returns
    /// the loss terms and the PSNR (dB) of the render against the target image. With
    /// `device_medium` (Vulkan with [`Self::enable_device_medium`] only) the medium's prior,
    /// tie and network backward run on the device too and only its parameter gradient comes
    /// back (`medium_grads` and `d_medium_loss` are then not written).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_and_backward(
        &mut self,
        gaussians: &Gaussians,
        medium: &MediumPlanes,
        medium9: &crate::medium::MediumPlanes,
        out: &RenderOutput,
        target: &crate::loss::TargetView,
        target_key: Option<loss::TargetKey>,
        loss_config: &crate::loss::LossConfig,
        loss_ws: &mut crate::loss::LossWorkspace,
        upstream: &mut RenderUpstream,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
        d_medium_loss: &mut crate::medium::MediumPlanes,
        device_medium: Option<&mut DeviceMediumBackward>,
    ) -> Result<(crate::loss::LossTerms, f64), VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.loss_and_backward(ctx, gaussians, target, target_key, loss_config, grads, medium_grads, d_medium_loss, device_medium),
            RenderBackend::Cpu { ws, .. } => {
                let rendered =
                    crate::loss::RenderedView { color: &out.colour, depth: &out.depth, depth_variance: &out.depth_var, alpha: &out.alpha, medium: Some(medium9) };
                let terms = crate::loss::total_loss(loss_ws, loss_config, &rendered, target)?;
                let psnr = crate::loss::psnr_db(&out.colour, target.image);
                let lg = loss_ws.grads();
                upstream.colour.data.copy_from_slice(&lg.d_color.data);
                upstream.depth.data.copy_from_slice(&lg.d_depth.data);
                upstream.depth_var.data.copy_from_slice(&lg.d_depth_variance.data);
                upstream.alpha.data.copy_from_slice(&lg.d_alpha.data);
                ws.backward(gaussians, medium, out, upstream, grads, medium_grads)?;
                d_medium_loss.data.copy_from_slice(&lg.d_medium.data);
                Ok((terms, psnr))
            }
        }
    }

    /// The backward of the last forward ([`GpuRenderer::backward`] /
    /// `RasterWorkspace::backward`): adds into `grads`, overwrites `medium_grads`.
    pub fn backward(
        &mut self,
        gaussians: &Gaussians,
        medium: &MediumPlanes,
        out: &RenderOutput,
        upstream: &RenderUpstream,
        grads: &mut GaussianGrads,
        medium_grads: &mut MediumPlanes,
    ) -> Result<(), VulkanRenderError> {
        match self {
            RenderBackend::Vulkan { ctx, renderer } => renderer.backward(ctx, gaussians, medium, out, upstream, grads, medium_grads),
            RenderBackend::Cpu { ws, .. } => Ok(ws.backward(gaussians, medium, out, upstream, grads, medium_grads)?),
        }
    }
}
