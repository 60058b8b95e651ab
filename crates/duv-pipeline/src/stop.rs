//! How a run is asked to stop. The first SIGINT or SIGTERM (or the caller) sets
//! [`Stop::requested`]: capture ends, tracking finishes the frames already queued, mapping
//! abandons its queue and its iteration in flight (the keyframes are in the log, the newest
//! checkpoint is on disk), the log closes, and the caller writes its outputs without the final
//! map optimisation. A second signal sets [`Stop::abort`]: the log drops what is still queued
//! and closes, and [`run`](super::run) returns [`PipelineError::Aborted`](super::PipelineError)
//! at once, without waiting for the other stages.

use super::PipelineError;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicI32, Ordering};
use std::sync::Arc;

/// Stop flags shared by the stages and the signal thread.
#[derive(Clone, Debug, Default)]
pub struct Stop {
    /// Finish like the end of the stream, as fast as the stages can.
    pub requested: Arc<AtomicBool>,
    /// Close the log and return now.
    pub abort: Arc<AtomicBool>,
    /// The first signal received (0: none).
    signal: Arc<AtomicI32>,
}

impl From<Arc<AtomicBool>> for Stop {
    fn from(requested: Arc<AtomicBool>) -> Self {
        Stop { requested, ..Default::default() }
    }
}

impl Stop {
    /// Flags set by SIGINT and SIGTERM: the first requests the stop, the second aborts.
    pub fn on_signals() -> Result<Self, PipelineError> {
        use signal_hook::consts::{SIGINT, SIGTERM};
        let stop = Stop::default();
        let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM]).map_err(|source| PipelineError::Io { path: PathBuf::from("<signal handler>"), source })?;
        let s = stop.clone();
        std::thread::Builder::new()
            .name("signals".into())
            .spawn(move || {
                for sig in signals.forever() {
                    if s.signal.compare_exchange(0, sig, Ordering::SeqCst, Ordering::SeqCst).is_ok() {
                        tracing::warn!("signal {sig} received: stopping (the log closes first; a second signal stops at once)");
                        s.requested.store(true, Ordering::SeqCst);
                    } else {
                        tracing::warn!("second signal {sig}: closing the log and stopping now");
                        s.requested.store(true, Ordering::SeqCst);
                        s.abort.store(true, Ordering::SeqCst);
                    }
                }
            })
            .map_err(|source| PipelineError::Io { path: PathBuf::from("<thread signals>"), source })?;
        Ok(stop)
    }

    pub fn is_aborted(&self) -> bool {
        self.abort.load(Ordering::Relaxed)
    }

    /// The first signal received, if any.
    pub fn signal(&self) -> Option<i32> {
        Some(self.signal.load(Ordering::SeqCst)).filter(|&s| s != 0)
    }

    /// The shell's exit status for the first signal: 128 + its number (130 for SIGINT, 143 for
    /// SIGTERM); `None` without a signal.
    pub fn exit_code(&self) -> Option<u8> {
        self.signal().and_then(|s| u8::try_from(128 + s).ok())
    }
}
