//! `duv sim`: generate an underwater sequence with exact ground truth (TUM RGB-D layout plus
//! the water-free images, the medium, the config and the navigation sensors' `nav.csv`).

use anyhow::Context;
use duv_sim::{write_sequence_with, Burst, NavNoise, SimConfig, TrajectoryKind, WaterPreset};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SimArgs {
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// Water type.
    #[arg(long, value_enum, default_value_t = WaterPreset::Coastal)]
    water: WaterPreset,
    /// Vehicle path.
    #[arg(long, value_enum, default_value_t = TrajectoryKind::Survey)]
    trajectory: TrajectoryKind,
    /// Number of frames [default: 300 survey, 400 loop, 200 hover].
    #[arg(long)]
    frames: Option<usize>,
    /// Image width in pixels [default: 320].
    #[arg(long)]
    width: Option<usize>,
    /// Image height in pixels [default: 240].
    #[arg(long)]
    height: Option<usize>,
    /// Frame rate in frames per second [default: 10].
    #[arg(long)]
    fps: Option<f64>,
    /// Horizontal field of view in degrees [default: 70].
    #[arg(long)]
    hfov_deg: Option<f64>,
    /// The vehicle's speed along the path in m/s (drift speed for hover) [default: 0.5, hover
    /// 0.05].
    #[arg(long, value_name = "M_PER_S")]
    vehicle_speed: Option<f64>,
    /// Not an option of `duv sim`: `--speed` is the playback factor of `duv run` and `duv
    /// replay`; the generated vehicle's speed is --vehicle-speed.
    #[arg(long, hide = true, value_name = "M_PER_S")]
    speed: Option<f64>,
    /// Camera altitude above the large-scale seabed in metres [default: 2].
    #[arg(long)]
    altitude: Option<f64>,
    /// Yo-yo altitude profile: the altitude swings this far above and below --altitude, metres
    /// (one sine cycle every --altitude-period seconds) [default: 0, constant altitude].
    #[arg(long)]
    altitude_swing: Option<f64>,
    /// Period of the yo-yo altitude profile in seconds [default: 20].
    #[arg(long)]
    altitude_period: Option<f64>,
    /// Camera pitch below the horizontal in degrees [default: 40, hover 35].
    #[arg(long)]
    pitch_deg: Option<f64>,
    /// Multiplies the roll/pitch/yaw/heave wobble amplitudes (0 = none) [default: 1].
    #[arg(long)]
    wobble_scale: Option<f64>,
    /// Vehicle lamps instead of sunlight (deep dive: dark veiling light).
    #[arg(long)]
    lamps: bool,
    /// With --lamps: the lamps' light scattered back by the water in front of the camera, a
    /// glow where the beams cross the view that stays put in the image as the vehicle moves
    /// (breaks brightness constancy); 1 adds some 30 grey levels in coastal water, less in
    /// clear, more in turbid [default: 0, none].
    #[arg(long, value_name = "S")]
    lamp_backscatter: Option<f64>,
    /// Marine snow, particles per cubic metre: world-fixed specks 1-4 mm across drifting a few
    /// cm/s, drawn 0.15-3 m in front of the camera, lit by the lamps (near ones saturate) or
    /// dimly by the sun; in rgb only, not in clear or depth [default: 0, none].
    #[arg(long, value_name = "N")]
    snow: Option<f64>,
    /// Turbidity burst: beta_D and beta_B of every channel rise to FACTOR times (20 % rise,
    /// 60 % hold, 20 % fall) from START_S for DURATION_S seconds, so the view fades into the
    /// haze and returns; medium.json keeps the base medium [FACTOR default: 8].
    #[arg(long, value_name = "START_S,DURATION_S[,FACTOR]")]
    burst: Option<Burst>,
    /// Contrast of the seabed's texture around a mid sand tint, in [0, 1]: 0.1 is nearly
    /// featureless sand (the relief's shading stays; pipe and wreck keep theirs) [default: 1].
    #[arg(long, value_name = "C")]
    seabed_texture: Option<f64>,
    /// A lamp-lit night dive with marine snow: --lamps --lamp-backscatter 1 --snow 150, each
    /// still overridable (coastal loop at 320x240: mean grey 49, the lamp-lit seabed below a
    /// dark green glow, some 0.1 % of the pixels saturated by near snow).
    #[arg(long)]
    night: bool,
    /// Sensor noise standard deviation, fraction of full scale [default: 0.006].
    #[arg(long)]
    noise: Option<f64>,
    /// Vignetting strength in [0, 1] (gain at the corners is 1 - strength) [default: 0.3].
    #[arg(long)]
    vignetting: Option<f64>,
    /// Rays that hit nothing within this range see pure water, metres [default: per water].
    #[arg(long)]
    max_range: Option<f64>,
    /// Random seed of the scene, the wobble and the noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Do not write nav.csv (the simulated depth sensor, altimeter, DVL and AHRS), for a
    /// camera-only dataset; one left by an earlier run in --out is removed.
    #[arg(long)]
    no_nav: bool,
    /// Do not show a progress bar.
    #[arg(long)]
    no_progress: bool,
}

impl SimArgs {
    fn config(&self) -> anyhow::Result<SimConfig> {
        let mut cfg = SimConfig::preset(self.water, self.trajectory);
        if let Some(v) = self.frames {
            cfg.frames = v;
        }
        if let Some(v) = self.width {
            cfg.width = v;
        }
        if let Some(v) = self.height {
            cfg.height = v;
        }
        if let Some(v) = self.fps {
            cfg.fps = v;
        }
        if let Some(v) = self.hfov_deg {
            cfg.hfov_deg = v;
        }
        if self.speed.is_some() {
            anyhow::bail!("duv sim has no --speed (the playback factor of `duv run` and `duv replay`): the vehicle's speed in m/s is --vehicle-speed");
        }
        if let Some(v) = self.vehicle_speed {
            cfg.speed_mps = v;
        }
        if let Some(v) = self.altitude {
            cfg.altitude_m = v;
        }
        if let Some(v) = self.altitude_swing {
            cfg.altitude_swing_m = v;
        }
        if let Some(v) = self.altitude_period {
            cfg.altitude_period_s = v;
        }
        if let Some(v) = self.pitch_deg {
            cfg.pitch_down_deg = v;
        }
        if let Some(k) = self.wobble_scale {
            anyhow::ensure!(k.is_finite() && k >= 0.0, "--wobble-scale must be a finite non-negative factor, got {k}");
            cfg.wobble = cfg.wobble.scaled(k);
        }
        if self.night {
            cfg.apply_night();
        }
        cfg.lamps |= self.lamps;
        if let Some(v) = self.lamp_backscatter {
            cfg.lamp_backscatter = v;
        }
        if let Some(v) = self.snow {
            cfg.snow_per_m3 = v;
        }
        cfg.burst = self.burst;
        if let Some(v) = self.seabed_texture {
            cfg.seabed_texture = v;
        }
        if let Some(v) = self.noise {
            cfg.noise_sigma = v;
        }
        if let Some(v) = self.vignetting {
            cfg.vignetting = v;
        }
        if let Some(v) = self.max_range {
            cfg.max_range_m = v;
        }
        cfg.seed = self.seed;
        Ok(cfg)
    }
}

pub fn run(args: SimArgs) -> anyhow::Result<()> {
    let cfg = args.config()?;
    let nav = (!args.no_nav).then(NavNoise::default);
    let report = write_sequence_with(&cfg, &args.out, !args.no_progress, nav.as_ref()).with_context(|| format!("generating a sequence into {}", args.out.display()))?;
    println!(
        "wrote {} frames ({}x{}, {} water, {}{}) to {} in {:.2} s: {:.1} frames/s, path {:.2} m",
        report.frames,
        cfg.width,
        cfg.height,
        cfg.water,
        cfg.trajectory,
        match cfg.conditions() {
            c if c.is_empty() => c,
            c => format!(", {c}"),
        },
        report.out_dir.display(),
        report.seconds,
        report.frames_per_sec,
        report.path_length_m
    );
    Ok(())
}
