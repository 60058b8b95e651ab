//! Compute pipelines from the caller's kernel table, through the on-disk pipeline cache.

use std::path::Path;

use super::*;

/// One kernel's pipeline and its layouts (all null for a kernel the device cannot run).
pub(super) struct Pipeline {
    pub(super) set_layout: vk::DescriptorSetLayout,
    pub(super) layout: vk::PipelineLayout,
    pub(super) pipeline: vk::Pipeline,
}

/// The kernel table a context was built with and a pipeline per kernel, built through the
/// pipeline cache (the part of a [`GpuContext`] dispatches look kernels up in).
pub(super) struct Pipelines {
    /// The caller's kernel table ([`GpuContext::new`]); [`KernelId`] indexes it.
    pub(super) kernels: &'static [KernelInfo],
    pub(super) cache: vk::PipelineCache,
    /// `list[k]` is the pipeline of `kernels[k]` once start-up built them all.
    pub(super) list: Vec<Pipeline>,
}

impl Pipelines {
    /// No pipelines yet, room for one per kernel of `kernels`.
    pub(super) fn new(kernels: &'static [KernelInfo]) -> Self {
        Pipelines { kernels, cache: vk::PipelineCache::null(), list: Vec::with_capacity(kernels.len()) }
    }

    /// The table entry of `kernel`.
    pub(super) fn kernel_info(&self, kernel: KernelId) -> Result<&'static KernelInfo, GpuError> {
        self.kernels.get(kernel.index()).ok_or(GpuError::UnknownKernel { index: kernel.index(), table: self.kernels.len() })
    }

    /// The name of `kernel` for an error message, `(no kernel)` when none.
    pub(super) fn name_of(&self, kernel: Option<KernelId>) -> &'static str {
        kernel.and_then(|k| self.kernels.get(k.index())).map_or("(no kernel)", |i| i.name)
    }

    pub(super) fn build(&self, device: &ash::Device, info: &'static KernelInfo) -> Result<Pipeline, GpuError> {
        let name = info.name;
        let kerr = |call: &'static str| move |result| GpuError::Kernel { kernel: name, call, result };
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
        let result = unsafe { device.create_compute_pipelines(self.cache, &create, None) };
        unsafe { device.destroy_shader_module(module, None) };
        let pipeline = result.map_err(|(_, r)| GpuError::Kernel { kernel: name, call: "vkCreateComputePipelines", result: r })?[0];
        Ok(Pipeline { set_layout, layout, pipeline })
    }

    /// Writes the pipeline cache to `file` (unique temp file, then rename); nothing without one.
    pub(super) fn save(&self, device: &ash::Device, file: Option<&Path>) -> Result<(), GpuError> {
        let Some(file) = file else { return Ok(()) };
        let data = unsafe { device.get_pipeline_cache_data(self.cache) }.map_err(vk_err("vkGetPipelineCacheData"))?;
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

    /// Destroys every pipeline, its layouts and the cache.
    ///
    /// # Safety
    /// `device` made them and no pending command uses them.
    pub(super) unsafe fn destroy(&mut self, device: &ash::Device) {
        unsafe {
            for p in self.list.drain(..) {
                device.destroy_pipeline(p.pipeline, None);
                device.destroy_pipeline_layout(p.layout, None);
                device.destroy_descriptor_set_layout(p.set_layout, None);
            }
            device.destroy_pipeline_cache(self.cache, None);
        }
        self.cache = vk::PipelineCache::null();
    }
}

impl GpuContext {
    /// Writes the pipeline cache to disk (unique temp file, then rename).
    pub fn save_pipeline_cache(&self) -> Result<(), GpuError> {
        self.pipelines.save(&self.selected.device, self.selected.info.pipeline_cache_file.as_deref())
    }

    /// The table entry of `kernel`.
    pub fn kernel_info(&self, kernel: impl Into<KernelId>) -> Result<&'static KernelInfo, GpuError> {
        self.pipelines.kernel_info(kernel.into())
    }
}
