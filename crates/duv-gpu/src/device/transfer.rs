//! Host transfers: writes and reads of the arena (mapped, or staged through host-cached
//! memory), deferred small writes, and reads of copies prefetched inside a submission.

use super::*;

impl GpuContext {
    pub(super) fn check_idle(&self, what: &'static str) -> Result<(), GpuError> {
        if self.recording {
            return Err(GpuError::NotRecording { what });
        }
        Ok(())
    }

    /// Copies `data` into the start of `buf` (host-visible memory; the queue must be idle,
    /// which it is outside `begin()`/`submit_and_wait()`).
    pub fn write<T: Pod>(&mut self, buf: &GpuBuffer<T>, data: &[T]) -> Result<(), GpuError> {
        self.check_idle("write")?;
        if data.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: data.len(), len: buf.len });
        }
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let t0 = Instant::now();
        // What the last submission copied for the host of this range is no longer the arena's.
        self.forget_prefetched(buf.offset, buf.offset + bytes.len() as u64);
        let deferred = self.mapped.is_null() && bytes.len() <= DEFERRED_WRITE_BYTES && (bytes.len() as u64) <= self.deferred_bytes;
        if !deferred {
            // In place or by a transfer: not while a submission may still read the arena. (A
            // deferred write goes after what a running submission copies from the staging
            // tail, and reaches the arena in the next submission, after it.)
            self.wait_in_flight()?;
        }
        if deferred {
            // Into the staging tail; copied at the start of the next submission (or transfer).
            let used = self.deferred_used.get();
            if used + bytes.len() as u64 > self.deferred_bytes || self.deferred.borrow().len() == MAX_DEFERRED_WRITES {
                self.flush_deferred()?;
            }
            let used = self.deferred_used.get();
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.staging_mapped.add((self.deferred_at + used) as usize), bytes.len()) };
            self.deferred.borrow_mut().push(vk::BufferCopy { src_offset: self.deferred_at + used, dst_offset: buf.offset, size: bytes.len() as u64 });
            // Each write from a 4-byte boundary.
            self.deferred_used.set((used + bytes.len() as u64).next_multiple_of(4));
        } else if self.mapped.is_null() {
            self.staged_transfer(buf.offset, Staged::Write(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.mapped.add(buf.offset as usize), bytes.len()) };
        }
        let mut h = self.host.get();
        h.writes += 1;
        h.write_bytes += bytes.len() as u64;
        h.write_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// Copies the first `out.len()` elements of `buf` to `out`.
    pub fn read<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.check_idle("read")?;
        self.wait_in_flight()?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let t0 = Instant::now();
        let len = bytes.len();
        let (start, end) = (buf.offset, buf.offset + len as u64);
        // The newest copy of the range (a chain of submissions can hold older ones).
        let copied = self.prefetched.borrow().iter().rev().find_map(|p| p.holds(start, end).filter(|_| !p.overwritten));
        if let Some(at) = copied {
            unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped.add(at as usize), bytes.as_mut_ptr(), len) };
            let mut h = self.host.get();
            h.prefetched_reads += 1;
            self.host.set(h);
        } else if self.mapped.is_null() {
            self.staged_transfer(buf.offset, Staged::Read(bytes))?;
        } else {
            unsafe { std::ptr::copy_nonoverlapping(self.mapped.add(buf.offset as usize), bytes.as_mut_ptr(), len) };
        }
        let mut h = self.host.get();
        h.reads += 1;
        h.read_bytes += len as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// The first `out.len()` elements of `buf` as the newest prefetch of them took them
    /// ([`Self::prefetch`]), waiting only for the submissions up to the one that made it, not
    /// for later ones still running (which may write `buf` again: a step's results read while
    /// the next step's work runs); with no such copy, as [`Self::read`].
    pub fn read_prefetched<T: Pod>(&self, buf: &GpuBuffer<T>, out: &mut [T]) -> Result<(), GpuError> {
        self.check_idle("read")?;
        if out.len() > buf.len {
            return Err(GpuError::OutOfRange { what: buf.what, requested: out.len(), len: buf.len });
        }
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(out);
        let (start, end) = (buf.offset, buf.offset + bytes.len() as u64);
        // The newest copy of the range; waited for (only the submissions up to the one that
        // made it) when it is not done yet.
        let newest = self.prefetched.borrow().iter().enumerate().rev().find_map(|(i, p)| p.holds(start, end).map(|at| (i, at)));
        let Some((index, at)) = newest else {
            return self.read(buf, bytemuck::cast_slice_mut(bytes));
        };
        while index >= self.prefetch_done.get() {
            if !self.wait_oldest()? {
                // Recorded but not submitted: not a copy yet.
                return self.read(buf, bytemuck::cast_slice_mut(bytes));
            }
        }
        let t0 = Instant::now();
        unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped.add(at as usize), bytes.as_mut_ptr(), bytes.len()) };
        let mut h = self.host.get();
        h.reads += 1;
        h.prefetched_reads += 1;
        h.read_bytes += bytes.len() as u64;
        h.read_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(())
    }

    /// Drops the prefetched copies that overlap arena bytes `start..end` (no longer the
    /// arena's, or not the newest), keeping the counts of finished and submitted ones right.
    pub(super) fn forget_prefetched(&mut self, start: u64, end: u64) {
        let list = self.prefetched.get_mut();
        let (mut done, mut submitted) = (self.prefetch_done.get(), self.prefetch_submitted.0);
        let mut flights = self.in_flight.get();
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
        self.prefetch_done.set(done);
        self.prefetch_submitted.0 = submitted;
        self.in_flight.set(flights);
    }

    /// Records the copies of the deferred small writes (in the order written) and forgets them.
    pub(super) fn record_deferred(&self, cb: vk::CommandBuffer) {
        let mut pending = self.deferred.borrow_mut();
        if pending.is_empty() {
            return;
        }
        unsafe { self.device.cmd_copy_buffer(cb, self.staging_buffer, self.buffer, &pending) };
        pending.clear();
        // The copied bytes stay reserved until the copies ran (`release_deferred`).
    }

    /// The staging tail is free again once the queue is idle and no write waits in it.
    pub(super) fn release_deferred(&self) {
        if self.in_flight.get()[0].is_none() && self.deferred.borrow().is_empty() {
            self.deferred_used.set(0);
        }
    }

    /// Waits for `fence`: in the driver, or polling it ([`Self::set_spin_wait`]).
    pub(super) unsafe fn wait_fence(&self, fence: vk::Fence) -> Result<(), vk::Result> {
        if self.spin_wait {
            loop {
                match unsafe { self.device.get_fence_status(fence) } {
                    Ok(true) => return Ok(()),
                    Ok(false) => std::hint::spin_loop(),
                    Err(e) => return Err(e),
                }
            }
        }
        unsafe { self.device.wait_for_fences(&[fence], true, u64::MAX) }
    }

    /// The deferred small writes to the device now, in a submission of their own.
    pub(super) fn flush_deferred(&self) -> Result<(), GpuError> {
        if self.deferred.borrow().is_empty() {
            return Ok(());
        }
        self.staged_transfer(0, Staged::Write(&[]))
    }

    /// A staged host transfer at arena offset `offset`, in chunks of the staging buffer: one
    /// submission per chunk on the idle queue, waited for; the deferred small writes are
    /// copied first, in the first one (an empty transfer submits only them).
    pub(super) fn staged_transfer(&self, offset: u64, mut transfer: Staged<'_>) -> Result<(), GpuError> {
        let (upload, len) = match &transfer {
            Staged::Write(b) => (true, b.len()),
            Staged::Read(b) => (false, b.len()),
        };
        self.wait_in_flight()?;
        let d = &self.device;
        let cb = self.command_buffer;
        let what = if upload { "write (staged)" } else { "read (staged)" };
        let terr = |call: &'static str| move |result| GpuError::Kernel { kernel: what, call, result };
        let chunk = self.staging_bytes as usize;
        let mut at = 0;
        let mut first = true;
        while at < len || first {
            let n = chunk.min(len - at);
            if let Staged::Write(b) = &transfer {
                unsafe { std::ptr::copy_nonoverlapping(b.as_ptr().add(at), self.staging_mapped, n) };
            }
            let (src, dst, src_off, dst_off) = match upload {
                true => (self.staging_buffer, self.buffer, 0, offset + at as u64),
                false => (self.buffer, self.staging_buffer, offset + at as u64, 0),
            };
            unsafe {
                d.reset_command_buffer(cb, vk::CommandBufferResetFlags::empty()).map_err(terr("vkResetCommandBuffer"))?;
                d.begin_command_buffer(cb, &vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT))
                    .map_err(terr("vkBeginCommandBuffer"))?;
                // Earlier kernels' writes before the copy, the copy before later kernels and
                // before the host reads the staging buffer.
                self.barrier();
                if first {
                    self.record_deferred(cb);
                    self.barrier();
                }
                if n > 0 {
                    d.cmd_copy_buffer(cb, src, dst, &[vk::BufferCopy { src_offset: src_off, dst_offset: dst_off, size: n as u64 }]);
                }
                self.barrier();
                let to_host = [vk::MemoryBarrier::default().src_access_mask(vk::AccessFlags::TRANSFER_WRITE).dst_access_mask(vk::AccessFlags::HOST_READ)];
                d.cmd_pipeline_barrier(cb, vk::PipelineStageFlags::TRANSFER, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
                d.end_command_buffer(cb).map_err(terr("vkEndCommandBuffer"))?;
                let cbs = [cb];
                d.queue_submit(self.queue, &[vk::SubmitInfo::default().command_buffers(&cbs)], self.fence).map_err(terr("vkQueueSubmit"))?;
                d.wait_for_fences(&[self.fence], true, u64::MAX).map_err(terr("vkWaitForFences"))?;
                d.reset_fences(&[self.fence]).map_err(terr("vkResetFences"))?;
            }
            if let Staged::Read(b) = &mut transfer {
                unsafe { std::ptr::copy_nonoverlapping(self.staging_mapped, b.as_mut_ptr().add(at), n) };
            }
            at += n;
            first = false;
        }
        self.release_deferred();
        Ok(())
    }
}
