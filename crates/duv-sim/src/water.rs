//! Water and sensor: medium presets, the image formation model, sunlight and vehicle lamps,
//! vignetting and sensor noise.
//!
//! Magnitudes follow Jerlov water types (diffuse attenuation of the direct signal roughly
//! 0.1-1.5 /m): in clear oceanic water red is gone within a few metres and blue travels
//! furthest; coastal water (chlorophyll and dissolved organic matter absorb blue) transmits
//! green best and has a green veiling light; turbid harbour water scatters strongly, so
//! visibility is a few metres and the haze is bright and brown-green. `beta_B` differs from
//! `beta_D` per channel (Akkaynak and Treibitz's revised model).

use super::WaterPreset;
use duv_core::MediumParams;
use nalgebra::Vector3;

/// Medium coefficients of a preset under sunlight (R, G, B; 1/m; veiling light in [0, 1]).
pub fn preset_medium(water: WaterPreset) -> MediumParams {
    match water {
        WaterPreset::Clear => MediumParams { beta_d: [0.42, 0.095, 0.075], beta_b: [0.33, 0.075, 0.055], b_inf: [0.03, 0.22, 0.44] },
        WaterPreset::Coastal => MediumParams { beta_d: [0.62, 0.24, 0.34], beta_b: [0.48, 0.19, 0.27], b_inf: [0.06, 0.38, 0.30] },
        WaterPreset::Turbid => MediumParams { beta_d: [1.15, 0.55, 0.75], beta_b: [0.95, 0.47, 0.66], b_inf: [0.20, 0.40, 0.26] },
    }
}

/// With lamps (a deep dive, no sunlight) the veiling light is what the lamps scatter back: the
/// same colour, much darker.
pub const LAMP_VEILING_SCALE: f64 = 0.3;

/// The medium of a preset as used for images (and written to `medium.json`).
pub fn medium(water: WaterPreset, lamps: bool) -> MediumParams {
    let mut m = preset_medium(water);
    if lamps {
        for c in &mut m.b_inf {
            *c *= LAMP_VEILING_SCALE;
        }
    }
    m
}

/// Default max range: where the best-transmitted channel keeps about 0.5% of the signal,
/// capped at 40 m (beyond that the seabed is a few grey levels above the veiling light).
pub fn default_max_range_m(water: WaterPreset) -> f64 {
    match water {
        WaterPreset::Clear => 40.0,
        WaterPreset::Coastal => 22.0,
        WaterPreset::Turbid => 8.0,
    }
}

/// Colour of the downwelling sunlight at the seabed (the water column above has already
/// filtered it), the illuminant of `J` without lamps.
pub fn sunlight_rgb(water: WaterPreset) -> [f64; 3] {
    match water {
        WaterPreset::Clear => [0.80, 0.95, 1.0],
        WaterPreset::Coastal => [0.82, 0.97, 0.86],
        WaterPreset::Turbid => [0.86, 0.95, 0.78],
    }
}

/// The image formation model of §3.2: `I = J exp(-beta_D r) + B_inf (1 - exp(-beta_B r))` per
/// channel; `range_m = inf` gives pure veiling light.
#[inline]
pub fn form_image(j: [f64; 3], range_m: f64, m: &MediumParams) -> [f64; 3] {
    let mut out = [0.0; 3];
    for c in 0..3 {
        let direct = (-m.beta_d[c] * range_m).exp();
        let backscatter = 1.0 - (-m.beta_b[c] * range_m).exp();
        out[c] = j[c] * direct + m.b_inf[c] * backscatter;
    }
    out
}

/// Sunlight: light from above, slightly off vertical, with a sky-like ambient share.
#[derive(Clone, Copy, Debug)]
pub struct Sun {
    /// Unit vector towards the light, world frame.
    pub dir: Vector3<f64>,
    pub rgb: [f64; 3],
    pub ambient: f64,
    pub diffuse: f64,
}

impl Sun {
    pub fn new(water: WaterPreset) -> Self {
        Sun { dir: Vector3::new(0.30, 0.18, 1.0).normalize(), rgb: sunlight_rgb(water), ambient: 0.45, diffuse: 0.85 }
    }
    /// Irradiance factor (times albedo gives `J`) for a surface normal; `lit` is 0 in shadow.
    #[inline]
    pub fn irradiance(&self, normal: &Vector3<f64>, lit: f64) -> [f64; 3] {
        let k = self.ambient + self.diffuse * lit * normal.dot(&self.dir).max(0.0);
        [self.rgb[0] * k, self.rgb[1] * k, self.rgb[2] * k]
    }
}

/// One vehicle lamp, in the camera frame.
#[derive(Clone, Copy, Debug)]
pub struct Lamp {
    pub pos_in_cam: Vector3<f64>,
    pub dir_in_cam: Vector3<f64>,
    /// Radiant intensity per channel (irradiance at 1 m on axis, no water).
    pub rgb: [f64; 3],
    /// Cosines of the full-intensity and the zero-intensity cone half angles.
    pub cos_inner: f64,
    pub cos_outer: f64,
}

/// Two LED lamps beside and above the camera, toed in slightly and tilted down, with
/// inverse-square falloff, a soft cone, and attenuation along the lamp-to-seabed path (the
/// light reaching the seabed is already filtered: red fades with distance even in `J`).
#[derive(Clone, Debug)]
pub struct Lamps {
    pub lamps: [Lamp; 2],
}

impl Default for Lamps {
    fn default() -> Self {
        let lamp = |x: f64| Lamp {
            pos_in_cam: Vector3::new(x, -0.12, 0.05),
            dir_in_cam: Vector3::new(-x * 0.25, 0.12, 1.0).normalize(),
            rgb: [7.5, 7.2, 6.5],
            cos_inner: 28f64.to_radians().cos(),
            cos_outer: 60f64.to_radians().cos(),
        };
        Lamps { lamps: [lamp(0.35), lamp(-0.35)] }
    }
}

/// Lamps placed in the world for one frame.
#[derive(Clone, Copy, Debug)]
pub struct LampsInWorld {
    pos: [Vector3<f64>; 2],
    dir: [Vector3<f64>; 2],
    rgb: [[f64; 3]; 2],
    cos_inner: [f64; 2],
    cos_outer: [f64; 2],
}

impl Lamps {
    pub fn in_world(&self, world_from_cam: &duv_core::Se3) -> LampsInWorld {
        let p = |l: &Lamp| (world_from_cam * nalgebra::Point3::from(l.pos_in_cam)).coords;
        let d = |l: &Lamp| world_from_cam.rotation * l.dir_in_cam;
        let [a, b] = &self.lamps;
        LampsInWorld {
            pos: [p(a), p(b)],
            dir: [d(a), d(b)],
            rgb: [a.rgb, b.rgb],
            cos_inner: [a.cos_inner, b.cos_inner],
            cos_outer: [a.cos_outer, b.cos_outer],
        }
    }
}

impl LampsInWorld {
    /// Lamp `k` seen from `point`: the unit direction from the lamp, the distance, its square
    /// and the cone factor; `None` outside the cone. Shared by the seabed's, the particles' and
    /// the water's lighting.
    #[inline]
    fn falloff(&self, k: usize, point: &Vector3<f64>) -> Option<(Vector3<f64>, f64, f64, f64)> {
        let to_point = point - self.pos[k];
        let d2 = to_point.norm_squared().max(1e-4);
        let d = d2.sqrt();
        let l = to_point / d;
        let cone = super::noise::smoothstep(self.cos_outer[k], self.cos_inner[k], l.dot(&self.dir[k]));
        (cone > 0.0).then_some((l, d, d2, cone))
    }

    /// Irradiance factor at a surface point with its normal; `beta` attenuates the
    /// lamp-to-point path.
    #[inline]
    pub fn irradiance(&self, point: &Vector3<f64>, normal: &Vector3<f64>, beta: &[f64; 3]) -> [f64; 3] {
        let mut e = [0.0; 3];
        for k in 0..2 {
            let Some((l, d, d2, cone)) = self.falloff(k, point) else { continue };
            let lambert = (-l).dot(normal).max(0.0);
            if lambert <= 0.0 {
                continue;
            }
            let g = cone * lambert / d2;
            for c in 0..3 {
                e[c] += self.rgb[k][c] * g * (-beta[c] * d).exp();
            }
        }
        e
    }
}

/// Lamp-lit backscatter (single scattering of the lamps' light towards the camera): the ray is
/// integrated from this range (metres; nearer water lies between the lamps and the lens)...
pub const LAMP_SCATTER_NEAR_M: f64 = 0.05;
/// ...out to the hit or this range, whichever is nearer (metres; beyond it inverse-square falloff
/// and attenuation leave under 2 % of the glow even in clear water).
pub const LAMP_SCATTER_FAR_M: f64 = 4.0;
/// Intervals along the ray; their edges are spaced as `s^1.5`, denser near the camera where
/// the lamps' light is strongest (6 cm first, 36 cm last).
pub const LAMP_SCATTER_STEPS: usize = 16;
/// The share of the light scattered at a sample that goes back into the lens (1/sr: a
/// phase-function value near 180 degrees), chosen so that with strength 1 the glow in coastal
/// water adds about 30 grey levels (green) where the cones cross the view and nothing
/// saturates (the render tests hold it to this).
pub const LAMP_SCATTER_PHASE: f64 = 0.08;

/// Scattering coefficient per channel (1/m) of a water type whose backscatter coefficients are
/// `beta_b` (the preset's, or a burst's): the model's veiling light is `B_inf = (b / beta_B) E`
/// for an illuminant `E`, so `b = beta_B B_inf / E` with the sunlit preset's `B_inf` and
/// [`sunlight_rgb`]. It gives the lamps' glow the colour of the water (green-blue in coastal
/// water) and its strength (weak in clear, strong in turbid water).
pub fn scattering_per_m(water: WaterPreset, beta_b: &[f64; 3]) -> [f64; 3] {
    let (b_inf, sun) = (preset_medium(water).b_inf, sunlight_rgb(water));
    [beta_b[0] * b_inf[0] / sun[0], beta_b[1] * b_inf[1] / sun[1], beta_b[2] * b_inf[2] / sun[2]]
}

/// Edge `k` of the [`LAMP_SCATTER_STEPS`] intervals, metres.
#[inline]
pub fn lamp_scatter_edge_m(k: usize) -> f64 {
    let s = k as f64 / LAMP_SCATTER_STEPS as f64;
    LAMP_SCATTER_NEAR_M + (LAMP_SCATTER_FAR_M - LAMP_SCATTER_NEAR_M) * s * s.sqrt()
}

/// The lamps' glow along one ray as a function of range: entry `k` is the glow integrated from
/// [`LAMP_SCATTER_NEAR_M`] to edge `k + 1` (see [`LampsInWorld::scatter_profile`],
/// [`glow_at`]).
pub type GlowProfile = [[f32; 3]; LAMP_SCATTER_STEPS];

/// The glow of a profile up to `range_m` (the hit, or `inf`): linear within an interval (the
/// integrand taken constant over it), so continuous in range; 0 before
/// [`LAMP_SCATTER_NEAR_M`], the whole profile beyond [`LAMP_SCATTER_FAR_M`].
#[inline]
pub fn glow_at(profile: &GlowProfile, range_m: f64) -> [f64; 3] {
    let mut below = [0f32; 3];
    let mut a = LAMP_SCATTER_NEAR_M;
    if range_m.is_nan() || range_m <= a {
        return [0.0; 3];
    }
    for (k, cum) in profile.iter().enumerate() {
        let b = lamp_scatter_edge_m(k + 1);
        if range_m < b {
            let f = (range_m - a) / (b - a);
            return [0, 1, 2].map(|c| below[c] as f64 + f * (cum[c] - below[c]) as f64);
        }
        below = *cum;
        a = b;
    }
    below.map(f64::from)
}

impl LampsInWorld {
    /// Irradiance factor at a point that faces the lamps (a small particle: no Lambert term);
    /// `beta` attenuates the lamp-to-point path.
    #[inline]
    pub fn irradiance_facing(&self, point: &Vector3<f64>, beta: &[f64; 3]) -> [f64; 3] {
        let mut e = [0.0; 3];
        for k in 0..2 {
            let Some((_, d, d2, cone)) = self.falloff(k, point) else { continue };
            let g = cone / d2;
            for c in 0..3 {
                e[c] += self.rgb[k][c] * g * (-beta[c] * d).exp();
            }
        }
        e
    }

    /// Lamp light scattered back along the unit ray `dir` from `origin` (the camera centre),
    /// accumulated interval by interval: the sum over both lamps of
    /// `b I cone / d^2 exp(-beta_D (d + t)) dt` times [`LAMP_SCATTER_PHASE`], sampled at each
    /// interval's middle, `b` the scattering coefficient ([`scattering_per_m`]), `d` the
    /// lamp-to-sample distance and `t` the sample's range. [`glow_at`] reads it at a range.
    pub fn scatter_profile(&self, origin: &Vector3<f64>, dir: &Vector3<f64>, scattering_per_m: &[f64; 3], beta_d: &[f64; 3]) -> GlowProfile {
        let mut profile = [[0f32; 3]; LAMP_SCATTER_STEPS];
        let mut sum = [0.0; 3];
        let mut a = lamp_scatter_edge_m(0);
        for (k, cum) in profile.iter_mut().enumerate() {
            let b = lamp_scatter_edge_m(k + 1);
            let (t, dt) = (0.5 * (a + b), b - a);
            a = b;
            let p = origin + dir * t;
            for l in 0..2 {
                let Some((_, d, d2, cone)) = self.falloff(l, &p) else { continue };
                let g = cone / d2 * dt * LAMP_SCATTER_PHASE;
                for c in 0..3 {
                    sum[c] += scattering_per_m[c] * self.rgb[l][c] * g * (-beta_d[c] * (d + t)).exp();
                }
            }
            *cum = sum.map(|x| x as f32);
        }
        profile
    }
}

/// Per-pixel vignetting gain `1 - v rho^2`, `rho` the distance to the principal point over the
/// distance to the farthest corner.
pub fn vignetting_gains(width: usize, height: usize, cx: f64, cy: f64, strength: f64) -> Vec<f32> {
    let corner2 = [(0.0, 0.0), (width as f64 - 1.0, 0.0), (0.0, height as f64 - 1.0), (width as f64 - 1.0, height as f64 - 1.0)]
        .iter()
        .map(|(x, y)| (x - cx).powi(2) + (y - cy).powi(2))
        .fold(1e-12, f64::max);
    let mut out = Vec::with_capacity(width * height);
    for v in 0..height {
        for u in 0..width {
            let rho2 = ((u as f64 - cx).powi(2) + (v as f64 - cy).powi(2)) / corner2;
            out.push((1.0 - strength * rho2).max(0.0) as f32);
        }
    }
    out
}

/// Standard normal samples from a seeded stream (Box-Muller, both branches used).
#[derive(Clone, Debug)]
pub struct GaussianStream {
    rng: duv_core::rng::Rng,
    spare: Option<f64>,
}

impl GaussianStream {
    pub fn new(rng: duv_core::rng::Rng) -> Self {
        GaussianStream { rng, spare: None }
    }

    #[inline]
    pub fn sample(&mut self) -> f64 {
        if let Some(v) = self.spare.take() {
            return v;
        }
        let u1 = self.rng.uniform().max(1e-300);
        let u2 = self.rng.uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f64::consts::TAU * u2).sin_cos();
        self.spare = Some(r * s);
        r * c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_are_physically_ordered() {
        for w in [WaterPreset::Clear, WaterPreset::Coastal, WaterPreset::Turbid] {
            let m = preset_medium(w);
            for c in 0..3 {
                assert!((0.05..=1.5).contains(&m.beta_d[c]), "{w:?} {m:?}");
                assert!(m.beta_b[c] > 0.0 && m.beta_b[c] != m.beta_d[c]);
                assert!((0.0..=1.0).contains(&m.b_inf[c]));
            }
            // Red is attenuated most in every type.
            assert!(m.beta_d[0] > m.beta_d[1] && m.beta_d[0] > m.beta_d[2], "{w:?}");
        }
        let clear = preset_medium(WaterPreset::Clear);
        let coastal = preset_medium(WaterPreset::Coastal);
        let turbid = preset_medium(WaterPreset::Turbid);
        assert!(clear.b_inf[2] > clear.b_inf[1], "clear water looks blue");
        assert!(coastal.b_inf[1] > coastal.b_inf[2], "coastal water looks green");
        // Visibility shrinks from clear to turbid in the best channel.
        let best = |m: &MediumParams| m.beta_d.iter().cloned().fold(f64::INFINITY, f64::min);
        assert!(best(&clear) < best(&coastal) && best(&coastal) < best(&turbid));
        assert_eq!(medium(WaterPreset::Coastal, true).b_inf[1], coastal.b_inf[1] * LAMP_VEILING_SCALE);
    }

    #[test]
    fn image_formation_limits() {
        let m = preset_medium(WaterPreset::Coastal);
        let j = [0.6, 0.5, 0.4];
        assert_eq!(form_image(j, 0.0, &m), j);
        let far = form_image(j, f64::INFINITY, &m);
        assert_eq!(far, m.b_inf);
        let mid = form_image(j, 3.0, &m);
        for c in 0..3 {
            let expect = j[c] * (-m.beta_d[c] * 3.0).exp() + m.b_inf[c] * (1.0 - (-m.beta_b[c] * 3.0).exp());
            assert!((mid[c] - expect).abs() < 1e-15);
        }
    }

    #[test]
    fn lamps_fall_off_with_distance_and_outside_the_cone() {
        let lamps = Lamps::default().in_world(&duv_core::Se3::identity());
        let n = Vector3::new(0.0, 0.0, -1.0);
        let beta = [0.0; 3];
        let near = lamps.irradiance(&Vector3::new(0.0, 0.0, 1.0), &n, &beta)[1];
        let far = lamps.irradiance(&Vector3::new(0.0, 0.0, 2.0), &n, &beta)[1];
        assert!(near > 3.0 * far && far > 0.0, "{near} {far}");
        let aside = lamps.irradiance(&Vector3::new(5.0, 0.0, 0.5), &Vector3::new(-1.0, 0.0, 0.0), &beta)[1];
        assert_eq!(aside, 0.0);
        let mut gauss = GaussianStream::new(duv_core::rng::Rng::new(5));
        let xs: Vec<f64> = (0..20_000).map(|_| gauss.sample()).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05, "{mean} {var}");
        let g = vignetting_gains(5, 3, 2.0, 1.0, 0.4);
        assert_eq!(g[7], 1.0);
        assert!((g[0] - 0.6).abs() < 1e-6);
    }

    #[test]
    fn lamp_glow_grows_with_range_continuously_and_stops_at_the_cap() {
        let lamps = Lamps::default().in_world(&duv_core::Se3::identity());
        let m = preset_medium(WaterPreset::Coastal);
        let b = scattering_per_m(WaterPreset::Coastal, &m.beta_b);
        // Coastal water scatters green and blue more than red: the glow is the water's colour.
        assert!(b[1] > 2.0 * b[0] && b[2] > 2.0 * b[0], "{b:?}");
        let axis = Vector3::new(0.0, 0.1, 1.0).normalize();
        let profile = lamps.scatter_profile(&Vector3::zeros(), &axis, &b, &m.beta_d);
        assert_eq!(glow_at(&profile, 0.0), [0.0; 3]);
        assert_eq!(glow_at(&profile, LAMP_SCATTER_NEAR_M), [0.0; 3]);
        assert_eq!(glow_at(&profile, f64::INFINITY), glow_at(&profile, LAMP_SCATTER_FAR_M));
        let mut last = 0.0;
        for k in 1..=400 {
            let g = glow_at(&profile, k as f64 * 0.01)[1];
            assert!(g >= last && g - last < 0.004, "range {} m: {last} -> {g}", k as f64 * 0.01);
            last = g;
        }
        // Most of the glow comes from the first two metres; past 4 m nothing is added.
        let (two, four) = (glow_at(&profile, 2.0)[1], glow_at(&profile, 4.0)[1]);
        assert!(two > 0.7 * four && four > 0.05, "{two} {four}");
        // A particle facing the lamps is lit without a cosine; 1 m ahead on the axis both
        // lamps reach it.
        let e = lamps.irradiance_facing(&Vector3::new(0.0, 0.0, 1.0), &[0.0; 3]);
        assert!((e[1] - 2.0 * 7.2 / (0.35f64.powi(2) + 0.12f64.powi(2) + 0.95f64.powi(2))).abs() < 1e-9, "{e:?}");
        assert_eq!(lamps.irradiance_facing(&Vector3::new(0.0, 0.0, -1.0), &[0.0; 3]), [0.0; 3]);
    }
}
