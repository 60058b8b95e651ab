//! Opening a device: the loader, instance and device choice (discrete, integrated, virtual, then
//! CPU devices; `DUV_VULKAN_DEVICE`), the queue, and at start-up every other part's Vulkan
//! objects: command buffers, fences, queries, the arena and the staging buffer, the pipelines.

use super::*;

/// The opened device: the part of a [`GpuContext`] every other part's Vulkan objects belong
/// to. Created first; its device and instance are destroyed last (the context's `Drop`), the
/// device before the instance.
pub(super) struct Selected {
    /// The process's loader (never unloaded, see `loader`).
    _entry: ash::Entry,
    pub(super) instance: ash::Instance,
    pub(super) device: ash::Device,
    pub(super) push_descriptor: ash::khr::push_descriptor::Device,
    /// The one compute queue.
    pub(super) queue: vk::Queue,
    pub(super) info: DeviceInfo,
    /// `maxComputeWorkGroupCount`.
    pub(super) max_groups: [u32; 3],
    /// Reductions instead of float atomics ([`GpuOptions::deterministic`]).
    pub(super) deterministic: bool,
}

impl Selected {
    fn new(entry: ash::Entry, instance: ash::Instance, device: ash::Device, cand: &Candidate) -> Self {
        let push_descriptor = ash::khr::push_descriptor::Device::new(&instance, &device);
        let queue = unsafe { device.get_device_queue(cand.queue_family, 0) };
        Selected {
            _entry: entry,
            instance,
            device,
            push_descriptor,
            queue,
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
            max_groups: [0; 3],
            deterministic: !cand.float_atomics,
        }
    }

    /// Switches deterministic mode; returns the mode in effect (always on without float
    /// atomics).
    pub(super) fn set_deterministic(&mut self, on: bool) -> bool {
        self.deterministic = on || !self.info.float_atomics;
        self.deterministic
    }

    /// Fills [`DeviceInfo`] and the limits from the device's properties (1.1 subgroup, 1.2
    /// driver) and returns them.
    fn learn(&mut self, cand: &Candidate) -> vk::PhysicalDeviceProperties {
        let mut driver_props = vk::PhysicalDeviceDriverProperties::default();
        let mut subgroup_props = vk::PhysicalDeviceSubgroupProperties::default();
        let mut props2 = vk::PhysicalDeviceProperties2::default().push_next(&mut driver_props).push_next(&mut subgroup_props);
        unsafe { self.instance.get_physical_device_properties2(cand.physical, &mut props2) };
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
        props
    }
}

/// The Vulkan 1.2 instance every context (and [`GpuContext::probe`]) starts from.
fn create_instance(entry: &ash::Entry) -> Result<ash::Instance, GpuError> {
    let app = vk::ApplicationInfo::default()
        .application_name(c"duv")
        .engine_name(c"duv")
        .api_version(vk::API_VERSION_1_2);
    match unsafe { entry.create_instance(&vk::InstanceCreateInfo::default().application_info(&app), None) } {
        Ok(i) => Ok(i),
        Err(vk::Result::ERROR_INCOMPATIBLE_DRIVER) => Err(GpuError::NoDevice { seen: String::new() }),
        Err(result) => Err(GpuError::Vulkan { call: "vkCreateInstance", result }),
    }
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

pub(super) fn type_name(t: vk::PhysicalDeviceType) -> &'static str {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
        vk::PhysicalDeviceType::CPU => "CPU",
        _ => "other",
    }
}

/// A usable device [`GpuContext::pick`] found.
pub(super) struct Candidate {
    index: usize,
    pub(super) physical: vk::PhysicalDevice,
    name: String,
    rank: u32,
    device_type: &'static str,
    pub(super) queue_family: u32,
    pub(super) timestamp_bits: u32,
    /// VK_EXT_shader_atomic_float with `shaderBufferFloat32AtomicAdd`.
    pub(super) float_atomics: bool,
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
        let instance = create_instance(&entry)?;
        // From here on a failure must destroy the instance.
        match Self::open(entry, instance, options, kernels) {
            Ok(ctx) => Ok(ctx),
            Err((instance, e)) => {
                unsafe { instance.destroy_instance(None) };
                Err(e)
            }
        }
    }

    /// The device [`GpuContext::new`] would open with `options`, as (name, type: "discrete
    /// GPU", "integrated GPU", "virtual GPU", "CPU" or "other"), found without creating it or
    /// allocating anything: a caller that would not use a CPU device asks before paying for
    /// (or failing on) the arena.
    pub fn probe(options: &GpuOptions) -> Result<(String, &'static str), GpuError> {
        let entry = loader()?.clone();
        let _lifecycle = lifecycle_lock();
        let instance = create_instance(&entry)?;
        let wanted = options.device.clone().or_else(|| std::env::var(DEVICE_ENV).ok().filter(|s| !s.trim().is_empty()));
        let picked = Self::pick(&instance, wanted.as_deref()).map(|c| (c.name, c.device_type));
        unsafe { instance.destroy_instance(None) };
        picked
    }

    pub(super) fn pick(instance: &ash::Instance, wanted: Option<&str>) -> Result<Candidate, GpuError> {
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
                    device_type: type_name(props.device_type),
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
    pub(super) fn open(entry: ash::Entry, instance: ash::Instance, options: &GpuOptions, kernels: &'static [KernelInfo]) -> Result<Self, (ash::Instance, GpuError)> {
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
                let instance = ctx.selected.instance.clone();
                ctx.destroy_device_objects();
                std::mem::forget(ctx);
                Err((instance, e))
            }
        }
    }

    /// The context with its device and queue, every other Vulkan object a null handle (what
    /// [`Self::init`] creates; `destroy_device_objects` destroys whatever exists by then).
    pub(super) fn skeleton(entry: ash::Entry, instance: ash::Instance, device: ash::Device, cand: &Candidate, arena_bytes: u64, kernels: &'static [KernelInfo]) -> Self {
        GpuContext {
            selected: Selected::new(entry, instance, device, cand),
            pipelines: Pipelines::new(kernels),
            memory: ArenaMemory::new(arena_bytes),
            transfers: Transfers::new(),
            recorder: Recorder::new(),
            submission: Submission::new(),
            profiler: Profiler::new(kernels),
        }
    }

    pub(super) fn init(&mut self, cand: &Candidate, options: &GpuOptions) -> Result<(), GpuError> {
        let props = self.selected.learn(cand);
        let GpuContext { selected, pipelines, memory, transfers, recorder, submission, profiler } = self;
        let (instance, device) = (&selected.instance, &selected.device);
        let limits = props.limits;
        memory.arena = Arena::new(memory.arena.capacity(), limits.min_storage_buffer_offset_alignment.max(256));

        // Command pool, buffers, fences, queries.
        recorder.pool = unsafe {
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
                    .command_pool(recorder.pool)
                    .level(vk::CommandBufferLevel::PRIMARY)
                    .command_buffer_count(SLOTS as u32),
            )
        }
        .map_err(vk_err("vkAllocateCommandBuffers"))?;
        for (buffer, cb) in recorder.buffers.iter_mut().zip(cbs) {
            *buffer = cb;
        }
        for fence in &mut submission.fences {
            *fence = unsafe { device.create_fence(&vk::FenceCreateInfo::default(), None) }.map_err(vk_err("vkCreateFence"))?;
        }
        recorder.current = 0;
        if selected.info.timestamp_period_ns.is_some() {
            profiler.query_pool = Some(
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
        let capacity = memory.arena.capacity();
        if capacity > limits.max_storage_buffer_range as u64 * 16 {
            return Err(GpuError::ArenaTooLarge { requested: capacity, limit: limits.max_storage_buffer_range as u64 * 16 });
        }
        memory.buffer = unsafe {
            device.create_buffer(
                &vk::BufferCreateInfo::default()
                    .size(capacity.max(256))
                    .usage(vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::UNIFORM_BUFFER | vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST | vk::BufferUsageFlags::INDIRECT_BUFFER)
                    .sharing_mode(vk::SharingMode::EXCLUSIVE),
                None,
            )
        }
        .map_err(vk_err("vkCreateBuffer (arena)"))?;
        let req = unsafe { device.get_buffer_memory_requirements(memory.buffer) };
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
        memory.memory = unsafe {
            device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(req.size).memory_type_index(type_index), None)
        }
        .map_err(vk_err("vkAllocateMemory (arena)"))?;
        unsafe { device.bind_buffer_memory(memory.buffer, memory.memory, 0) }.map_err(vk_err("vkBindBufferMemory (arena)"))?;
        if staged {
            let bytes = options.host_staging.unwrap_or(STAGING_BYTES).min(capacity.max(256)).max(256);
            transfers.buffer = unsafe {
                device.create_buffer(
                    &vk::BufferCreateInfo::default()
                        .size(bytes)
                        .usage(vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST)
                        .sharing_mode(vk::SharingMode::EXCLUSIVE),
                    None,
                )
            }
            .map_err(vk_err("vkCreateBuffer (staging)"))?;
            let sreq = unsafe { device.get_buffer_memory_requirements(transfers.buffer) };
            let stype = find(sreq.memory_type_bits, sreq.size, host | F::HOST_CACHED)
                .or_else(|| find(sreq.memory_type_bits, sreq.size, host))
                .ok_or(GpuError::NoMemoryType)?;
            transfers.memory = unsafe {
                device.allocate_memory(&vk::MemoryAllocateInfo::default().allocation_size(sreq.size).memory_type_index(stype), None)
            }
            .map_err(vk_err("vkAllocateMemory (staging)"))?;
            unsafe { device.bind_buffer_memory(transfers.buffer, transfers.memory, 0) }.map_err(vk_err("vkBindBufferMemory (staging)"))?;
            transfers.mapped = unsafe { device.map_memory(transfers.memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }
                .map_err(vk_err("vkMapMemory (staging)"))? as *mut u8;
            transfers.lay_out(bytes);
            selected.info.host_transfers = "staged";
        } else {
            memory.mapped = unsafe { device.map_memory(memory.memory, 0, vk::WHOLE_SIZE, vk::MemoryMapFlags::empty()) }
                .map_err(vk_err("vkMapMemory (arena)"))? as *mut u8;
            selected.info.host_transfers = "mapped";
        }

        // Pipeline cache keyed by vendor, device, driver version and the cache UUID.
        let uuid: String = props.pipeline_cache_uuid.iter().map(|b| format!("{b:02x}")).collect();
        let cache_file = options.pipeline_cache_dir.as_ref().map(|d| {
            d.join(format!("pipelines-{:04x}-{:04x}-{:08x}-{uuid}.bin", props.vendor_id, props.device_id, props.driver_version))
        });
        let initial = cache_file.as_ref().and_then(|f| std::fs::read(f).ok()).unwrap_or_default();
        let cache_info = vk::PipelineCacheCreateInfo::default().initial_data(&initial);
        pipelines.cache = match unsafe { device.create_pipeline_cache(&cache_info, None) } {
            Ok(c) => c,
            // A corrupt or foreign cache file: start empty.
            Err(_) => unsafe { device.create_pipeline_cache(&vk::PipelineCacheCreateInfo::default(), None) }
                .map_err(vk_err("vkCreatePipelineCache"))?,
        };
        selected.info.pipeline_cache_file = cache_file;

        selected.deterministic = options.deterministic || !selected.info.float_atomics;
        for info in pipelines.kernels {
            // A kernel with float atomics has no pipeline on a device without them (a null
            // pipeline; dispatching it is an error).
            let p = if info.float_atomics && !selected.info.float_atomics {
                Pipeline { set_layout: vk::DescriptorSetLayout::null(), layout: vk::PipelineLayout::null(), pipeline: vk::Pipeline::null() }
            } else {
                pipelines.build(device, info)?
            };
            pipelines.list.push(p);
        }
        // A cache that cannot be written costs start-up time only: warn, go on.
        if let Err(e) = self.save_pipeline_cache() {
            tracing::warn!("gpu: {e}");
        }
        tracing::info!(device = %self.selected.info, arena_mb = capacity / (1024 * 1024), "gpu: device open");
        Ok(())
    }
}
