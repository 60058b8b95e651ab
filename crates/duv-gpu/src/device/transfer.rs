//! Host transfers: writes and reads of the arena (mapped, or staged through host-cached
//! memory), deferred small writes, and reads of copies prefetched inside a submission.

use super::*;

/// What a staged transfer moves: host bytes to the arena, or arena bytes to the host.
pub(super) enum Staged<'a> {
    Write(&'a [u8]),
    Read(&'a mut [u8]),
}

/// A copy for the host recorded by [`GpuContext::prefetch`].
#[derive(Clone, Copy, Debug)]
pub(super) struct Prefetched {
    /// src_offset: arena, dst_offset: staging.
    pub(super) copy: vk::BufferCopy,
    /// A later command writes the range: the copy is still what [`GpuContext::read_prefetched`]
    /// wants (that moment's values), no longer what [`GpuContext::read`] does (the arena's).
    pub(super) overwritten: bool,
}

impl Prefetched {
    /// Where in the staging buffer arena bytes `start..end` are, if this copy holds them.
    fn holds(&self, start: u64, end: u64) -> Option<u64> {
        let c = &self.copy;
        (c.src_offset <= start && end <= c.src_offset + c.size).then(|| c.dst_offset + (start - c.src_offset))
    }
}

/// The staging buffer of staged host transfers and what waits in it: the part of a
/// [`GpuContext`] the host's reads and writes of a device-local arena go through. Null
/// handles and zero sizes when the arena is mapped (`ArenaMemory::mapped`).
pub(super) struct Transfers {
    /// A host-visible, coherent (cached where the device has it) buffer: `bytes` for chunks
    /// of transfers from its start, then the deferred-write and prefetch tails; mapped at
    /// `mapped`.
    pub(super) memory: vk::DeviceMemory,
    pub(super) buffer: vk::Buffer,
    pub(super) mapped: *mut u8,
    pub(super) bytes: u64,
    /// The tail from `deferred_at`, `deferred_bytes` long, holds small writes not yet copied;
    /// `deferred` lists their copies, recorded at the start of the next submission (see
    /// [`GpuContext::write`]), `deferred_used` the bytes taken.
    pub(super) deferred_at: u64,
    pub(super) deferred_bytes: u64,
    pub(super) deferred: RefCell<Vec<vk::BufferCopy>>,
    pub(super) deferred_used: Cell<u64>,
    /// After the deferred writes, `prefetch_bytes` from `prefetch_at` take the copies
    /// [`GpuContext::prefetch`] records into a submission; `prefetched` lists them
    /// (src_offset: arena, dst_offset: staging) until the next `begin` or write, and
    /// `prefetch_used` counts their bytes. How many of them were submitted and finished is
    /// `Submission`'s.
    pub(super) prefetch_at: u64,
    pub(super) prefetch_bytes: u64,
    pub(super) prefetched: RefCell<Vec<Prefetched>>,
    pub(super) prefetch_used: u64,
}

impl Transfers {
    /// No staging buffer (null handles, no room).
    pub(super) fn new() -> Self {
        Transfers {
            memory: vk::DeviceMemory::null(),
            buffer: vk::Buffer::null(),
            mapped: std::ptr::null_mut(),
            bytes: 0,
            deferred_at: 0,
            deferred_bytes: 0,
            deferred: RefCell::new(Vec::with_capacity(MAX_DEFERRED_WRITES)),
            deferred_used: Cell::new(0),
            prefetch_at: 0,
            prefetch_bytes: 0,
            prefetched: RefCell::new(Vec::with_capacity(MAX_PREFETCHES)),
            prefetch_used: 0,
        }
    }

    /// Divides a staging buffer of `bytes`: the last eighth (at most 2 MiB) half for deferred
    /// small writes, half for prefetched reads; the rest for chunks.
    pub(super) fn lay_out(&mut self, bytes: u64) {
        let tail = (bytes / 8).min(2 << 20) & !7;
        self.deferred_bytes = tail / 2;
        self.prefetch_bytes = tail - self.deferred_bytes;
        self.bytes = bytes - tail;
        self.deferred_at = self.bytes;
        self.prefetch_at = self.deferred_at + self.deferred_bytes;
    }

    /// A command writes `accesses` (`(range, written)`): a copy for the host taken before it
    /// no longer is the arena's where it writes.
    pub(super) fn overwritten_by(&mut self, accesses: &[(GpuRange, bool)]) {
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

    /// Drops the prefetched copies that overlap arena bytes `start..end` (no longer the
    /// arena's, or not the newest), keeping `submission`'s counts of finished and submitted
    /// ones right.
    pub(super) fn forget_prefetched(&mut self, submission: &mut Submission, start: u64, end: u64) {
        let list = self.prefetched.get_mut();
        let (mut done, mut submitted) = (submission.prefetch_done.get(), submission.prefetch_submitted.0);
        let mut flights = submission.in_flight.get();
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
        submission.prefetch_done.set(done);
        submission.prefetch_submitted.0 = submitted;
        submission.in_flight.set(flights);
    }

    /// Records into `cb` the copies of the deferred small writes to `arena` (in the order
    /// written) and forgets them.
    pub(super) fn record_deferred(&self, device: &ash::Device, cb: vk::CommandBuffer, arena: vk::Buffer) {
        let mut pending = self.deferred.borrow_mut();
        if pending.is_empty() {
            return;
        }
        unsafe { device.cmd_copy_buffer(cb, self.buffer, arena, &pending) };
        pending.clear();
        // The copied bytes stay reserved until the copies ran (`release_deferred`).
    }

    /// The staging tail is free again once the queue is idle (`queue_idle`: no submission
    /// left running) and no write waits in it.
    pub(super) fn release_deferred(&self, queue_idle: bool) {
        if queue_idle && self.deferred.borrow().is_empty() {
            self.deferred_used.set(0);
        }
    }

    /// Unmaps and frees the staging buffer.
    ///
    /// # Safety
    /// `device` made it and no pending command uses it.
    pub(super) unsafe fn destroy(&mut self, device: &ash::Device) {
        unsafe {
            if !self.mapped.is_null() {
                device.unmap_memory(self.memory);
            }
            device.destroy_buffer(self.buffer, None);
            device.free_memory(self.memory, None);
        }
        (self.buffer, self.memory, self.mapped) = (vk::Buffer::null(), vk::DeviceMemory::null(), std::ptr::null_mut());
    }
}

impl GpuContext {
    /// Copies `data` into the start of `buf` (host-visible memory; the queue must be idle,
    /// which it is outside `begin()`/`submit_and_wait()`).
    pub fn write<T: Pod>(&mut self, buf: &GpuBuffer<T>, data: &[T]) -> Result<(), GpuError> {
        self.recorder.check_idle("write")?;
        if data.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: data.len(), len: buf.len });
        }
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let t0 = Instant::now();
        // What the last submission copied for the host of this range is no longer the arena's.
        self.transfers.forget_prefetched(&mut self.submission, buf.offset, buf.offset + bytes.len() as u64);
        let deferred = !self.memory.is_mapped() && bytes.len() <= DEFERRED_WRITE_BYTES && (bytes.len() as u64) <= self.transfers.deferred_bytes;
        if !deferred {
            // In place or by a transfer: not while a submission may still read the arena. (A
            // deferred write goes after what a running submission copies from the staging
            // tail, and reaches the arena in the next submission, after it.)
            self.submission.wait_in_flight(&self.selected.device, &self.profiler.host)?;
        }
        if deferred {
            // Into the staging tail; copied at the start of the next submission (or transfer).
            let used = self.transfers.deferred_used.get();
            if used + bytes.len() as u64 > self.transfers.deferred_bytes || self.transfers.deferred.borrow().len() == MAX_DEFERRED_WRITES {
                self.flush_deferred()?;
            }
            let t = &self.transfers;
            let used = t.deferred_used.get();
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), t.mapped.add((t.deferred_at + used) as usize), bytes.len()) };
            t.deferred.borrow_mut().push(vk::BufferCopy { src_offset: t.deferred_at + used, dst_offset: buf.offset, size: bytes.len() as u64 });
            // Each write from a 4-byte boundary.
            t.deferred_used.set((used + bytes.len() as u64).next_multiple_of(4));
        } else if !self.memory.is_mapped() {
            self.staged_transfer(buf.offset, Staged::Write(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.memory.mapped.add(buf.offset as usize), bytes.len()) };
        }
        let host = &self.profiler.host;
        let mut h = host.get();
        h.writes += 1;
        h.write_bytes += bytes.len() as u64;
        h.write_ns += t0.elapsed().as_nanos() as u64;
        host.set(h);
        Ok(())
    }

    /// Copies the first `out.len()` elements of `buf` to `out`.
    pub fn read<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.recorder.check_idle("read")?;
        let host = &self.profiler.host;
        self.submission.wait_in_flight(&self.selected.device, host)?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let t0 = Instant::now();
        let len = bytes.len();
        let (start, end) = (buf.offset, buf.offset + len as u64);
        // The newest copy of the range (a chain of submissions can hold older ones).
        let copied = self.transfers.prefetched.borrow().iter().rev().find_map(|p| p.holds(start, end).filter(|_| !p.overwritten));
        if let Some(at) = copied {
            unsafe { std::ptr::copy_nonoverlapping(self.transfers.mapped.add(at as usize), bytes.as_mut_ptr(), len) };
            let mut h = host.get();
            h.prefetched_reads += 1;
            host.set(h);
        } else if !self.memory.is_mapped() {
            self.staged_transfer(buf.offset, Staged::Read(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(self.memory.mapped.add(buf.offset as usize), bytes.as_mut_ptr(), len) };
        }
        let mut h = host.get();
        h.reads += 1;
        h.read_bytes += len as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        host.set(h);
        Ok(())
    }

    /// The first `out.len()` elements of `buf` as the newest prefetch of them took them
    /// ([`Self::prefetch`]), waiting only for the submissions up to the one that made it, not
    /// for later ones still running (which may write `buf` again: a step's results read while
    /// the next step's work runs); with no such copy, as [`Self::read`].
    pub fn read_prefetched<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.recorder.check_idle("read")?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let (start, end) = (buf.offset, buf.offset + bytes.len() as u64);
        // The newest copy of the range; waited for (only the submissions up to the one that
        // made it) when it is not done yet.
        let newest = self.transfers.prefetched.borrow().iter().enumerate().rev().find_map(|(i, p)| p.holds(start, end).map(|at| (i, at)));
        let Some((index, at)) = newest else {
            return self.read(buf, bytemuck::cast_slice_mut(bytes));
        };
        let host = &self.profiler.host;
        while index >= self.submission.prefetch_done.get() {
            if !self.submission.wait_oldest(&self.selected.device, host)? {
                // Recorded but not submitted: not a copy yet.
                return self.read(buf, bytemuck::cast_slice_mut(bytes));
            }
        }
        let t0 = Instant::now();
        unsafe { std::ptr::copy_nonoverlapping(self.transfers.mapped.add(at as usize), bytes.as_mut_ptr(), bytes.len()) };
        let mut h = host.get();
        h.reads += 1;
        h.prefetched_reads += 1;
        h.read_bytes += bytes.len() as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        host.set(h);
        Ok(())
    }

    /// The deferred small writes to the device now, in a submission of their own.
    pub(super) fn flush_deferred(&self) -> Result<(), GpuError> {
        if self.transfers.deferred.borrow().is_empty() {
            return Ok(());
        }
        self.staged_transfer(0, Staged::Write(&[]))
    }

    /// A staged host transfer at arena offset `offset`, in chunks of the staging buffer: one
    /// submission per chunk on the idle queue, waited for, in the slot being recorded next;
    /// the deferred small writes are copied first, in the first one (an empty transfer submits
    /// only them).
    pub(super) fn staged_transfer(&self, offset: u64, mut transfer: Staged<'_>) -> Result<(), GpuError> {
        let GpuContext { selected, memory, transfers, recorder, submission, profiler, .. } = self;
        let (upload, len) = match &transfer {
            Staged::Write(b) => (true, b.len()),
            Staged::Read(b) => (false, b.len()),
        };
        submission.wait_in_flight(&selected.device, &profiler.host)?;
        let d = &selected.device;
        let cb = recorder.command_buffer();
        let fence = submission.fences[recorder.current];
        let what = if upload { "write (staged)" } else { "read (staged)" };
        let terr = |call: &'static str| move |result| GpuError::Kernel { kernel: what, call, result };
        let chunk = transfers.bytes as usize;
        let mut at = 0;
        let mut first = true;
        while at < len || first {
            let n = chunk.min(len - at);
            if let Staged::Write(b) = &transfer {
                unsafe { std::ptr::copy_nonoverlapping(b.as_ptr().add(at), transfers.mapped, n) };
            }
            let (src, dst, src_off, dst_off) = match upload {
                true => (transfers.buffer, memory.buffer, 0, offset + at as u64),
                false => (memory.buffer, transfers.buffer, offset + at as u64, 0),
            };
            unsafe {
                d.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()).map_err(terr("vkResetCommandBuffer"))?;
                d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                    .map_err(terr("vkBeginCommandBuffer"))?;
                // Earlier kernels' writes before the copy, the copy before later kernels and
                // before the host reads the staging buffer.
                recorder.barrier(d);
                if first {
                    transfers.record_deferred(d, cb, memory.buffer);
                    recorder.barrier(d);
                }
                if n > 0 {
                    d.cmd_copy_buffer(cb, src, dst, &[vk::BufferCopy { src_offset: src_off, dst_offset: dst_off, size: n as u64 }]);
                }
                recorder.barrier(d);
                let to_host = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
                d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
                d.end_command_buffer(cb).map_err(terr("vkEndCommandBuffer"))?;
                let cbs = [cb];
                d.queue_submit(selected.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], fence).map_err(terr("vkQueueSubmit"))?;
                d.wait_for_fences(&[fence], true, u64::MAX).map_err(terr("vkWaitForFences"))?;
                d.reset_fences(&[fence]).map_err(terr("vkResetFences"))?;
            }
            if let Staged::Read(b) = &mut transfer {
                unsafe { std::ptr::copy_nonoverlapping(transfers.mapped, b.as_mut_ptr().add(at), n) };
            }
            at += n;
            first = false;
        }
        transfers.release_deferred(submission.idle());
        Ok(())
    }
}
