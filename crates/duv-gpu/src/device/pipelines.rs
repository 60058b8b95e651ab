//! Compute pipelines from the caller's kernel table, through the on-disk pipeline cache.

use super::*;

impl GpuContext {
    pub(super) fn build_pipeline(&self, info: &'static KernelInfo) -> Result<Pipeline, GpuError> {
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
}
