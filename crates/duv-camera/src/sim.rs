//! The generator as a live frame source: `sim:WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=P]`
//! renders frames at the board's resolution and frame rate, with exact ground truth.
//!
//! `pace=realtime` (the default) releases frame `i` no earlier than `i / fps` seconds after the
//! first, like a camera; `pace=none` renders as fast as it can (offline runs, tests). The time
//! stamps are the generator's own (`i / fps`) either way.

use super::{CameraError, FrameSource, SourceStats};
use duv_core::config::board::Board;
use duv_core::{Frame, FrameImage, PinholeCamera, StampedPose};
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use std::time::{Duration, Instant};

/// Frames a `sim:` source generates unless `frames=N` says otherwise.
pub const SIM_DEFAULT_FRAMES: usize = 300;

/// How a `sim:` source paces its frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimPace {
    /// One frame per `1 / fps` of wall time, like a camera.
    Realtime,
    /// As fast as the renderer goes.
    None,
}

/// `WATER[-TRAJECTORY]`: water clear|coastal|turbid, trajectory survey|loop|hover.
pub fn parse_sim_preset(spec: &str, preset: &str) -> Result<(WaterPreset, TrajectoryKind), CameraError> {
    let bad = |problem: String| CameraError::BadSpec { spec: spec.to_string(), problem };
    let mut parts = preset.splitn(2, '-');
    let water = match parts.next().unwrap_or("") {
        "clear" => WaterPreset::Clear,
        "coastal" => WaterPreset::Coastal,
        "turbid" => WaterPreset::Turbid,
        w => return Err(bad(format!("unknown water {w:?} (expected clear, coastal or turbid)"))),
    };
    let trajectory = match parts.next() {
        None | Some("survey") => TrajectoryKind::Survey,
        Some("loop") => TrajectoryKind::Loop,
        Some("hover") => TrajectoryKind::Hover,
        Some(t) => return Err(bad(format!("unknown trajectory {t:?} (expected survey, loop or hover)"))),
    };
    Ok((water, trajectory))
}

/// A parsed `sim:` spec, `WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=realtime|none]`: the
/// one parser of the syntax, for [`SimSource`] and for `duv run`'s in-memory generator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimSpec {
    pub water: WaterPreset,
    pub trajectory: TrajectoryKind,
    /// `frames=N`, when given.
    pub frames: Option<usize>,
    /// `seed=S`, when given.
    pub seed: Option<u64>,
    /// `pace=`, when given ([`SimSource`] paces in real time unless told otherwise).
    pub pace: Option<SimPace>,
    /// `nav=on`: the run also gets the generator's navigation sensors (`duv_sim::nav`, the
    /// noise `duv sim` writes into `nav.csv`); off unless asked for.
    pub nav: bool,
}

impl SimSpec {
    /// Parses the part of `spec` after `sim:` (`rest`); errors name `spec`.
    pub fn parse(spec: &str, rest: &str) -> Result<SimSpec, CameraError> {
        let bad = |problem: String| CameraError::BadSpec { spec: spec.to_string(), problem };
        let mut parts = rest.split(',');
        let (water, trajectory) = parse_sim_preset(spec, parts.next().unwrap_or("").trim())?;
        let mut parsed = SimSpec { water, trajectory, frames: None, seed: None, pace: None, nav: false };
        for part in parts {
            let (key, value) = part.split_once('=').map(|(k, v)| (k.trim(), v.trim())).ok_or_else(|| bad(format!("option {part:?} is not KEY=VALUE")))?;
            let number = || value.parse::<u64>().map_err(|_| bad(format!("{key}={value:?} is not a whole number")));
            match key {
                "frames" => parsed.frames = Some(number()? as usize),
                "seed" => parsed.seed = Some(number()?),
                "pace" => {
                    parsed.pace = Some(match value {
                        "realtime" => SimPace::Realtime,
                        "none" => SimPace::None,
                        _ => return Err(bad(format!("pace={value:?} (expected realtime or none)"))),
                    })
                }
                "nav" => {
                    parsed.nav = match value {
                        "on" => true,
                        "off" => false,
                        _ => return Err(bad(format!("nav={value:?} (expected on or off)"))),
                    }
                }
                _ => return Err(bad(format!("unknown option {key:?} (accepted: frames, seed, pace, nav)"))),
            }
        }
        Ok(parsed)
    }
}

/// The generator as a [`FrameSource`].
pub struct SimSource {
    renderer: Box<SimRenderer>,
    next: usize,
    pace: SimPace,
    started: Option<Instant>,
    stats: SourceStats,
}

impl SimSource {
    /// Opens `sim:` from the part after the colon; size and frame rate from the board.
    pub fn open(spec: &str, rest: &str, board: &Board) -> Result<SimSource, CameraError> {
        let parsed = SimSpec::parse(spec, rest)?;
        let mut cfg = SimConfig::preset(parsed.water, parsed.trajectory);
        cfg.width = board.camera.width as usize;
        cfg.height = board.camera.height as usize;
        cfg.fps = board.camera.fps;
        cfg.frames = parsed.frames.unwrap_or(SIM_DEFAULT_FRAMES);
        if let Some(seed) = parsed.seed {
            cfg.seed = seed;
        }
        let renderer = SimRenderer::new(&cfg).map_err(|e| CameraError::BadSpec { spec: spec.to_string(), problem: e.to_string() })?;
        Ok(SimSource { renderer: Box::new(renderer), next: 0, pace: parsed.pace.unwrap_or(SimPace::Realtime), started: None, stats: SourceStats::default() })
    }

    pub fn renderer(&self) -> &SimRenderer {
        &self.renderer
    }

    /// Frames not yet delivered.
    pub fn remaining(&self) -> usize {
        self.renderer.len() - self.next
    }
}

impl FrameSource for SimSource {
    fn camera(&self) -> &PinholeCamera {
        self.renderer.camera()
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        if self.next >= self.renderer.len() {
            return Ok(None);
        }
        let i = self.next;
        self.next += 1;
        let frame = self.renderer.render(i);
        if self.pace == SimPace::Realtime {
            let started = *self.started.get_or_insert_with(Instant::now);
            let due = started + Duration::from_secs_f64(i as f64 / self.renderer.config().fps);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        self.stats.delivered += 1;
        tracing::trace!(seq = i, t_ns = frame.t_ns.t_ns(), "sim frame");
        Ok(Some(Frame { t_ns: frame.t_ns, seq: i as u64, image: FrameImage::Rgb8(frame.rgb) }))
    }

    fn describe(&self) -> String {
        let c = self.renderer.config();
        let pace = match self.pace {
            SimPace::Realtime => "real time",
            SimPace::None => "unpaced",
        };
        format!("sim {} water, {} path, {} frames {}x{} at {} fps ({pace})", c.water, c.trajectory, self.renderer.len(), c.width, c.height, c.fps)
    }

    fn stats(&self) -> SourceStats {
        self.stats
    }

    fn ground_truth(&self) -> Option<&[StampedPose]> {
        Some(self.renderer.poses())
    }
}
