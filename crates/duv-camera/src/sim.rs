//! The generator as a live frame source: `sim:WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=P]`
//! `[,nav=on][,lamps=on][,backscatter=S][,snow=N][,seabed=C][,burst=START:DURATION[:FACTOR]][,night=on]`
//! renders frames at the board's resolution and frame rate, with exact ground truth.
//!
//! `pace=realtime` (the default) releases frame `i` no earlier than `i / fps` seconds after the
//! first, like a camera; `pace=none` renders as fast as it can (offline runs, tests). The time
//! stamps are the generator's own (`i / fps`) either way.

use super::{CameraError, FrameSource, SourceStats};
use duv_core::config::board::Board;
use duv_core::{Frame, FrameImage, PinholeCamera, StampedPose};
use duv_sim::{Burst, SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
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

/// A parsed `sim:` spec, `WATER[-TRAJECTORY][,frames=N][,seed=S][,pace=realtime|none][,nav=on]`
/// `[,lamps=on][,backscatter=S][,snow=N][,seabed=C][,burst=START:DURATION[:FACTOR]][,night=on]`: the one
/// parser of the syntax, for [`SimSource`] and for `duv run`'s in-memory generator. The scene
/// options are `duv sim`'s (`--lamps`, `--lamp-backscatter`, `--snow`, `--burst`, `--night`);
/// [`SimSpec::apply`] sets them on a config.
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
    /// `night=on`: `duv sim --night` (lamps, lamp-lit backscatter, marine snow), before the
    /// options below, which override it.
    pub night: bool,
    /// `lamps=on|off`, when given.
    pub lamps: Option<bool>,
    /// `backscatter=S`: the lamps' glow strength, when given.
    pub backscatter: Option<f64>,
    /// `snow=N`: marine snow particles per cubic metre, when given.
    pub snow: Option<f64>,
    /// `seabed=C`: contrast of the seabed texture (`SimConfig::seabed_texture`).
    pub seabed: Option<f64>,
    /// `burst=START:DURATION[:FACTOR]`: a turbidity burst, seconds.
    pub burst: Option<Burst>,
}

impl SimSpec {
    /// Parses the part of `spec` after `sim:` (`rest`); errors name `spec`.
    pub fn parse(spec: &str, rest: &str) -> Result<SimSpec, CameraError> {
        let bad = |problem: String| CameraError::BadSpec { spec: spec.to_string(), problem };
        let mut parts = rest.split(',');
        let (water, trajectory) = parse_sim_preset(spec, parts.next().unwrap_or("").trim())?;
        let mut parsed = SimSpec { water, trajectory, frames: None, seed: None, pace: None, nav: false, night: false, lamps: None, backscatter: None, snow: None, seabed: None, burst: None };
        for part in parts {
            let (key, value) = part.split_once('=').map(|(k, v)| (k.trim(), v.trim())).ok_or_else(|| bad(format!("option {part:?} is not KEY=VALUE")))?;
            let number = || value.parse::<u64>().map_err(|_| bad(format!("{key}={value:?} is not a whole number")));
            let real = || value.parse::<f64>().ok().filter(|v| v.is_finite() && *v >= 0.0).ok_or_else(|| bad(format!("{key}={value:?} is not a non-negative number")));
            let on_off = || match value {
                "on" => Ok(true),
                "off" => Ok(false),
                _ => Err(bad(format!("{key}={value:?} (expected on or off)"))),
            };
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
                "nav" => parsed.nav = on_off()?,
                "night" => parsed.night = on_off()?,
                "lamps" => parsed.lamps = Some(on_off()?),
                "backscatter" => parsed.backscatter = Some(real()?),
                "snow" => parsed.snow = Some(real()?),
                "seabed" => parsed.seabed = Some(real()?),
                "burst" => parsed.burst = Some(value.parse::<Burst>().map_err(|e| bad(format!("{e} (in a spec: burst=START:DURATION[:FACTOR])")))?),
                _ => return Err(bad(format!("unknown option {key:?} (accepted: frames, seed, pace, nav, night, lamps, backscatter, snow, seabed, burst)"))),
            }
        }
        Ok(parsed)
    }

    /// Sets the scene options of the spec on `cfg`: `night=on` first, then `lamps`,
    /// `backscatter`, `snow` and `burst` (`SimConfig::validate` checks the result, e.g. a
    /// backscatter without lamps).
    pub fn apply(&self, cfg: &mut SimConfig) {
        if self.night {
            cfg.apply_night();
        }
        if let Some(on) = self.lamps {
            cfg.lamps = on;
        }
        if let Some(s) = self.backscatter {
            cfg.lamp_backscatter = s;
        }
        if let Some(n) = self.snow {
            cfg.snow_per_m3 = n;
        }
        if let Some(c) = self.seabed {
            cfg.seabed_texture = c;
        }
        if self.burst.is_some() {
            cfg.burst = self.burst;
        }
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
        parsed.apply(&mut cfg);
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
        let conditions = match c.conditions() {
            s if s.is_empty() => s,
            s => format!(", {s}"),
        };
        format!("sim {} water, {} path, {} frames {}x{} at {} fps{conditions} ({pace})", c.water, c.trajectory, self.renderer.len(), c.width, c.height, c.fps)
    }

    fn stats(&self) -> SourceStats {
        self.stats
    }

    fn ground_truth(&self) -> Option<&[StampedPose]> {
        Some(self.renderer.poses())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(rest: &str) -> Result<SimSpec, CameraError> {
        SimSpec::parse(&format!("sim:{rest}"), rest)
    }

    #[test]
    fn scene_options_parse_and_apply_like_duv_sim() {
        let plain = parse("coastal").unwrap();
        let mut cfg = SimConfig::default();
        plain.apply(&mut cfg);
        assert_eq!(cfg, SimConfig::default(), "no options change nothing");

        // night=on is --night: lamps, backscatter 1, 150 particles per m^3.
        let mut night = SimConfig::default();
        parse("coastal-loop,night=on").unwrap().apply(&mut night);
        assert!(night.lamps);
        assert_eq!((night.lamp_backscatter, night.snow_per_m3), (duv_sim::NIGHT_LAMP_BACKSCATTER, duv_sim::NIGHT_SNOW_PER_M3));
        assert_eq!((night.lamp_backscatter, night.snow_per_m3), (1.0, 150.0));
        night.validate().unwrap();

        // Explicit options override night=on whatever their order.
        let spec = parse("turbid,snow=40,night=on,backscatter=0.5,burst=3:4").unwrap();
        assert_eq!(spec.snow, Some(40.0));
        assert_eq!(spec.burst, Some(Burst { start_s: 3.0, duration_s: 4.0, factor: 8.0 }));
        let mut cfg = SimConfig::default();
        spec.apply(&mut cfg);
        assert_eq!((cfg.lamps, cfg.lamp_backscatter, cfg.snow_per_m3), (true, 0.5, 40.0));
        assert_eq!(cfg.burst, Some(Burst { start_s: 3.0, duration_s: 4.0, factor: 8.0 }));
        let spec = parse("clear,lamps=on,burst=1.5:2:3").unwrap();
        assert_eq!((spec.lamps, spec.burst.map(|b| b.factor)), (Some(true), Some(3.0)));
        // seabed=C is --seabed-texture C.
        let mut sand = SimConfig::default();
        parse("coastal,seabed=0.05").unwrap().apply(&mut sand);
        assert_eq!(sand.seabed_texture, 0.05);

        // lamps=off after night=on leaves a glow without lamps: the config refuses it by name.
        let mut cfg = SimConfig::default();
        parse("coastal,night=on,lamps=off").unwrap().apply(&mut cfg);
        assert!(cfg.validate().unwrap_err().to_string().contains("lamp_backscatter"));
    }

    #[test]
    fn bad_scene_options_name_the_option() {
        for (rest, needle) in [
            ("coastal,snow=-3", "snow=\"-3\" is not a non-negative number"),
            ("coastal,snow=lots", "snow=\"lots\""),
            ("coastal,night=yes", "night=\"yes\" (expected on or off)"),
            ("coastal,lamps=1", "lamps=\"1\""),
            ("coastal,burst=3", "invalid turbidity burst \"3\""),
            ("coastal,burst=3:x", "every part must be a number"),
            ("coastal,backscatter=NaN", "backscatter=\"NaN\""),
            ("coastal,fog=on", "accepted: frames, seed, pace, nav, night, lamps, backscatter, snow, seabed, burst"),
        ] {
            let e = parse(rest).unwrap_err().to_string();
            assert!(e.contains(needle) && e.contains(&format!("sim:{rest}")), "{rest}: {e}");
        }
    }
}
