//! Submission: up to two submissions in flight on the one queue, fences, waiting.

use super::*;

/// A submission left running ([`GpuContext::submit`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct Flight {
    /// Its command buffer and fence (`Recorder::buffers`, `Submission::fences`).
    pub(super) slot: usize,
    /// When it was submitted (host stats).
    pub(super) since: Instant,
    /// The prefetched copies it and the earlier ones made (`Transfers::prefetched`).
    pub(super) prefetch_len: usize,
}

/// Fences and the submissions in flight: the part of a [`GpuContext`] that knows what the
/// queue still runs, and waits for it.
pub(super) struct Submission {
    /// A fence per slot (the slot's command buffer is `Recorder::buffers`).
    pub(super) fences: [vk::Fence; SLOTS],
    /// Submissions running that nothing waited for yet, oldest first (at most two: the
    /// device has the next one queued while the host waits for the older's results).
    pub(super) in_flight: Cell<[Option<Flight>; SLOTS - 1]>,
    /// Dispatches in submitted command buffers since the queue was last idle at a `begin`, and
    /// the prefetch list's length and bytes then (what a running submission will fill).
    pub(super) submitted: usize,
    pub(super) prefetch_submitted: (usize, u64),
    /// The first this many of `Transfers::prefetched` were made by submissions that finished
    /// ([`GpuContext::read_prefetched`] serves them while a later one runs).
    pub(super) prefetch_done: Cell<usize>,
    /// When a wait left the queue idle ([`HostStats::idle_ns`]).
    pub(super) idle_since: Cell<Option<Instant>>,
    /// Waits poll the fence instead of sleeping in the driver ([`GpuContext::set_spin_wait`]).
    pub(super) spin_wait: bool,
}

impl Submission {
    /// No fences yet (null handles), nothing in flight.
    pub(super) fn new() -> Self {
        Submission {
            fences: [vk::Fence::null(); SLOTS],
            in_flight: Cell::new([None; SLOTS - 1]),
            submitted: 0,
            prefetch_submitted: (0, 0),
            prefetch_done: Cell::new(0),
            idle_since: Cell::new(None),
            spin_wait: false,
        }
    }

    /// No submission left running.
    pub(super) fn idle(&self) -> bool {
        self.in_flight.get()[0].is_none()
    }

    /// Waits for `fence`: in the driver, or polling it ([`GpuContext::set_spin_wait`]).
    ///
    /// # Safety
    /// `device` made `fence`.
    pub(super) unsafe fn wait_fence(&self, device: &ash::Device, fence: vk::Fence) -> Result<(), vk::Result> {
        if self.spin_wait {
            loop {
                match unsafe { device.get_fence_status(fence) } {
                    Ok(true) => return Ok(()),
                    Ok(false) => std::hint::spin_loop(),
                    Err(e) => return Err(e),
                }
            }
        }
        unsafe { device.wait_for_fences(&[fence], true, u64::MAX) }
    }

    /// Waits for the submissions [`GpuContext::submit`] left running, if any.
    pub(super) fn wait_in_flight(&self, device: &ash::Device, host: &Cell<HostStats>) -> Result<(), GpuError> {
        while self.wait_oldest(device, host)? {}
        Ok(())
    }

    /// Waits for the oldest submission left running (its wait counted in `host`); `false`
    /// when there was none.
    pub(super) fn wait_oldest(&self, device: &ash::Device, host: &Cell<HostStats>) -> Result<bool, GpuError> {
        let mut flights = self.in_flight.get();
        let Some(f) = flights[0] else { return Ok(false) };
        let fence = self.fences[f.slot];
        unsafe {
            self.wait_fence(device, fence).map_err(vk_err("vkWaitForFences (submission left running)"))?;
            device.reset_fences(&[fence]).map_err(vk_err("vkResetFences"))?;
        }
        flights.rotate_left(1);
        flights[SLOTS - 2] = None;
        self.in_flight.set(flights);
        self.prefetch_done.set(f.prefetch_len.max(self.prefetch_done.get()));
        let mut h = host.get();
        h.submit_wait_ns += f.since.elapsed().as_nanos() as u64;
        host.set(h);
        Ok(true)
    }

    /// Destroys the fences.
    ///
    /// # Safety
    /// `device` made them and no submission uses them.
    pub(super) unsafe fn destroy(&mut self, device: &ash::Device) {
        for fence in &mut self.fences {
            if *fence != vk::Fence::null() {
                unsafe { device.destroy_fence(*fence, None) };
            }
            *fence = vk::Fence::null();
        }
    }
}

impl GpuContext {
    /// Leaves the time from the last wait to the next submission out of
    /// [`HostStats::idle_ns`] (a caller that did other work in between: a benchmark's blocks).
    pub fn forget_idle(&self) {
        self.submission.idle_since.set(None);
    }

    /// Waits poll the fence (`on`) instead of sleeping in the driver (the default): the
    /// thread spins a core for the whole wait, but sees the fence without the driver's wake-up
    /// latency. Returns the previous setting.
    pub fn set_spin_wait(&mut self, on: bool) -> bool {
        std::mem::replace(&mut self.submission.spin_wait, on)
    }

    /// Ends the recording: the host-visibility barrier, `vkEndCommandBuffer`, `vkQueueSubmit`
    /// with the recorded slot's fence.
    pub(super) fn end_and_submit(&mut self) -> Result<Instant, GpuError> {
        let GpuContext { selected, pipelines, transfers, recorder, submission, profiler, .. } = self;
        recorder.check_recording("submit")?;
        recorder.recording = false;
        let name = pipelines.name_of(recorder.last_kernel);
        let d = &selected.device;
        let cb = recorder.command_buffer();
        let host = &profiler.host;
        unsafe {
            // What the kernels wrote, visible to the host (a mapped arena is read in place).
            let to_host = [vk::MemoryBarrier::default()
                .src_access_mask(vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE)
                .dst_access_mask(vk::AccessFlags::HOST_READ)];
            let stages = vk::PipelineStageFlags::COMPUTE_SHADER | vk::PipelineStageFlags::TRANSFER;
            d.cmd_pipeline_barrier(cb, stages, vk::PipelineStageFlags::HOST, vk::DependencyFlags::empty(), &to_host, &[], &[]);
            d.end_command_buffer(cb).map_err(vk_err("vkEndCommandBuffer"))?;
            let cbs = [cb];
            let submit = [vk::SubmitInfo::default().command_buffers(&cbs)];
            let t0 = Instant::now();
            if let Some((since, running)) = recorder.since.take() {
                let mut h = host.get();
                let ns = t0.duration_since(since).as_nanos() as u64;
                h.record_ns += ns;
                // Recorded while nothing ran, or the one running finished meanwhile (unknown
                // here: counted as running).
                if !running {
                    h.record_idle_ns += ns;
                }
                host.set(h);
            }
            d.queue_submit(selected.queue, &submit, submission.fences[recorder.current])
                .map_err(|result| GpuError::Kernel { kernel: name, call: "vkQueueSubmit", result })?;
            if let Some(since) = submission.idle_since.take() {
                let mut h = host.get();
                h.idle_ns += since.elapsed().as_nanos() as u64;
                h.idle_gaps += 1;
                host.set(h);
            }
            submission.submitted = recorder.recorded;
            submission.prefetch_submitted = (transfers.prefetched.get_mut().len(), transfers.prefetch_used);
            profiler.untimed = true;
            let mut h = host.get();
            h.submits += 1;
            host.set(h);
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
        self.recorder.check_recording("submit")?;
        if self.submission.in_flight.get()[SLOTS - 2].is_some() {
            self.submission.wait_oldest(&self.selected.device, &self.profiler.host)?;
        }
        let since = self.end_and_submit()?;
        let (recorder, submission) = (&mut self.recorder, &mut self.submission);
        let mut flights = submission.in_flight.get();
        let flight = Flight { slot: recorder.current, since, prefetch_len: submission.prefetch_submitted.0 };
        *flights.iter_mut().find(|f| f.is_none()).expect("a free place: the oldest was waited for") = Some(flight);
        submission.in_flight.set(flights);
        // The next recording takes the slot no running submission holds.
        recorder.current = (0..SLOTS).find(|s| flights.iter().flatten().all(|f| f.slot != *s)).expect("one slot more than can run");
        Ok(())
    }

    /// Submits what was recorded, waits for it (and for a submission [`Self::submit`] left
    /// running) and adds the dispatch times to the profile.
    pub fn submit_and_wait(&mut self) -> Result<(), GpuError> {
        self.recorder.check_recording("submit_and_wait")?;
        let name = self.pipelines.name_of(self.recorder.last_kernel);
        let t0 = self.end_and_submit()?;
        let GpuContext { selected, transfers, recorder, submission, profiler, .. } = self;
        let d = &selected.device;
        let fence = submission.fences[recorder.current];
        unsafe {
            submission
                .wait_fence(d, fence)
                .map_err(|result| GpuError::Kernel { kernel: name, call: "vkWaitForFences (last kernel recorded)", result })?;
            d.reset_fences(&[fence]).map_err(vk_err("vkResetFences"))?;
        }
        let mut h = profiler.host.get();
        h.submit_wait_ns += t0.elapsed().as_nanos() as u64;
        profiler.host.set(h);
        submission.wait_in_flight(d, &profiler.host)?;
        submission.prefetch_done.set(transfers.prefetched.get_mut().len());
        submission.idle_since.set(Some(Instant::now()));
        self.collect_timestamps()?;
        self.transfers.release_deferred(self.submission.idle());
        Ok(())
    }

    /// Waits for every submission left running and adds their dispatch times to the profile
    /// (a chain of submissions, each left running while the next is recorded, reaches an idle
    /// queue only now and then).
    pub fn finish(&mut self) -> Result<(), GpuError> {
        if self.recorder.recording {
            return Err(GpuError::NotRecording { what: "finish (a recording is open)" });
        }
        self.submission.wait_in_flight(&self.selected.device, &self.profiler.host)?;
        self.collect_timestamps()?;
        self.transfers.release_deferred(self.submission.idle());
        Ok(())
    }
}
