//! Profiling: timestamp queries per dispatch ([`KernelProfile`], the last timeline) and the
//! host-side counters ([`HostStats`]).

use super::*;

/// One timed stretch of the queue: its dispatch count and `(kernel, start, end)` ticks.
type Stretch = (usize, [(KernelId, u64, u64); MAX_DISPATCHES]);

/// Timestamp queries and what they and the host counters summed: the part of a [`GpuContext`]
/// that measures.
pub(super) struct Profiler {
    /// Two timestamps per dispatch of a submission; `None` when the queue has none.
    pub(super) query_pool: Option<vk::QueryPool>,
    /// Timestamp queries wanted ([`GpuContext::set_timestamps`]) and, latched at `begin`,
    /// taken in the open submission.
    pub(super) timestamps_wanted: bool,
    pub(super) timing: bool,
    /// The timestamps of the dispatches submitted so far are not yet in the profile.
    pub(super) untimed: bool,
    timestamps: Box<[u64; 2 * MAX_DISPATCHES]>,
    /// The dispatches of the last two timed stretches ([`GpuContext::last_timeline`]).
    timeline: Box<[Stretch; 2]>,
    profile: KernelProfile,
    /// Host-side counters; a `Cell` because reads take `&self`.
    pub(super) host: Cell<HostStats>,
}

/// Host-side cost of driving the device, summed since start or [`GpuContext::reset_profile`]:
/// what the kernel timestamps do not show (submission latency, transfers, host copies).
#[derive(Clone, Copy, Debug, Default)]
pub struct HostStats {
    /// Kernel submissions ([`GpuContext::submit_and_wait`], [`GpuContext::submit`]) and the
    /// wall time from submit to the fence (GPU time included), summed per submission: one left
    /// running overlaps the next, so the sum can exceed the wall time.
    pub submits: u64,
    pub submit_wait_ns: u64,
    /// Host reads and writes of the arena (a staged one is one submission per chunk), bytes
    /// and wall time.
    pub reads: u64,
    pub read_bytes: u64,
    pub read_ns: u64,
    pub writes: u64,
    pub write_bytes: u64,
    pub write_ns: u64,
    /// Of `reads`, those served from a copy the last submission made
    /// ([`GpuContext::prefetch`]; no submission of their own).
    pub prefetched_reads: u64,
    /// Pipeline barriers recorded inside submissions: one only where a command touches what
    /// another since the last barrier wrote (or writes what one read), see [`Hazards`].
    pub barriers: u64,
    /// Host time recording submissions (from [`GpuContext::begin`] to the submit), and of it
    /// the time recorded with no submission running (the device waits for the host then).
    pub record_ns: u64,
    pub record_idle_ns: u64,
    /// Host time from a wait that left the queue idle ([`GpuContext::submit_and_wait`]) to the
    /// next kernel submission: all the device waits for the host between submissions (the
    /// host's own work, recording, transfers), `record_idle_ns` included.
    pub idle_ns: u64,
    /// The stretches in `idle_ns`.
    pub idle_gaps: u64,
}

impl HostStats {
    /// The counts since `earlier` (an earlier [`GpuContext::host_stats`]).
    pub fn since(&self, earlier: &HostStats) -> HostStats {
        HostStats {
            submits: self.submits - earlier.submits,
            submit_wait_ns: self.submit_wait_ns - earlier.submit_wait_ns,
            reads: self.reads - earlier.reads,
            read_bytes: self.read_bytes - earlier.read_bytes,
            read_ns: self.read_ns - earlier.read_ns,
            writes: self.writes - earlier.writes,
            write_bytes: self.write_bytes - earlier.write_bytes,
            write_ns: self.write_ns - earlier.write_ns,
            prefetched_reads: self.prefetched_reads - earlier.prefetched_reads,
            barriers: self.barriers - earlier.barriers,
            record_ns: self.record_ns - earlier.record_ns,
            record_idle_ns: self.record_idle_ns - earlier.record_idle_ns,
            idle_ns: self.idle_ns - earlier.idle_ns,
            idle_gaps: self.idle_gaps - earlier.idle_gaps,
        }
    }
    /// One line per `per` steps: submissions, reads, writes, their bytes and milliseconds.
    pub fn describe_per(&self, per: u64) -> String {
        let p = per.max(1) as f64;
        format!(
            "{:.1} submissions ({:.3} ms submit to fence, {:.1} barriers; recorded in {:.3} ms, {:.3} ms of it with none running; {:.1} times an idle queue's fence to the next submission, {:.3} ms each), {:.1} reads ({:.1} prefetched; {:.2} MB, {:.3} ms), {:.1} writes ({:.2} MB, {:.3} ms)",
            self.submits as f64 / p,
            self.submit_wait_ns as f64 * 1e-6 / p,
            self.barriers as f64 / p,
            self.record_ns as f64 * 1e-6 / p,
            self.record_idle_ns as f64 * 1e-6 / p,
            self.idle_gaps as f64 / p,
            self.idle_ns as f64 * 1e-6 / self.idle_gaps.max(1) as f64,
            self.reads as f64 / p,
            self.prefetched_reads as f64 / p,
            self.read_bytes as f64 * 1e-6 / p,
            self.read_ns as f64 * 1e-6 / p,
            self.writes as f64 / p,
            self.write_bytes as f64 * 1e-6 / p,
            self.write_ns as f64 * 1e-6 / p
        )
    }
}

/// Time per kernel from the timestamp queries, summed over submissions.
#[derive(Clone, Debug)]
pub struct KernelProfile {
    /// The kernel table the counts are indexed by.
    pub kernels: &'static [KernelInfo],
    pub dispatches: [u64; MAX_KERNELS],
    pub total_ns: [f64; MAX_KERNELS],
    /// From the first dispatch's start to the last one's end of every timed stretch of the
    /// queue (the submissions between two idle points: a mapper step's two), summed: the
    /// kernels plus the gaps between them (barriers, a submission waiting for the next).
    pub span_ns: f64,
    /// The timed stretches in `span_ns`.
    pub spans: u64,
}

impl Default for KernelProfile {
    fn default() -> Self {
        KernelProfile::new(&[])
    }
}

impl KernelProfile {
    /// An empty profile of the kernels of `kernels`.
    pub fn new(kernels: &'static [KernelInfo]) -> Self {
        KernelProfile { kernels, dispatches: [0; MAX_KERNELS], total_ns: [0.0; MAX_KERNELS], span_ns: 0.0, spans: 0 }
    }

    /// `(kernel, dispatches, total ms)` of every kernel that ran.
    pub fn rows(&self) -> impl Iterator<Item = (&'static KernelInfo, u64, f64)> + '_ {
        self.kernels.iter().enumerate().filter(|(k, _)| self.dispatches[*k] > 0).map(|(k, info)| (info, self.dispatches[k], self.total_ns[k] * 1e-6))
    }
}

impl Profiler {
    /// No query pool yet; an empty profile of the kernels of `kernels`.
    pub(super) fn new(kernels: &'static [KernelInfo]) -> Self {
        Profiler {
            query_pool: None,
            timestamps_wanted: true,
            timing: false,
            untimed: false,
            timestamps: Box::new([0; 2 * MAX_DISPATCHES]),
            timeline: Box::new([(0, [(KernelId::default(), 0, 0); MAX_DISPATCHES]); 2]),
            profile: KernelProfile::new(kernels),
            host: Cell::new(HostStats::default()),
        }
    }

    /// The query pool, when the open submission takes timestamps.
    pub(super) fn timing_pool(&self) -> Option<vk::QueryPool> {
        self.query_pool.filter(|_| self.timing)
    }

    /// At a `begin` on an idle queue: the submissions up to the next idle one take timestamps
    /// when they are wanted and the queue has them.
    pub(super) fn latch_timing(&mut self) {
        self.timing = self.timestamps_wanted && self.query_pool.is_some();
    }

    /// Records into `cb` the reset of the queries from dispatch `first_dispatch` on (those of
    /// submissions still running before it are kept), when timing.
    pub(super) fn reset_queries(&self, device: &ash::Device, cb: vk::CommandBuffer, first_dispatch: usize) {
        if let Some(q) = self.timing_pool() {
            let first = 2 * first_dispatch as u32;
            unsafe { device.cmd_reset_query_pool(cb, q, first, 2 * MAX_DISPATCHES as u32 - first) };
        }
    }

    /// Adds the timestamps of the submissions since the last collection to the profile (the
    /// queue is idle): `kernels[i]` is the kernel of dispatch `i`, `period_ns` the tick.
    pub(super) fn collect(&mut self, device: &ash::Device, period_ns: Option<f32>, kernels: &[KernelId]) -> Result<(), GpuError> {
        if !std::mem::take(&mut self.untimed) {
            return Ok(());
        }
        if let (Some(q), Some(period), true) = (self.query_pool, period_ns, self.timing) {
            let n = kernels.len();
            if n > 0 {
                let ts = &mut self.timestamps[..2 * n];
                unsafe { device.get_query_pool_results(q, 0, ts, vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT) }
                    .map_err(vk_err("vkGetQueryPoolResults"))?;
                for (i, k) in kernels.iter().enumerate() {
                    let k = k.index();
                    let ticks = self.timestamps[2 * i + 1].wrapping_sub(self.timestamps[2 * i]);
                    self.profile.dispatches[k] += 1;
                    self.profile.total_ns[k] += ticks as f64 * period as f64;
                }
                let first = self.timestamps[..2 * n].iter().step_by(2).min().copied().unwrap_or(0);
                let last = self.timestamps[..2 * n].iter().skip(1).step_by(2).max().copied().unwrap_or(0);
                self.profile.span_ns += last.saturating_sub(first) as f64 * period as f64;
                self.profile.spans += 1;
                // The last two stretches for `last_timeline` (a mapper step's two).
                self.timeline.swap(0, 1);
                for (i, &k) in kernels.iter().enumerate() {
                    self.timeline[1].1[i] = (k, self.timestamps[2 * i], self.timestamps[2 * i + 1]);
                }
                self.timeline[1].0 = n;
            }
        }
        Ok(())
    }

    /// Destroys the query pool.
    ///
    /// # Safety
    /// `device` made it and no pending command uses it.
    pub(super) unsafe fn destroy(&mut self, device: &ash::Device) {
        if let Some(q) = self.query_pool.take() {
            unsafe { device.destroy_query_pool(q, None) };
        }
    }
}

impl GpuContext {
    /// Adds the timestamps of the submissions since the last collection to the profile (the
    /// queue is idle).
    pub(super) fn collect_timestamps(&mut self) -> Result<(), GpuError> {
        let GpuContext { selected, recorder, submission, profiler, .. } = self;
        profiler.collect(&selected.device, selected.info.timestamp_period_ns, &recorder.kernels[..submission.submitted])
    }

    /// Timestamp queries around every dispatch from the next [`Self::begin`] on (`on`, the
    /// default) or none (they cost the device a little per dispatch, and the host a read per
    /// submission). Returns whether the device can take them at all.
    pub fn set_timestamps(&mut self, on: bool) -> bool {
        self.profiler.timestamps_wanted = on;
        self.profiler.query_pool.is_some()
    }

    /// Per-kernel times so far.
    pub fn profile(&self) -> &KernelProfile {
        &self.profiler.profile
    }

    /// The dispatches of the last two timed stretches of the queue (see
    /// [`KernelProfile::span_ns`]; a mapper step's two submissions) in recording order:
    /// `(kernel, start ms, end ms)` from the earliest dispatch's start. Empty without
    /// timestamps.
    pub fn last_timeline(&self) -> impl Iterator<Item = (&'static KernelInfo, f64, f64)> + '_ {
        let timeline = &self.profiler.timeline;
        let entries = || timeline.iter().flat_map(|(n, e)| e[..*n].iter());
        let first = entries().map(|e| e.1).min().unwrap_or(0);
        let period = self.selected.info.timestamp_period_ns.unwrap_or(0.0) as f64 * 1e-6;
        let kernels = self.pipelines.kernels;
        entries().map(move |&(k, start, end)| (&kernels[k.index()], start.wrapping_sub(first) as f64 * period, end.wrapping_sub(first) as f64 * period))
    }
    pub fn reset_profile(&mut self) {
        self.profiler.profile = KernelProfile::new(self.pipelines.kernels);
        self.profiler.host.set(HostStats::default());
    }
    /// Host-side counters so far ([`HostStats`]).
    pub fn host_stats(&self) -> HostStats {
        self.profiler.host.get()
    }
}
