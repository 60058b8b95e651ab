//! Where the stage threads run: tracking owns its cores, mapping and logging yield to it (the
//! board's `[threads]`; ARCHITECTURE.md, "Threads and queues").
//!
//! - **Cores.** `tracking_cores` / `mapping_cores` pin a stage's thread and its data-parallel
//!   workers (`sched_setaffinity`); absent, the OS places them. A core the process may not run
//!   on is left out with a warning; none left: the threads run unpinned.
//! - **Priority.** The mapping thread and its workers, and the logging thread, raise their
//!   nice value by the board's `mapping_nice` / `logging_nice` (`setpriority` on the thread;
//!   Linux nice values are per thread, and lowering a priority needs no privileges). Tracking
//!   keeps the process's priority, so wherever the stages share a core the scheduler gives it
//!   to tracking first.
//! - **Workers.** The CPU mapper runs in its own pool of `threads.mapping` workers (the
//!   pipeline builds it in the mapping thread), so it never takes more than that many cores.
//!
//! Placement is applied where the OS allows (Linux); elsewhere, or when a call fails, a warning
//! and the thread runs as it was: never an error. [`PlacementReport::summary`] says what was
//! applied, one line at the end of a run.

use duv_core::config::board::Threads;
use std::sync::Mutex;

/// A stage thread the board places.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StageThread {
    Tracking,
    Mapping,
    Logging,
}

impl StageThread {
    fn name(self) -> &'static str {
        match self {
            StageThread::Tracking => "tracking",
            StageThread::Mapping => "mapping",
            StageThread::Logging => "logging",
        }
    }
}

/// The board's thread placement.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ThreadPlacement {
    pub tracking_cores: Option<Vec<usize>>,
    pub mapping_cores: Option<Vec<usize>>,
    /// Added to the process's nice value for the mapping thread and its workers.
    pub mapping_nice: i32,
    /// Added to the process's nice value for the logging thread.
    pub logging_nice: i32,
    /// Workers of the CPU mapper's pool (0: the pipeline makes no pool of its own).
    pub mapping_workers: usize,
}

/// What placing one thread did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Applied {
    /// The cores the thread is pinned to (`None`: not asked), or why it is not.
    pub cores: Result<Option<Vec<usize>>, String>,
    /// The thread's nice value now, or why it was not changed.
    pub nice: Result<i32, String>,
}

impl ThreadPlacement {
    /// The board's `[threads]`.
    pub fn from_board(t: &Threads) -> Self {
        let cores = |c: &Option<Vec<u32>>| c.as_ref().map(|c| c.iter().map(|c| *c as usize).collect());
        ThreadPlacement {
            tracking_cores: cores(&t.tracking_cores),
            mapping_cores: cores(&t.mapping_cores),
            mapping_nice: t.mapping_nice as i32,
            logging_nice: t.logging_nice as i32,
            mapping_workers: t.mapping as usize,
        }
    }

    fn cores(&self, role: StageThread) -> Option<&[usize]> {
        match role {
            StageThread::Tracking => self.tracking_cores.as_deref(),
            StageThread::Mapping => self.mapping_cores.as_deref(),
            StageThread::Logging => None,
        }
    }

    fn nice(&self, role: StageThread) -> i32 {
        match role {
            StageThread::Tracking => 0,
            StageThread::Mapping => self.mapping_nice,
            StageThread::Logging => self.logging_nice,
        }
    }

    /// Places the calling thread as `role`'s (cores, then nice); what was applied.
    pub fn apply_here(&self, role: StageThread) -> Applied {
        let cores = match self.cores(role) {
            None => Ok(None),
            Some(want) => os::pin_current_thread(want).map(Some),
        };
        let nice = os::raise_nice_of_current_thread(self.nice(role));
        Applied { cores, nice }
    }
}

/// The first placement of each stage thread in a run, for the end-of-run line.
#[derive(Debug, Default)]
pub struct PlacementReport {
    applied: Mutex<[Option<Applied>; 3]>,
    /// Workers of the mapping pool made (0: none, e.g. a run without a map).
    mapping_workers: std::sync::atomic::AtomicUsize,
}

impl PlacementReport {
    /// Places the calling thread as `role`'s and keeps the first outcome per role; a failure
    /// is a warning, once per role.
    pub fn apply_here(&self, placement: &ThreadPlacement, role: StageThread) {
        let a = placement.apply_here(role);
        let mut g = self.applied.lock().unwrap_or_else(|p| p.into_inner());
        let slot = &mut g[role as usize];
        if slot.is_none() {
            if let Err(why) = &a.cores {
                tracing::warn!("{} thread not pinned: {why}", role.name());
            }
            if let Err(why) = &a.nice {
                tracing::warn!("{} thread priority not lowered: {why}", role.name());
            }
            *slot = Some(a);
        }
    }

    /// The mapping stage made its pool of `n` workers.
    pub fn mapping_pool_made(&self, n: usize) {
        self.mapping_workers.store(n, std::sync::atomic::Ordering::Relaxed);
    }

    /// One line: what each stage thread got, e.g. `threads: tracking cores [0] nice 0;
    /// mapping nice 19 workers 1; logging nice 5`.
    pub fn summary(&self) -> String {
        let g = self.applied.lock().unwrap_or_else(|p| p.into_inner());
        let mut parts = Vec::with_capacity(3);
        for role in [StageThread::Tracking, StageThread::Mapping, StageThread::Logging] {
            let Some(a) = &g[role as usize] else { continue };
            let cores = match &a.cores {
                Ok(None) => String::new(),
                Ok(Some(c)) => format!(" cores {c:?}"),
                Err(why) => format!(" NOT PINNED ({why})"),
            };
            let nice = match &a.nice {
                Ok(n) => format!(" nice {n}"),
                Err(why) => format!(" nice NOT SET ({why})"),
            };
            let made = self.mapping_workers.load(std::sync::atomic::Ordering::Relaxed);
            let workers = if role == StageThread::Mapping && made > 0 { format!(" workers {made}") } else { String::new() };
            parts.push(format!("{}{cores}{nice}{workers}", role.name()));
        }
        format!("threads: {}", parts.join("; "))
    }
}

#[cfg(target_os = "linux")]
mod os {
    use rustix::process::{getpriority_process, setpriority_process};
    use rustix::thread::{gettid, sched_getaffinity, sched_setaffinity, CpuSet};

    /// Pins the calling thread to those of `want` it may run on; the cores it is pinned to.
    pub fn pin_current_thread(want: &[usize]) -> Result<Vec<usize>, String> {
        let allowed = sched_getaffinity(None).map_err(|e| format!("sched_getaffinity: {e}"))?;
        let mut set = CpuSet::new();
        let mut got = Vec::with_capacity(want.len());
        for &c in want {
            if c < CpuSet::MAX_CPU && allowed.is_set(c) {
                set.set(c);
                got.push(c);
            }
        }
        if got.is_empty() {
            let have: Vec<usize> = (0..CpuSet::MAX_CPU).filter(|c| allowed.is_set(*c)).collect();
            return Err(format!("none of cores {want:?} is available (this process may run on {have:?})"));
        }
        if got.len() < want.len() {
            tracing::warn!("cores {want:?}: only {got:?} available to this process");
        }
        sched_setaffinity(None, &set).map_err(|e| format!("sched_setaffinity: {e}"))?;
        Ok(got)
    }

    /// Adds `by` to the calling thread's nice value (at most 19); the value now.
    pub fn raise_nice_of_current_thread(by: i32) -> Result<i32, String> {
        let tid = Some(gettid());
        let now = getpriority_process(tid).map_err(|e| format!("getpriority: {e}"))?;
        if by <= 0 {
            return Ok(now);
        }
        let to = (now + by).min(19);
        setpriority_process(tid, to).map_err(|e| format!("setpriority {to}: {e}"))?;
        Ok(to)
    }
}

#[cfg(not(target_os = "linux"))]
mod os {
    pub fn pin_current_thread(_want: &[usize]) -> Result<Vec<usize>, String> {
        Err("pinning threads is only supported on Linux".into())
    }
    pub fn raise_nice_of_current_thread(by: i32) -> Result<i32, String> {
        if by <= 0 { Ok(0) } else { Err("thread priorities are only supported on Linux".into()) }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    /// On a thread of its own: the nice value goes up by the board's amount and the thread is
    /// pinned to the one core asked for; a core the machine does not have is a reason, not a
    /// panic.
    #[test]
    fn a_mapping_thread_is_pinned_and_yields() {
        let placement = ThreadPlacement { mapping_cores: Some(vec![0]), mapping_nice: 7, ..Default::default() };
        let (a, before, cores_after) = std::thread::spawn(move || {
            let before = rustix::process::getpriority_process(Some(rustix::thread::gettid())).unwrap();
            let a = placement.apply_here(StageThread::Mapping);
            let set = rustix::thread::sched_getaffinity(None).unwrap();
            (a, before, (0..64).filter(|c| set.is_set(*c)).collect::<Vec<_>>())
        })
        .join()
        .unwrap();
        assert_eq!(a.cores, Ok(Some(vec![0])));
        assert_eq!(cores_after, vec![0]);
        assert_eq!(a.nice, Ok((before + 7).min(19)));
        // The test thread itself is untouched.
        assert_eq!(rustix::process::getpriority_process(Some(rustix::thread::gettid())).unwrap(), before);
    }

    #[test]
    fn the_summary_says_what_was_applied() {
        let placement = ThreadPlacement { tracking_cores: Some(vec![1000]), mapping_nice: 3, mapping_workers: 1, ..Default::default() };
        let report = std::sync::Arc::new(PlacementReport::default());
        for role in [StageThread::Tracking, StageThread::Mapping] {
            let (r, p) = (report.clone(), placement.clone());
            std::thread::spawn(move || r.apply_here(&p, role)).join().unwrap();
        }
        // No pool made (a run without a map): no workers said.
        assert!(!report.summary().contains("workers"), "{}", report.summary());
        report.mapping_pool_made(1);
        let line = report.summary();
        assert!(line.starts_with("threads: tracking NOT PINNED (none of cores [1000] is available"), "{line}");
        assert!(line.contains("; mapping nice "), "{line}");
        assert!(line.ends_with(" workers 1"), "{line}");
        assert!(!line.contains("logging"), "{line}");
    }
}
