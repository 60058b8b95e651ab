//! Submission: up to two submissions in flight on the one queue, fences, waiting.

use super::*;

impl GpuContext {
    /// Leaves the time from the last wait to the next submission out of
    /// [`HostStats::idle_ns`] (a caller that did other work in between: a benchmark's blocks).
    pub fn forget_idle(&self) {
        self.idle_since.set(None);
    }

    /// Waits poll the fence (`on`) instead of sleeping in the driver (the default): the
    /// thread spins a core for the whole wait, but sees the fence without the driver's wake-up
    /// latency. Returns the previous setting.
    pub fn set_spin_wait(&mut self, on: bool) -> bool {
        std::mem::replace(&mut self.spin_wait, on)
    }

    /// Waits for the submissions [`Self::submit`] left running, if any.
    pub(super) fn wait_in_flight(&self) -> Result<(), GpuError> {
        while self.wait_oldest()? {}
        Ok(())
    }

    /// Waits for the oldest submission left running; `false` when there was none.
    pub(super) fn wait_oldest(&self) -> Result<bool, GpuError> {
        let mut flights = self.in_flight.get();
        let Some(f) = flights[0] else { return Ok(false) };
        let d = &self.device;
        let fence = self.slots[f.slot].1;
        unsafe {
            self.wait_fence(fence).map_err(vk_err("vkWaitForFences (submission left running)"))?;
            d.reset_fences(&[fence]).map_err(vk_err("vkResetFences"))?;
        }
        flights.rotate_left(1);
        flights[SLOTS - 2] = None;
        self.in_flight.set(flights);
        self.prefetch_done.set(f.prefetch_len.max(self.prefetch_done.get()));
        let mut h = self.host.get();
        h.submit_wait_ns += f.since.elapsed().as_nanos() as u64;
        self.host.set(h);
        Ok(true)
    }

    /// Ends the recording: the host-visibility barrier, `vkEndCommandBuffer`, `vkQueueSubmit`
    /// with `self.fence`.
    pub(super) fn end_and_submit(&mut self) -> Result<Instant, GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit" });
        }
        self.recording = false;
        let name = self.last_kernel.and_then(|k| self.kernels.get(k.index())).map_or("(no kernel)", |i| i.name);
        let d = &self.device;
        unsafe {
            // What the kernels wrote, visible to the host (a mapped arena is read in place).
            let to_host = [vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::HOST_READ)];
            let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
            d.cmd_pipeline_barrier(self.command_buffer, stages, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
            d.end_command_buffer(self.command_buffer).map_err(vk_err("vkEndCommandBuffer"))?;
            let cbs = [self.command_buffer];
            let submit = [vk::SubmitInfo::default().command_buffers(&cbs)];
            let t0 = Instant::now();
            if let Some((since, running)) = self.recording_since.take() {
                let mut h = self.host.get();
                let ns = t0.duration_since(since).as_nanos() as u64;
                h.record_ns += ns;
                // Recorded while nothing ran, or the one running finished meanwhile (unknown
                // here: counted as running).
                if !running {
                    h.record_idle_ns += ns;
                }
                self.host.set(h);
            }
            d.queue_submit(self.queue, &submit, self.fence).map_err(|result| GpuError::Kernel { kernel: name, call: "vkQueueSubmit", result })?;
            if let Some(since) = self.idle_since.take() {
                let mut h = self.host.get();
                h.idle_ns += since.elapsed().as_nanos() as u64;
                h.idle_gaps += 1;
                self.host.set(h);
            }
            self.submitted = self.recorded;
            self.prefetch_submitted = (self.prefetched.get_mut().len(), self.prefetch_used);
            self.untimed = true;
            let mut h = self.host.get();
            h.submits += 1;
            self.host.set(h);
            Ok(t0)
        }
    }

    /// Submits what was recorded and returns without waiting: the device runs it while the
    /// host records the next submission, which [`Self::begin`] orders after it. Reads and
    /// writes that are not deferred wait for it ([`Self::read_prefetched`] only for the
    /// submission that made its copy); [`Self::submit_and_wait`] waits for all. Two
    /// submissions run this way at a time: a third waits for the oldest first, so the device
    /// has the next one queued behind the one the host waits for.
    pub fn submit(&mut self) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit" });
        }
        if self.in_flight.get()[SLOTS - 2].is_some() {
            self.wait_oldest()?;
        }
        let since = self.end_and_submit()?;
        let mut flights = self.in_flight.get();
        let flight = Flight { slot: self.current, since, prefetch_len: self.prefetch_submitted.0 };
        *flights.iter_mut().find(|f| f.is_none()).expect("a free place: the oldest was waited for") = Some(flight);
        self.in_flight.set(flights);
        // The next recording takes the slot no running submission holds.
        self.current = (0..SLOTS).find(|s| flights.iter().flatten().all(|f| f.slot != *s)).expect("one slot more than can run");
        (self.command_buffer, self.fence) = self.slots[self.current];
        Ok(())
    }

    /// Submits what was recorded, waits for it (and for a submission [`Self::submit`] left
    /// running) and adds the dispatch times to the profile.
    pub fn submit_and_wait(&mut self) -> Result<(), GpuError> {
        if !self.recording {
            return Err(GpuError::NotRecording { what: "submit_and_wait" });
        }
        let name = self.last_kernel.and_then(|k| self.kernels.get(k.index())).map_or("(no kernel)", |i| i.name);
        let t0 = self.end_and_submit()?;
        let d = &self.device;
        unsafe {
            self.wait_fence(self.fence).map_err(|result| GpuError::Kernel { kernel: name, call: "vkWaitForFences (last kernel recorded)", result })?;
            d.reset_fences(&[self.fence]).map_err(vk_err("vkResetFences"))?;
        }
        let mut h = self.host.get();
        h.submit_wait_ns += t0.elapsed().as_nanos() as u64;
        self.host.set(h);
        self.wait_in_flight()?;
        self.prefetch_done.set(self.prefetched.get_mut().len());
        self.idle_since.set(Some(Instant::now()));
        self.collect_timestamps()?;
        self.release_deferred();
        Ok(())
    }

    /// Waits for every submission left running and adds their dispatch times to the profile
    /// (a chain of submissions, each left running while the next is recorded, reaches an idle
    /// queue only now and then).
    pub fn finish(&mut self) -> Result<(), GpuError> {
        if self.recording {
            return Err(GpuError::NotRecording { what: "finish (a recording is open)" });
        }
        self.wait_in_flight()?;
        self.collect_timestamps()?;
        self.release_deferred();
        Ok(())
    }
}
