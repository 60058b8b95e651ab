//! Underwater sequence generator with exact ground truth (`duv sim`).
//!
//! A procedural seabed (a heightfield with dunes, sand ripples, rocks and boulders; sand, rock
//! and algae albedo with detail down to millimetres; a pipeline and a wreck for inspection) is
//! flown over by an AUV-like camera (lawnmower survey, closed loop, hover with yaw) and seen
//! through water with the image formation model of the paper (§3.2), per colour channel:
//!
//! `I = J exp(-beta_D r) + B_inf (1 - exp(-beta_B r))`, `r` the range along the ray.
//!
//! The hard cases of a real dive are options: the lamps' light scattered back by the water in
//! front of the camera (a glow fixed in the image, [`water::LampsInWorld::scatter_profile`]),
//! marine snow fixed in the world ([`snow`]) and a turbidity burst ([`Burst`]).
//!
//! Everything is a pure function of the [`SimConfig`] (seeded with [`duv_core::rng::Rng`]
//! and our own lattice noise), so the same config gives byte-identical files. The output
//! folder uses the TUM RGB-D layout (see [`writer`]).
//!
//! World frame: x east, y north, z up, seabed around z = 0. Camera frame: x right, y down,
//! z forward. Poses are `world_from_cam`.

pub mod heightfield;
pub mod hit;
pub mod keyframes;
pub mod materials;
pub mod nav;
pub mod noise;
pub mod render;
pub mod scene;
pub mod snow;
pub mod structures;
pub mod terrain;
pub mod trajectory;
pub mod water;
pub mod writer;

pub use render::{SimFrame, SimRenderer};
pub use nav::NavNoise;
pub use writer::{write_sequence, write_sequence_with, SimManifest, SimReport};

use duv_core::{MediumParams, PinholeCamera};
use std::path::PathBuf;

/// Water type: attenuation, backscatter and veiling light (see [`water`] for the values).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum WaterPreset {
    /// Clear oceanic water (Jerlov I-II): blue cast, red lost within metres, long visibility.
    Clear,
    /// Coastal water (Jerlov 3C-5C): green veiling light, moderate visibility.
    Coastal,
    /// Turbid harbour water (Jerlov 7C-9C): brown-green haze, visibility of a few metres.
    Turbid,
}

/// The vehicle's path.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum TrajectoryKind {
    /// Lawnmower: parallel lanes joined by rounded (semicircular) turns.
    Survey,
    /// A closed stadium-shaped loop that returns over its start and runs a little past it.
    Loop,
    /// Station keeping: slow drift on a small circle with a slow yaw sweep.
    Hover,
}

impl std::fmt::Display for WaterPreset {
    /// The name the command line takes (`coastal`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            WaterPreset::Clear => "clear",
            WaterPreset::Coastal => "coastal",
            WaterPreset::Turbid => "turbid",
        })
    }
}

impl std::fmt::Display for TrajectoryKind {
    /// The name the command line takes (`survey`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            TrajectoryKind::Survey => "survey",
            TrajectoryKind::Loop => "loop",
            TrajectoryKind::Hover => "hover",
        })
    }
}

/// Vehicle attitude and depth wobble: each axis is a sum of two incommensurate sinusoids with
/// seeded phases (smooth, never periodic within a sequence).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Wobble {
    /// Roll amplitude, degrees.
    pub roll_deg: f64,
    /// Pitch amplitude, degrees (added to the camera's pitch-down).
    pub pitch_deg: f64,
    /// Yaw amplitude, degrees (sway around the path heading).
    pub yaw_deg: f64,
    /// Heave (vertical) amplitude, metres.
    pub heave_m: f64,
    /// Main period, seconds.
    pub period_s: f64,
}

impl Wobble {
    /// A calm AUV in light current.
    pub const DEFAULT: Wobble = Wobble { roll_deg: 1.5, pitch_deg: 1.0, yaw_deg: 1.0, heave_m: 0.05, period_s: 7.0 };
    pub const NONE: Wobble = Wobble { roll_deg: 0.0, pitch_deg: 0.0, yaw_deg: 0.0, heave_m: 0.0, period_s: 7.0 };

    /// All amplitudes multiplied by `factor` (the period is kept).
    pub fn scaled(self, factor: f64) -> Wobble {
        Wobble {
            roll_deg: self.roll_deg * factor,
            pitch_deg: self.pitch_deg * factor,
            yaw_deg: self.yaw_deg * factor,
            heave_m: self.heave_m * factor,
            period_s: self.period_s,
        }
    }
}

/// Everything that defines a generated sequence. `sim.json` holds a copy.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    pub water: WaterPreset,
    pub trajectory: TrajectoryKind,
    /// Number of frames (>= 1).
    pub frames: usize,
    /// Image width in pixels (>= 2).
    pub width: usize,
    /// Image height in pixels (>= 2).
    pub height: usize,
    /// Frame rate, frames per second; time stamps are `i / fps` seconds.
    pub fps: f64,
    /// Horizontal field of view, degrees (pinhole, square pixels, no distortion).
    pub hfov_deg: f64,
    /// Vehicle speed along the path, m/s (the drift speed for `hover`).
    pub speed_mps: f64,
    /// Nominal altitude of the camera above the large-scale seabed, metres.
    pub altitude_m: f64,
    /// Yo-yo altitude profile: the altitude swings this far above and below `altitude_m`
    /// (metres; 0 = constant altitude), `altitude_m + swing sin(2 pi t / period)`, so the
    /// seabed is seen from different ranges along the way (as on an AUV that climbs and
    /// descends over the survey, or a diver's camera).
    #[serde(default)]
    pub altitude_swing_m: f64,
    /// Period of the yo-yo altitude profile, seconds.
    #[serde(default = "default_altitude_period_s")]
    pub altitude_period_s: f64,
    /// Camera pitch below the horizontal, degrees (forward-looking camera tilted down).
    pub pitch_down_deg: f64,
    pub wobble: Wobble,
    /// Vehicle lamps instead of sunlight (a deep dive: darker veiling light).
    pub lamps: bool,
    /// Strength of the lamps' light scattered back by the water in front of the camera (0 =
    /// only the uniform veiling light; 1 = the calibrated glow of [`water::LAMP_SCATTER_PHASE`]).
    /// Needs `lamps`. The glow is fixed in the image as the vehicle moves.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lamp_backscatter: f64,
    /// Marine snow, particles per cubic metre (0 = none): world-fixed specks 1-4 mm across
    /// drifting a few cm/s, drawn in `rgb` only (see [`snow`]).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub snow_per_m3: f64,
    /// A turbidity burst: the attenuation and backscatter coefficients rise and fall over a
    /// time window (`medium.json` keeps the base medium).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub burst: Option<Burst>,
    /// Contrast of the seabed's texture (sand grain, film, rocks, algae) around a mid sand
    /// tint, in [0, 1]: 1 as generated, 0.1 nearly featureless sand (the relief's shading
    /// stays). Pipe and wreck keep theirs.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub seabed_texture: f64,
    /// Gaussian sensor noise, standard deviation as a fraction of full scale (0.004 ~ 1 DN).
    pub noise_sigma: f64,
    /// Vignetting strength in [0, 1]: gain `1 - v rho^2` with `rho` 1 at the image corners.
    pub vignetting: f64,
    pub seed: u64,
    /// Rays that hit nothing within this range see pure water and have depth 0 (metres).
    pub max_range_m: f64,
    /// Survey lane length, metres.
    pub lane_length_m: f64,
    /// Survey lane spacing, metres (the turn radius is half of it).
    pub lane_spacing_m: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey)
    }
}

impl SimConfig {
    /// Sensible defaults for a water type and a trajectory (320x240 at 10 fps, 2 m altitude,
    /// camera pitched 40 degrees down).
    pub fn preset(water: WaterPreset, trajectory: TrajectoryKind) -> Self {
        let (frames, speed_mps, pitch_down_deg) = match trajectory {
            TrajectoryKind::Survey => (300, 0.5, 40.0),
            TrajectoryKind::Loop => (400, 0.5, 40.0),
            TrajectoryKind::Hover => (200, 0.05, 35.0),
        };
        SimConfig {
            water,
            trajectory,
            frames,
            width: 320,
            height: 240,
            fps: 10.0,
            hfov_deg: 70.0,
            speed_mps,
            altitude_m: 2.0,
            altitude_swing_m: 0.0,
            altitude_period_s: default_altitude_period_s(),
            pitch_down_deg,
            wobble: Wobble::DEFAULT,
            lamps: false,
            lamp_backscatter: 0.0,
            snow_per_m3: 0.0,
            burst: None,
            seabed_texture: 1.0,
            noise_sigma: 0.006,
            vignetting: 0.3,
            seed: 1,
            max_range_m: water::default_max_range_m(water),
            lane_length_m: 10.0,
            lane_spacing_m: 3.0,
        }
    }

    /// The pinhole camera of the images (principal point at the centre, square pixels). Only
    /// meaningful for a config that passes [`SimConfig::validate`].
    pub fn camera(&self) -> PinholeCamera {
        let fx = 0.5 * self.width as f64 / (0.5 * self.hfov_deg.to_radians()).tan();
        PinholeCamera {
            fx,
            fy: fx,
            cx: (self.width as f64 - 1.0) * 0.5,
            cy: (self.height as f64 - 1.0) * 0.5,
            width: self.width,
            height: self.height,
            distortion: None,
        }
    }

    /// The medium the images are formed with (as written to `medium.json`).
    pub fn medium(&self) -> MediumParams {
        water::medium(self.water, self.lamps)
    }

    /// The medium of the frame at `t_s` seconds: [`SimConfig::medium`] with `beta_D` and
    /// `beta_B` times the burst's [`Burst::multiplier`] (exactly the base medium outside it).
    pub fn medium_at(&self, t_s: f64) -> MediumParams {
        let mut m = self.medium();
        if let Some(burst) = &self.burst {
            let k = burst.multiplier(t_s);
            if k != 1.0 {
                for c in 0..3 {
                    m.beta_d[c] *= k;
                    m.beta_b[c] *= k;
                }
            }
        }
        m
    }

    /// The `--night` shorthand: lamps, lamp-lit backscatter [`NIGHT_LAMP_BACKSCATTER`] and
    /// marine snow [`NIGHT_SNOW_PER_M3`].
    pub fn apply_night(&mut self) {
        self.lamps = true;
        self.lamp_backscatter = NIGHT_LAMP_BACKSCATTER;
        self.snow_per_m3 = NIGHT_SNOW_PER_M3;
    }

    /// The lighting and water events in words, e.g. `lamps, backscatter 1, snow 150/m3, burst
    /// 10+6 s x8` (empty under plain sunlight).
    pub fn conditions(&self) -> String {
        let mut parts = Vec::new();
        if self.lamps {
            parts.push("lamps".to_string());
        }
        if self.lamp_backscatter > 0.0 {
            parts.push(format!("backscatter {}", self.lamp_backscatter));
        }
        if self.snow_per_m3 > 0.0 {
            parts.push(format!("snow {}/m3", self.snow_per_m3));
        }
        if let Some(b) = &self.burst {
            parts.push(format!("burst {}+{} s x{}", b.start_s, b.duration_s, b.factor));
        }
        if self.seabed_texture != 1.0 {
            parts.push(format!("seabed texture x{}", self.seabed_texture));
        }
        parts.join(", ")
    }

    /// Duration from the first to the last frame, seconds.
    pub fn duration_secs(&self) -> f64 {
        self.frames.saturating_sub(1) as f64 / self.fps
    }

    /// Checks every field; the first problem found is the error.
    pub fn validate(&self) -> Result<(), SimError> {
        fn bad(field: &'static str, value: impl std::fmt::Display, expected: &'static str) -> Result<(), SimError> {
            Err(SimError::InvalidConfig { field, value: value.to_string(), expected })
        }
        let finite_in = |v: f64, lo: f64, hi: f64| v.is_finite() && v >= lo && v <= hi;
        if self.frames == 0 || self.frames > MAX_FRAMES {
            return bad("frames", self.frames, "between 1 and 1000000");
        }
        if self.width < 2 || self.width > MAX_SIDE {
            return bad("width", self.width, "between 2 and 16384 pixels");
        }
        if self.height < 2 || self.height > MAX_SIDE {
            return bad("height", self.height, "between 2 and 16384 pixels");
        }
        if !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 1000.0) {
            return bad("fps", self.fps, "a frame rate in (0, 1000]");
        }
        if !finite_in(self.hfov_deg, 10.0, 160.0) {
            return bad("hfov_deg", self.hfov_deg, "a field of view in [10, 160] degrees");
        }
        if !(self.speed_mps.is_finite() && self.speed_mps > 0.0 && self.speed_mps <= 5.0) {
            return bad("speed_mps", self.speed_mps, "a speed in (0, 5] m/s");
        }
        if !finite_in(self.altitude_m, 0.3, 20.0) {
            return bad("altitude_m", self.altitude_m, "an altitude in [0.3, 20] m");
        }
        if !finite_in(self.altitude_swing_m, 0.0, 10.0) || self.altitude_m - self.altitude_swing_m < 0.3 {
            return bad("altitude_swing_m", self.altitude_swing_m, "a swing in [0, 10] m that keeps the lowest altitude (altitude_m - swing) at 0.3 m or more");
        }
        if !finite_in(self.altitude_period_s, 1.0, 10_000.0) {
            return bad("altitude_period_s", self.altitude_period_s, "a period in [1, 10000] s");
        }
        if !finite_in(self.pitch_down_deg, 0.0, 90.0) {
            return bad("pitch_down_deg", self.pitch_down_deg, "a pitch in [0, 90] degrees below the horizontal");
        }
        let w = &self.wobble;
        for (field, v, hi) in [
            ("wobble.roll_deg", w.roll_deg, 30.0),
            ("wobble.pitch_deg", w.pitch_deg, 30.0),
            ("wobble.yaw_deg", w.yaw_deg, 30.0),
            ("wobble.heave_m", w.heave_m, 1.0),
        ] {
            if !finite_in(v, 0.0, hi) {
                return bad(field, v, "a finite non-negative amplitude (at most 30 degrees or 1 m)");
            }
        }
        if !(w.period_s.is_finite() && w.period_s >= 0.1 && w.period_s <= 1000.0) {
            return bad("wobble.period_s", w.period_s, "a period in [0.1, 1000] s");
        }
        if !finite_in(self.lamp_backscatter, 0.0, 100.0) {
            return bad("lamp_backscatter", self.lamp_backscatter, "a strength in [0, 100]");
        }
        if self.lamp_backscatter > 0.0 && !self.lamps {
            return bad("lamp_backscatter", self.lamp_backscatter, "0 without lamps (it is the lamps' light scattered back: turn the lamps on)");
        }
        if !finite_in(self.seabed_texture, 0.0, 1.0) {
            return bad("seabed_texture", self.seabed_texture, "a contrast in [0, 1] (1: as generated)");
        }
        if !finite_in(self.snow_per_m3, 0.0, MAX_SNOW_PER_M3) {
            return bad("snow_per_m3", self.snow_per_m3, "a density in [0, 5000] particles per cubic metre");
        }
        if let Some(b) = &self.burst {
            if !finite_in(b.start_s, 0.0, 1e7) {
                return bad("burst.start_s", b.start_s, "a start time in [0, 1e7] s");
            }
            if !(b.duration_s.is_finite() && b.duration_s > 0.0 && b.duration_s <= 1e7) {
                return bad("burst.duration_s", b.duration_s, "a duration in (0, 1e7] s");
            }
            if !finite_in(b.factor, 1.0, 100.0) {
                return bad("burst.factor", b.factor, "a factor in [1, 100] on beta_D and beta_B");
            }
        }
        if !finite_in(self.noise_sigma, 0.0, 0.5) {
            return bad("noise_sigma", self.noise_sigma, "a standard deviation in [0, 0.5] of full scale");
        }
        if !finite_in(self.vignetting, 0.0, 1.0) {
            return bad("vignetting", self.vignetting, "a strength in [0, 1]");
        }
        if !finite_in(self.max_range_m, 0.5, 200.0) {
            return bad("max_range_m", self.max_range_m, "a range in [0.5, 200] m");
        }
        if !finite_in(self.lane_length_m, 0.5, 1000.0) {
            return bad("lane_length_m", self.lane_length_m, "a length in [0.5, 1000] m");
        }
        if !finite_in(self.lane_spacing_m, 0.2, 100.0) {
            return bad("lane_spacing_m", self.lane_spacing_m, "a spacing in [0.2, 100] m");
        }
        self.camera().validate().map_err(SimError::Camera)
    }
}

const MAX_FRAMES: usize = 1_000_000;
const MAX_SNOW_PER_M3: f64 = 5000.0;

/// Lamp-lit backscatter strength of `--night`.
pub const NIGHT_LAMP_BACKSCATTER: f64 = 1.0;
/// Marine snow density of `--night`, particles per cubic metre.
pub const NIGHT_SNOW_PER_M3: f64 = 150.0;

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn one() -> f64 {
    1.0
}

fn is_one(v: &f64) -> bool {
    *v == 1.0
}

/// A turbidity burst (sediment stirred up, a plume drifting through): `beta_D` and `beta_B` of
/// every channel are multiplied by `1 + (factor - 1) envelope(t)`, the envelope a raised
/// cosine that rises over the first [`Burst::RISE`] of the duration, holds at 1 and falls over
/// the last [`Burst::FALL`]; the view fades into the veiling light and returns.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Burst {
    /// Start, seconds from the first frame.
    pub start_s: f64,
    /// Whole duration (rise, hold, fall), seconds.
    pub duration_s: f64,
    /// Peak multiplier of the coefficients (>= 1).
    #[serde(default = "default_burst_factor")]
    pub factor: f64,
}

fn default_burst_factor() -> f64 {
    Burst::DEFAULT_FACTOR
}

impl Burst {
    pub const DEFAULT_FACTOR: f64 = 8.0;
    /// Fraction of the duration spent rising (and, [`Burst::FALL`], falling).
    pub const RISE: f64 = 0.2;
    pub const FALL: f64 = 0.2;

    /// 0 before and after, 1 in the hold, a raised cosine in between.
    pub fn envelope(&self, t_s: f64) -> f64 {
        let x = (t_s - self.start_s) / self.duration_s;
        if !(x > 0.0 && x < 1.0) {
            0.0
        } else if x < Self::RISE {
            0.5 - 0.5 * (std::f64::consts::PI * x / Self::RISE).cos()
        } else if x <= 1.0 - Self::FALL {
            1.0
        } else {
            0.5 + 0.5 * (std::f64::consts::PI * (x - (1.0 - Self::FALL)) / Self::FALL).cos()
        }
    }

    /// The coefficients' multiplier at `t_s`: `1 + (factor - 1) envelope(t_s)`.
    pub fn multiplier(&self, t_s: f64) -> f64 {
        let e = self.envelope(t_s);
        if e == 0.0 {
            1.0
        } else {
            1.0 + (self.factor - 1.0) * e
        }
    }
}

impl std::str::FromStr for Burst {
    type Err = SimError;

    /// `START_S,DURATION_S[,FACTOR]` (or with `:` between the numbers, as in a `sim:` spec);
    /// the factor defaults to [`Burst::DEFAULT_FACTOR`]. Values are checked by
    /// [`SimConfig::validate`].
    fn from_str(text: &str) -> Result<Burst, SimError> {
        let bad = |problem: &'static str| SimError::BadBurst { text: text.to_string(), problem };
        let numbers: Vec<&str> = text.split([',', ':']).map(str::trim).collect();
        if !(2..=3).contains(&numbers.len()) {
            return Err(bad("expected START_S,DURATION_S[,FACTOR]"));
        }
        let parse = |s: &str| s.parse::<f64>().map_err(|_| bad("every part must be a number"));
        Ok(Burst { start_s: parse(numbers[0])?, duration_s: parse(numbers[1])?, factor: numbers.get(2).map(|s| parse(s)).transpose()?.unwrap_or(Burst::DEFAULT_FACTOR) })
    }
}

fn default_altitude_period_s() -> f64 {
    20.0
}
const MAX_SIDE: usize = 16_384;

/// Errors of the `sim` module.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("invalid sim config: {field} = {value}, expected {expected}")]
    InvalidConfig { field: &'static str, value: String, expected: &'static str },
    #[error("invalid turbidity burst {text:?}: {problem}")]
    BadBurst { text: String, problem: &'static str },
    #[error("invalid sim camera: {0}")]
    Camera(#[from] duv_core::CameraModelError),
    #[error("the seabed for this trajectory needs {cells} heightfield cells ({width_m:.0} m x {height_m:.0} m), more than the limit of {limit}; use fewer frames, a lower speed or a shorter max range")]
    SceneTooLarge { cells: usize, limit: usize, width_m: f64, height_m: f64 },
    #[error("{path}: cannot write {what}: {reason}")]
    Serialize { path: PathBuf, what: &'static str, reason: String },
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_bad_values_name_the_field() {
        for w in [WaterPreset::Clear, WaterPreset::Coastal, WaterPreset::Turbid] {
            for t in [TrajectoryKind::Survey, TrajectoryKind::Loop, TrajectoryKind::Hover] {
                SimConfig::preset(w, t).validate().unwrap();
            }
        }
        let base = SimConfig::default();
        let cases: Vec<(SimConfig, &str)> = vec![
            (SimConfig { frames: 0, ..base.clone() }, "frames"),
            (SimConfig { width: 0, ..base.clone() }, "width"),
            (SimConfig { height: 1, ..base.clone() }, "height"),
            (SimConfig { speed_mps: f64::NAN, ..base.clone() }, "speed_mps"),
            (SimConfig { fps: 0.0, ..base.clone() }, "fps"),
            (SimConfig { fps: -3.0, ..base.clone() }, "fps"),
            (SimConfig { hfov_deg: f64::INFINITY, ..base.clone() }, "hfov_deg"),
            (SimConfig { vignetting: 1.5, ..base.clone() }, "vignetting"),
            (SimConfig { noise_sigma: -0.1, ..base.clone() }, "noise_sigma"),
            (SimConfig { wobble: Wobble { heave_m: f64::NAN, ..Wobble::DEFAULT }, ..base.clone() }, "wobble.heave_m"),
            (SimConfig { altitude_swing_m: 1.8, ..base.clone() }, "altitude_swing_m"),
            (SimConfig { altitude_swing_m: -0.1, ..base.clone() }, "altitude_swing_m"),
            (SimConfig { altitude_period_s: 0.0, ..base.clone() }, "altitude_period_s"),
            (SimConfig { lamps: true, lamp_backscatter: f64::NAN, ..base.clone() }, "lamp_backscatter"),
            (SimConfig { lamps: true, lamp_backscatter: -0.5, ..base.clone() }, "lamp_backscatter"),
            (SimConfig { lamp_backscatter: 1.0, ..base.clone() }, "lamp_backscatter"),
            (SimConfig { snow_per_m3: -1.0, ..base.clone() }, "snow_per_m3"),
            (SimConfig { seabed_texture: 1.5, ..base.clone() }, "seabed_texture"),
            (SimConfig { seabed_texture: f64::NAN, ..base.clone() }, "seabed_texture"),
            (SimConfig { snow_per_m3: f64::NAN, ..base.clone() }, "snow_per_m3"),
            (SimConfig { snow_per_m3: 1e6, ..base.clone() }, "snow_per_m3"),
            (SimConfig { burst: Some(Burst { start_s: 1.0, duration_s: 2.0, factor: 0.5 }), ..base.clone() }, "burst.factor"),
            (SimConfig { burst: Some(Burst { start_s: 1.0, duration_s: 2.0, factor: f64::NAN }), ..base.clone() }, "burst.factor"),
            (SimConfig { burst: Some(Burst { start_s: 1.0, duration_s: 0.0, factor: 8.0 }), ..base.clone() }, "burst.duration_s"),
            (SimConfig { burst: Some(Burst { start_s: f64::NAN, duration_s: 2.0, factor: 8.0 }), ..base.clone() }, "burst.start_s"),
            (SimConfig { burst: Some(Burst { start_s: -1.0, duration_s: 2.0, factor: 8.0 }), ..base.clone() }, "burst.start_s"),
        ];
        for (cfg, field) in cases {
            let e = cfg.validate().unwrap_err();
            assert!(matches!(&e, SimError::InvalidConfig { field: f, .. } if *f == field), "{field}: {e}");
            assert!(e.to_string().contains(field), "{e}");
        }
    }

    #[test]
    fn camera_matches_hfov_and_config_round_trips_through_json() {
        let cfg = SimConfig::preset(WaterPreset::Clear, TrajectoryKind::Loop);
        let cam = cfg.camera();
        let reference = PinholeCamera::from_hfov(cfg.hfov_deg, cfg.width, cfg.height).unwrap();
        assert_eq!(cam, reference);
        let text = serde_json::to_string(&cfg).unwrap();
        let back: SimConfig = serde_json::from_str(&text).unwrap();
        assert_eq!(back, cfg);
        assert!(text.contains("\"water\":\"clear\"") && text.contains("\"trajectory\":\"loop\""), "{text}");
        // A sim.json written before the yo-yo profile existed reads as a flat survey.
        let mut old: serde_json::Value = serde_json::from_str(&text).unwrap();
        old.as_object_mut().unwrap().retain(|k, _| !k.starts_with("altitude_swing") && !k.starts_with("altitude_period"));
        let back: SimConfig = serde_json::from_value(old).unwrap();
        assert_eq!((back.altitude_swing_m, back.altitude_period_s), (0.0, 20.0));
        back.validate().unwrap();
        // Without the night options their keys are left out (sim.json as before them), and a
        // file without them reads as no glow, no snow, no burst.
        for key in ["lamp_backscatter", "snow_per_m3", "burst", "seabed_texture"] {
            assert!(!text.contains(key), "{text}");
        }
        assert_eq!((back.lamp_backscatter, back.snow_per_m3, back.burst, back.seabed_texture), (0.0, 0.0, None, 1.0));
        // With them they round-trip; a burst without a factor takes the default.
        let mut night = SimConfig { burst: Some(Burst { start_s: 2.0, duration_s: 5.0, factor: 4.0 }), ..cfg.clone() };
        night.apply_night();
        let text = serde_json::to_string(&night).unwrap();
        assert!(text.contains("\"burst\":{\"start_s\":2.0,\"duration_s\":5.0,\"factor\":4.0}") && text.contains("\"snow_per_m3\":150.0"), "{text}");
        assert_eq!(serde_json::from_str::<SimConfig>(&text).unwrap(), night);
        let b: Burst = serde_json::from_str(r#"{"start_s":1,"duration_s":3}"#).unwrap();
        assert_eq!(b.factor, 8.0);
    }

    #[test]
    fn burst_envelope_rises_holds_and_falls() {
        let b = Burst { start_s: 10.0, duration_s: 10.0, factor: 5.0 };
        let at = |t: f64| b.envelope(t);
        for (t, e) in [(0.0, 0.0), (10.0, 0.0), (11.0, 0.5), (12.0, 1.0), (15.0, 1.0), (18.0, 1.0), (19.0, 0.5), (20.0, 0.0), (30.0, 0.0)] {
            assert!((at(t) - e).abs() < 1e-12, "envelope({t}) = {} not {e}", at(t));
        }
        // Smooth: no jump anywhere, monotonic in the rise.
        let samples: Vec<f64> = (0..=2000).map(|k| at(9.0 + k as f64 * 0.006)).collect();
        assert!(samples.windows(2).all(|w| (w[1] - w[0]).abs() < 0.01));
        assert!(samples[167..=500].windows(2).all(|w| w[1] >= w[0]));
        assert_eq!((b.multiplier(5.0), b.multiplier(15.0), b.multiplier(11.0)), (1.0, 5.0, 3.0));
        // The frame medium: the base one outside, beta_D and beta_B times the factor in the
        // hold, the veiling light unchanged.
        let cfg = SimConfig { burst: Some(b), ..SimConfig::default() };
        let (base, hold) = (cfg.medium(), cfg.medium_at(15.0));
        assert_eq!(cfg.medium_at(9.9), base);
        assert_eq!(cfg.medium_at(20.0), base);
        for c in 0..3 {
            assert_eq!((hold.beta_d[c], hold.beta_b[c], hold.b_inf[c]), (base.beta_d[c] * 5.0, base.beta_b[c] * 5.0, base.b_inf[c]));
        }
        // Parsed from the command line (commas) or a sim: spec (colons).
        assert_eq!("3,4".parse::<Burst>().unwrap(), Burst { start_s: 3.0, duration_s: 4.0, factor: 8.0 });
        assert_eq!("3:4:2.5".parse::<Burst>().unwrap(), Burst { start_s: 3.0, duration_s: 4.0, factor: 2.5 });
        for bad in ["3", "3,4,5,6", "a,4", ""] {
            let e = bad.parse::<Burst>().unwrap_err();
            assert!(matches!(e, SimError::BadBurst { .. }) && e.to_string().contains(&format!("{bad:?}")), "{bad}: {e}");
        }
        assert_eq!(cfg.conditions(), "burst 10+10 s x5");
        assert_eq!(SimConfig::default().conditions(), "");
    }
}
