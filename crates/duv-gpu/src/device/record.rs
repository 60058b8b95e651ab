//! Recording: `begin`, dispatches (direct, indirect, by binding name), fills and copies, and the
//! barriers the byte-range hazards of the arena ask for ([`Hazards`]).

use super::*;

/// How a dispatch's workgroup count is given.
#[derive(Clone, Copy, Debug)]
pub(super) enum Launch {
    Groups([u32; 3]),
    /// Three u32 in the arena, read by the device.
    Indirect(GpuRange),
}

/// Command buffers and the recording: the part of a [`GpuContext`] that `begin` opens and
/// dispatches, fills and copies write into.
pub(super) struct Recorder {
    pub(super) pool: vk::CommandPool,
    /// A command buffer per slot: `buffers[current]` is recorded next; the other slots belong
    /// to submissions [`GpuContext::submit`] left running (`Submission::in_flight`) or are
    /// free. The slot's fence is `Submission::fences[current]`.
    pub(super) buffers: [vk::CommandBuffer; SLOTS],
    pub(super) current: usize,
    /// Between `begin` and a submit.
    pub(super) recording: bool,
    /// When the open recording began and whether a submission was running then (HostStats).
    pub(super) since: Option<(Instant, bool)>,
    /// Dispatches in the command buffers since the queue was last idle at a `begin` (those of
    /// running submissions included), and their kernels (timestamp query pair `i` times
    /// `kernels[i]`).
    pub(super) recorded: usize,
    pub(super) kernels: [KernelId; MAX_DISPATCHES],
    /// The last kernel recorded (named when a submission fails).
    pub(super) last_kernel: Option<KernelId>,
    /// What the commands since the last barrier of the open submission touched.
    pub(super) hazards: Hazards,
}

/// Arena ranges [`Hazards`] remembers between barriers; one more is a barrier.
pub(super) const MAX_HAZARD_RANGES: usize = 48;

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

impl Recorder {
    /// No command pool or buffers yet (null handles).
    pub(super) fn new() -> Self {
        Recorder {
            pool: vk::CommandPool::null(),
            buffers: [vk::CommandBuffer::null(); SLOTS],
            current: 0,
            recording: false,
            since: None,
            recorded: 0,
            kernels: [KernelId::default(); MAX_DISPATCHES],
            last_kernel: None,
            hazards: Hazards::default(),
        }
    }

    /// The command buffer being recorded next.
    pub(super) fn command_buffer(&self) -> vk::CommandBuffer {
        self.buffers[self.current]
    }

    /// `NotRecording` for `what` unless a recording is open.
    pub(super) fn check_recording(&self, what: &'static str) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what });
        }
        Ok(())
    }

    /// `NotRecording` for `what` while a recording is open (host transfers need the queue).
    pub(super) fn check_idle(&self, what: &'static str) -> Result<(), GpuError> {
        if self.recording {
            return Err(GpuError::NotRecording { what });
        }
        Ok(())
    }

    /// A full compute and transfer barrier into the command buffer being recorded.
    pub(super) fn barrier(&self, device: &ash::Device) {
        barrier(device, self.command_buffer());
    }

    /// Orders a command touching `accesses` (`(range, written)`) after the earlier commands
    /// of the submission where it must ([`Hazards`]; counted in `host`), then remembers its
    /// accesses.
    pub(super) fn order(&mut self, device: &ash::Device, host: &Cell<HostStats>, accesses: &[(GpuRange, bool)]) {
        if self.hazards.needs_barrier(accesses) {
            self.barrier(device);
            self.hazards.clear();
            let mut h = host.get();
            h.barriers += 1;
            host.set(h);
        }
        self.hazards.record(accesses);
    }

    /// Destroys the command pool and with it the command buffers.
    ///
    /// # Safety
    /// `device` made it and no command buffer of it is pending.
    pub(super) unsafe fn destroy(&mut self, device: &ash::Device) {
        unsafe { device.destroy_command_pool(self.pool, None) };
        self.pool = vk::CommandPool::null();
        self.buffers = [vk::CommandBuffer::null(); SLOTS];
    }
}

/// Records into `cb` a barrier that orders every earlier compute shader and transfer write
/// before every later compute, transfer and indirect-argument access.
pub(super) fn barrier(device: &ash::Device, cb: vk::CommandBuffer) {
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
    unsafe { device.cmd_pipeline_barrier(cb, stages, dst, vk::DependencyFlags::empty(), &mb, &[], &[]) };
}

impl GpuContext {
    /// Starts recording a submission.
    pub fn begin(&mut self) -> Result<(), GpuError> {
        let mut running = !self.submission.idle();
        if running && (2 * self.submission.submitted > MAX_DISPATCHES || 4 * self.submission.prefetch_submitted.1 > 3 * self.transfers.prefetch_bytes) {
            // A chain of submissions, each left running while the next was recorded, has used
            // half of the timestamp queries (a recording past them all is an error) or three
            // quarters of the room for copies to the host (past it, reads wait for the
            // device): this one starts on an idle queue, where they start over.
            self.submission.wait_in_flight(&self.selected.device, &self.profiler.host)?;
            running = false;
        }
        self.recorder.since = Some((Instant::now(), running));
        if !running {
            self.collect_timestamps()?;
        }
        let GpuContext { selected, memory, transfers, recorder, submission, profiler, .. } = self;
        let d = &selected.device;
        let cb = recorder.command_buffer();
        unsafe {
            d.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()).map_err(vk_err("vkResetCommandBuffer"))?;
            d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                .map_err(vk_err("vkBeginCommandBuffer"))?;
        }
        if running {
            // After a submission still running: its queries, prefetched copies and deferred
            // copies are kept (what a recording abandoned since added is dropped), and this one
            // starts with a barrier that orders it after that one's commands.
            recorder.recorded = submission.submitted;
            let (len, used) = submission.prefetch_submitted;
            transfers.prefetched.get_mut().truncate(len);
            submission.prefetch_done.set(submission.prefetch_done.get().min(len));
            transfers.prefetch_used = used;
            profiler.reset_queries(d, cb, recorder.recorded);
            recorder.barrier(d);
        } else {
            profiler.latch_timing();
            profiler.reset_queries(d, cb, 0);
            transfers.prefetched.get_mut().clear();
            submission.prefetch_done.set(0);
            transfers.prefetch_used = 0;
            recorder.recorded = 0;
            submission.submitted = 0;
        }
        recorder.hazards.clear();
        if !transfers.deferred.borrow().is_empty() {
            transfers.record_deferred(d, cb, memory.buffer);
            recorder.barrier(d);
        }
        recorder.recording = true;
        recorder.last_kernel = None;
        Ok(())
    }

    /// Orders a command touching `accesses` (`(range, written)`) after the earlier commands
    /// of the submission where it must ([`Hazards`]), then remembers its accesses; a copy for
    /// the host taken before it no longer is the arena's where it writes.
    pub(super) fn order(&mut self, accesses: &[(GpuRange, bool)]) {
        self.recorder.order(&self.selected.device, &self.profiler.host, accesses);
        self.transfers.overwritten_by(accesses);
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

    pub(super) fn record_dispatch(&mut self, kernel: KernelId, buffers: &[GpuRange], immediates: &[u8], launch: Launch) -> Result<(), GpuError> {
        let info = self.pipelines.kernel_info(kernel)?;
        let name = info.name;
        self.recorder.check_recording(name)?;
        if buffers.len() != info.bindings.len() {
            return Err(GpuError::BindingCount { kernel: name, expected: info.bindings.len(), got: buffers.len() });
        }
        if immediates.len() != info.immediate_bytes as usize {
            return Err(GpuError::Immediates { kernel: name, expected: info.immediate_bytes, got: immediates.len() });
        }
        if let Launch::Groups(groups) = launch {
            for (g, max) in groups.iter().zip(self.selected.max_groups) {
                if *g > max {
                    return Err(GpuError::TooManyWorkgroups { kernel: name, groups: *g, max });
                }
            }
        }
        if self.recorder.recorded >= MAX_DISPATCHES {
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
            *slot = vk::DescriptorBufferInfo { buffer: self.memory.buffer, offset: range.offset, range: range.size };
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
        if self.pipelines.list[kernel.index()].pipeline == vk::Pipeline::null() {
            return Err(GpuError::NoFloatAtomics { kernel: name });
        }
        let mut n_access = info.bindings.len();
        if let Launch::Indirect(args) = launch {
            accesses[n_access] = (GpuRange { offset: args.offset, size: 12 }, false);
            n_access += 1;
        }
        self.order(&accesses[..n_access]);
        let GpuContext { selected, pipelines, memory, recorder, profiler, .. } = self;
        let d = &selected.device;
        let p = &pipelines.list[kernel.index()];
        let cb = recorder.command_buffer();
        let slot = recorder.recorded as u32;
        let timing = profiler.timing_pool();
        unsafe {
            if let Some(q) = timing {
                d.cmd_write_timestamp(cb, vk::PipelineStageFlags::TOP_OF_PIPE, q, 2 * slot);
            }
            d.cmd_bind_pipeline(cb, vk::PipelineBindPoint::COMPUTE, p.pipeline);
            selected.push_descriptor.cmd_push_descriptor_set(cb, vk::PipelineBindPoint::COMPUTE, p.layout, 0, &writes[..info.bindings.len()]);
            if !immediates.is_empty() {
                d.cmd_push_constants(cb, p.layout, vk::ShaderStageFlags::COMPUTE, 0, immediates);
            }
            match launch {
                Launch::Groups(g) => d.cmd_dispatch(cb, g[0], g[1], g[2]),
                Launch::Indirect(args) => d.cmd_dispatch_indirect(cb, memory.buffer, args.offset),
            }
            if let Some(q) = timing {
                d.cmd_write_timestamp(cb, vk::PipelineStageFlags::BOTTOM_OF_PIPE, q, 2 * slot + 1);
            }
        }
        recorder.kernels[recorder.recorded] = kernel;
        recorder.recorded += 1;
        recorder.last_kernel = Some(kernel);
        Ok(())
    }

    /// [`Self::dispatch`] with the buffers looked up by the WGSL names of the kernel's
    /// bindings (`lookup(name)`), so the caller writes no binding list by hand; a binding
    /// `lookup` does not know is [`GpuError::UnknownBinding`].
    pub fn dispatch_named(&mut self, kernel: impl Into<KernelId>, lookup: impl Fn(&str) -> Option<GpuRange>, immediates: &[u8], groups: [u32; 3]) -> Result<(), GpuError> {
        let kernel = kernel.into();
        let info = self.pipelines.kernel_info(kernel)?;
        let mut ranges = [GpuRange { offset: 0, size: 0 }; MAX_BINDINGS];
        for (slot, b) in ranges.iter_mut().zip(info.bindings) {
            *slot = lookup(b.name).ok_or(GpuError::UnknownBinding { kernel: info.name, name: b.name })?;
        }
        self.dispatch(kernel, &ranges[..info.bindings.len().min(MAX_BINDINGS)], immediates, groups)
    }

    /// Records filling `range` with the u32 `value` (size a multiple of 4).
    pub fn fill(&mut self, range: GpuRange, value: u32) -> Result<(), GpuError> {
        self.recorder.check_recording("fill")?;
        self.order(&[(range, true)]);
        unsafe { self.selected.device.cmd_fill_buffer(self.recorder.command_buffer(), self.memory.buffer, range.offset, range.size, value) };
        Ok(())
    }

    /// Records a copy of `range` for the host at this point of the submission: after
    /// [`Self::submit_and_wait`] a [`Self::read`] within it takes the copy instead of a
    /// submission of its own (until the next [`Self::begin`] or [`Self::write`]). Staged
    /// transfers only (a mapped arena is read in place); a range that does not fit what is
    /// left of the prefetch space is read the ordinary way.
    pub fn prefetch(&mut self, range: GpuRange) -> Result<(), GpuError> {
        self.recorder.check_recording("prefetch")?;
        let size = range.size.next_multiple_of(4);
        if self.memory.is_mapped() || size == 0 {
            return Ok(());
        }
        let transfers = &mut self.transfers;
        if transfers.prefetch_used + size > transfers.prefetch_bytes || transfers.prefetched.get_mut().len() == MAX_PREFETCHES {
            // No room: a read takes the range from the arena, not from an older copy.
            transfers.forget_prefetched(&mut self.submission, range.offset, range.offset + range.size);
            return Ok(());
        }
        let copy = vk::BufferCopy { src_offset: range.offset, dst_offset: transfers.prefetch_at + transfers.prefetch_used, size: range.size };
        self.order(&[(range, false)]);
        let GpuContext { selected, memory, transfers, recorder, .. } = self;
        let d = &selected.device;
        let cb = recorder.command_buffer();
        unsafe {
            d.cmd_copy_buffer(cb, memory.buffer, transfers.buffer, &[copy]);
            let to_host = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
            d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
        }
        transfers.prefetch_used += size;
        transfers.prefetched.get_mut().push(Prefetched { copy, overwritten: false });
        Ok(())
    }

    /// Records a copy of `src` into `dst` (the smaller of the two sizes).
    pub fn copy(&mut self, src: GpuRange, dst: GpuRange) -> Result<(), GpuError> {
        self.recorder.check_recording("copy")?;
        let size = src.size.min(dst.size);
        let region = [vk::BufferCopy { src_offset: src.offset, dst_offset: dst.offset, size }];
        self.order(&[(GpuRange { offset: src.offset, size }, false), (GpuRange { offset: dst.offset, size }, true)]);
        let buffer = self.memory.buffer;
        unsafe { self.selected.device.cmd_copy_buffer(self.recorder.command_buffer(), buffer, buffer, &region) };
        Ok(())
    }
}
