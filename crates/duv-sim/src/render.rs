//! Frame rendering: one ray per pixel through the scene, lighting for `J`, the water model for
//! `I` (with the frame's medium, a turbidity burst included), the lamps' light scattered back
//! along the ray, marine snow composited over it, then vignetting, sensor noise and 8-bit
//! quantisation. Rows render in parallel; the noise of a row comes from its own seeded stream
//! and the snow from a hashed grid, so the result does not depend on the thread schedule.

use super::scene::{Hit, Scene};
use super::snow::{self, SnowField, SnowSplat};
use super::trajectory::{self, PlanarPlan};
use super::water::{self, GlowProfile, Lamps, LampsInWorld, Sun};
use super::{SimConfig, SimError};
use duv_core::frame::unit_to_u8;
use duv_core::rng::Rng;
use duv_core::{ImageRgb8, MediumParams, PinholeCamera, PlaneF32, Se3, StampedPose, Timestamp};
use nalgebra::Vector3;
use rayon::prelude::*;

/// One rendered frame with its ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct SimFrame {
    pub t_ns: Timestamp,
    pub world_from_cam: Se3,
    /// What the camera records: water, vignetting, noise.
    pub rgb: ImageRgb8,
    /// The same view without water (`J`, same lighting): the restoration target.
    pub clear: ImageRgb8,
    /// Depth along the optical axis, metres; 0 where the ray hit nothing within the max range.
    pub depth_m: PlaneF32,
    /// Euclidean distance from the camera centre along the ray, metres; 0 where nothing was hit.
    pub range_m: PlaneF32,
}

/// Renders the frames of one configuration: the scene, trajectory and camera are built once.
pub struct SimRenderer {
    cfg: SimConfig,
    camera: PinholeCamera,
    medium: MediumParams,
    scene: Scene,
    poses: Vec<StampedPose>,
    /// Unit viewing ray of every pixel, camera frame, row-major.
    rays_in_cam: Vec<Vector3<f64>>,
    vignette: Vec<f32>,
    sun: Sun,
    lamps: Option<Lamps>,
    /// The lamps in the camera frame (they move with it), for the backscatter and the snow.
    lamps_in_cam: Option<LampsInWorld>,
    /// The lamps' glow along every pixel's ray in the base medium (it moves with the camera,
    /// so it is the same in every frame outside a burst), row-major; empty without the glow
    /// or when it would exceed [`GLOW_CACHE_MAX_BYTES`] (then computed per frame).
    glow_cache: Vec<GlowProfile>,
    snow: Option<SnowField>,
}

/// Largest per-pixel glow table kept between frames (bytes): 64 MiB, 640x480 and a bit more.
const GLOW_CACHE_MAX_BYTES: usize = 64 << 20;

/// A Lambertian sphere lit from (nearly) the camera's side returns this share of what a disc
/// facing the light would: its mean cosine over the visible hemisphere.
const SNOW_LAMP_SHARE: f64 = 2.0 / 3.0;
/// Under sunlight a particle's `J` is its albedo times the sun's ambient share plus this share
/// of the direct light (a sphere lit from above, seen from the side).
const SNOW_SUN_SHARE: f64 = 0.25;
/// A particle's light is kept up to this multiple of full scale before vignetting and the
/// sensor clip it: a near lamp-lit particle saturates even in the image corners.
const SNOW_MAX_RADIANCE: f64 = 1.5;

/// Fine heightfield margin around the path per pixel of focal length, metres: at that range
/// a 12 cm ripple seen at the usual grazing angles spans less than two pixels.
const FINE_MARGIN_PER_FX: f64 = 0.035;

/// Stream id of the sensor noise (mixed with the seed, the frame and the row).
const NOISE_STREAM: u64 = 0x4E01_5E00;

impl SimRenderer {
    pub fn new(cfg: &SimConfig) -> Result<Self, SimError> {
        cfg.validate()?;
        let camera = cfg.camera();
        let plan: PlanarPlan = trajectory::plan_planar(cfg);
        // Fine relief out to where ripples fade below the pixel footprint, coarse out to max
        // range.
        let fine_margin = (FINE_MARGIN_PER_FX * camera.fx).clamp(2.0, 20.0).min(cfg.max_range_m) + 1.0;
        let coarse_margin = cfg.max_range_m + 1.0;
        let started = std::time::Instant::now();
        let mut scene = Scene::new(cfg.seed, &plan, fine_margin, coarse_margin)?;
        scene.set_seabed_texture(cfg.seabed_texture);
        tracing::debug!(secs = started.elapsed().as_secs_f64(), "sim: seabed built");
        let poses = trajectory::poses(cfg, &plan, |x, y| scene.ground_reference(x, y));
        // Pinhole without distortion: the ray through pixel (u, v) in closed form.
        let mut rays_in_cam = Vec::with_capacity(cfg.width * cfg.height);
        for v in 0..cfg.height {
            for u in 0..cfg.width {
                rays_in_cam.push(Vector3::new((u as f64 - camera.cx) / camera.fx, (v as f64 - camera.cy) / camera.fy, 1.0).normalize());
            }
        }
        let vignette = water::vignetting_gains(cfg.width, cfg.height, camera.cx, camera.cy, cfg.vignetting);
        let lamps_in_cam = cfg.lamps.then(|| Lamps::default().in_world(&Se3::identity()));
        let glow_cache = match &lamps_in_cam {
            Some(l) if cfg.lamp_backscatter > 0.0 && rays_in_cam.len() * std::mem::size_of::<GlowProfile>() <= GLOW_CACHE_MAX_BYTES => {
                let m = cfg.medium();
                let scattering = water::scattering_per_m(cfg.water, &m.beta_b);
                rays_in_cam.par_iter().map(|ray| l.scatter_profile(&Vector3::zeros(), ray, &scattering, &m.beta_d)).collect()
            }
            _ => Vec::new(),
        };
        Ok(SimRenderer {
            cfg: cfg.clone(),
            camera,
            medium: cfg.medium(),
            scene,
            poses,
            rays_in_cam,
            vignette,
            sun: Sun::new(cfg.water),
            lamps: cfg.lamps.then(Lamps::default),
            lamps_in_cam,
            glow_cache,
            snow: (cfg.snow_per_m3 > 0.0).then(|| SnowField::new(cfg.seed, cfg.snow_per_m3)),
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Ground-truth pose of frame `i` (`world_from_cam`). Panics if `i >= len()`.
    pub fn pose(&self, i: usize) -> StampedPose {
        self.poses[i]
    }

    pub fn poses(&self) -> &[StampedPose] {
        &self.poses
    }

    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    pub fn medium(&self) -> &MediumParams {
        &self.medium
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Length of the camera path, metres.
    pub fn path_length_m(&self) -> f64 {
        trajectory::path_length_m(&self.poses)
    }

    /// Height of the camera of frame `i` above what lies straight below it, metres.
    pub fn altitude_m(&self, i: usize) -> Option<f64> {
        self.scene.altitude_below(&self.poses[i].world_from_cam.translation.vector)
    }

    /// `J` at a hit: albedo times the sunlight (with structure shadows) or the lamps.
    /// Known bias: distant seabed comes out brighter than the surface it covers (+4.4 % at
    /// 4-6 m, +6.1 % at 6-8 m on the clear survey at 320x240 against a 4x finer render boxed
    /// down), since the footprint-filtered normal shades rough ground brighter than its facets
    /// and some unresolved albedo detail loses its mean; see the README's mapping figures.
    fn shade(&self, hit: &Hit, ray_dir: &Vector3<f64>, lamps: Option<&LampsInWorld>, medium: &MediumParams) -> [f64; 3] {
        // Footprint of a pixel on the surface: wider at range and at grazing incidence.
        let cos_incidence = hit.normal.dot(ray_dir).abs().max(0.1);
        let footprint = hit.t / self.camera.fx / cos_incidence.powf(0.75);
        let albedo = self.scene.albedo(hit, footprint);
        let irradiance = match lamps {
            Some(l) => l.irradiance(&hit.point, &hit.normal, &medium.beta_d),
            None => {
                let lit = if hit.normal.dot(&self.sun.dir) > 0.0 && self.scene.structure_blocks(&(hit.point + hit.normal * 1e-4), &self.sun.dir, 30.0) {
                    0.0
                } else {
                    1.0
                };
                self.sun.irradiance(&hit.normal, lit)
            }
        };
        [(albedo[0] * irradiance[0]).clamp(0.0, 1.0), (albedo[1] * irradiance[1]).clamp(0.0, 1.0), (albedo[2] * irradiance[2]).clamp(0.0, 1.0)]
    }

    /// True depth along the optical axis (metres; 0 where the ray hits nothing within the max
    /// range) seen from any pose of this camera, without shading the image (`render(i)`'s
    /// `depth_m` for frame `i`'s pose).
    pub fn depth_at(&self, world_from_cam: &Se3) -> PlaneF32 {
        let rotation = world_from_cam.rotation.to_rotation_matrix();
        let origin = world_from_cam.translation.vector;
        let (w, h) = (self.cfg.width, self.cfg.height);
        let pixel_angle = 1.0 / self.camera.fx;
        let mut depth = vec![0f32; w * h];
        depth.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
            for (u, d) in row.iter_mut().enumerate() {
                let ray_in_cam = &self.rays_in_cam[v * w + u];
                if let Some(hit) = self.scene.intersect(&origin, &(rotation * ray_in_cam), self.cfg.max_range_m, pixel_angle) {
                    *d = (hit.t * ray_in_cam.z) as f32;
                }
            }
        });
        PlaneF32 { width: w, height: h, data: depth }
    }

    /// Time of frame `i`, seconds from the first.
    fn t_s(&self, i: usize) -> f64 {
        i as f64 / self.cfg.fps
    }

    /// The lamps when their glow is on (lamps and a backscatter strength above 0).
    fn glowing_lamps(&self) -> Option<&LampsInWorld> {
        self.lamps_in_cam.as_ref().filter(|_| self.cfg.lamp_backscatter > 0.0)
    }

    /// Adds the lamps' glow along the camera-frame ray `ray_in_cam` up to `range_m` to
    /// `image`, times the configured strength; `cached` is the ray's profile in `medium` when
    /// the cache holds it.
    fn add_glow(&self, image: &mut [f64; 3], lamps: &LampsInWorld, ray_in_cam: &Vector3<f64>, range_m: f64, medium: &MediumParams, cached: Option<&GlowProfile>) {
        let fresh;
        let profile = match cached {
            Some(p) => p,
            None => {
                fresh = lamps.scatter_profile(&Vector3::zeros(), ray_in_cam, &water::scattering_per_m(self.cfg.water, &medium.beta_b), &medium.beta_d);
                &fresh
            }
        };
        let glow = water::glow_at(profile, range_m);
        for c in 0..3 {
            image[c] += glow[c] * self.cfg.lamp_backscatter;
        }
    }

    /// The marine snow particles frame `i` sees, farthest first, with their world positions at
    /// the frame's time (empty without snow).
    pub fn snow(&self, i: usize) -> Vec<SnowSplat> {
        match &self.snow {
            Some(field) => field.visible(&self.camera, &self.poses[i].world_from_cam, self.t_s(i), self.cfg.max_range_m),
            None => Vec::new(),
        }
    }

    /// What a particle looks like through the water: its albedo times the lamps' light at it
    /// (or the sunlight's ambient share), attenuated and veiled over its range, plus the lamps'
    /// glow in front of it; clamped to [`SNOW_MAX_RADIANCE`] (not to full scale like the
    /// seabed's `J`: a particle is not in `clear`, and near ones outshine the sensor).
    fn snow_colour(&self, splat: &SnowSplat, medium: &MediumParams) -> [f64; 3] {
        let e = match &self.lamps_in_cam {
            Some(l) => l.irradiance_facing(&splat.p_in_cam, &medium.beta_d).map(|e| e * SNOW_LAMP_SHARE),
            None => self.sun.irradiance(&self.sun.dir, SNOW_SUN_SHARE),
        };
        let j = e.map(|e| splat.particle.albedo * e);
        let mut image = water::form_image(j, splat.range_m, medium);
        if let Some(lamps) = self.glowing_lamps() {
            self.add_glow(&mut image, lamps, &(splat.p_in_cam / splat.range_m), splat.range_m, medium, None);
        }
        image.map(|x| x.min(SNOW_MAX_RADIANCE))
    }

    /// Renders frame `i`. Panics if `i >= len()`.
    pub fn render(&self, i: usize) -> SimFrame {
        let pose = self.poses[i];
        let world_from_cam = pose.world_from_cam;
        let rotation = world_from_cam.rotation.to_rotation_matrix();
        let origin = world_from_cam.translation.vector;
        let lamps = self.lamps.as_ref().map(|l| l.in_world(&world_from_cam));
        let medium = self.cfg.medium_at(self.t_s(i));
        let (w, h) = (self.cfg.width, self.cfg.height);
        let sigma = self.cfg.noise_sigma;
        let max_range = self.cfg.max_range_m;
        let pixel_angle = 1.0 / self.camera.fx;
        let glowing = self.glowing_lamps();
        // The cached glow is the base medium's: outside a burst.
        let glow_cache = (!self.glow_cache.is_empty() && medium == self.medium).then_some(&self.glow_cache);
        let snow: Vec<(SnowSplat, [f64; 3])> = self.snow(i).into_iter().map(|s| (s, self.snow_colour(&s, &medium))).collect();
        let mut rgb = vec![0u8; w * h * 3];
        let mut clear = vec![0u8; w * h * 3];
        let mut depth = vec![0f32; w * h];
        let mut range = vec![0f32; w * h];
        rgb.par_chunks_mut(w * 3)
            .zip(clear.par_chunks_mut(w * 3))
            .zip(depth.par_chunks_mut(w))
            .zip(range.par_chunks_mut(w))
            .enumerate()
            .for_each(|(v, (((rgb_row, clear_row), depth_row), range_row))| {
                let mut gauss = water::GaussianStream::new(Rng::derive(self.cfg.seed ^ NOISE_STREAM, ((i as u64) << 24) | v as u64));
                // What reaches the lens (before vignetting and noise) and the hit range.
                let mut images: Vec<([f64; 3], f64)> = Vec::with_capacity(w);
                for u in 0..w {
                    let k = v * w + u;
                    let ray_in_cam = &self.rays_in_cam[k];
                    let dir = rotation * ray_in_cam;
                    let (j, r) = match self.scene.intersect(&origin, &dir, max_range, pixel_angle) {
                        Some(hit) => {
                            let j = self.shade(&hit, &dir, lamps.as_ref(), &medium);
                            depth_row[u] = (hit.t * ray_in_cam.z) as f32;
                            range_row[u] = hit.t as f32;
                            (j, hit.t)
                        }
                        None => ([0.0; 3], f64::INFINITY),
                    };
                    let mut image = water::form_image(j, r, &medium);
                    if let Some(lamps) = glowing {
                        self.add_glow(&mut image, lamps, ray_in_cam, r, &medium, glow_cache.map(|g| &g[k]));
                    }
                    for c in 0..3 {
                        clear_row[u * 3 + c] = unit_to_u8(j[c] as f32);
                    }
                    images.push((image, r));
                }
                // Snow in front of the seabed, back to front.
                let vf = v as f64;
                for (splat, colour) in &snow {
                    let reach = splat.radius_px + 0.5;
                    if (vf - splat.v).abs() > reach {
                        continue;
                    }
                    let u0 = ((splat.u - reach).ceil() as i64).max(0);
                    let u1 = ((splat.u + reach).floor() as i64).min(w as i64 - 1);
                    for u in u0..=u1 {
                        let (image, r) = &mut images[u as usize];
                        if splat.range_m >= *r {
                            continue;
                        }
                        let a = snow::coverage(splat, u as f64, vf);
                        if a > 0.0 {
                            for c in 0..3 {
                                image[c] += a * (colour[c] - image[c]);
                            }
                        }
                    }
                }
                for (u, (image, _)) in images.iter().enumerate() {
                    let gain = self.vignette[v * w + u] as f64;
                    let noise = if sigma > 0.0 {
                        [gauss.sample() * sigma, gauss.sample() * sigma, gauss.sample() * sigma]
                    } else {
                        [0.0; 3]
                    };
                    for c in 0..3 {
                        rgb_row[u * 3 + c] = unit_to_u8((image[c] * gain + noise[c]) as f32);
                    }
                }
            });
        SimFrame {
            t_ns: pose.t_ns,
            world_from_cam,
            rgb: ImageRgb8 { width: w, height: h, data: rgb },
            clear: ImageRgb8 { width: w, height: h, data: clear },
            depth_m: PlaneF32 { width: w, height: h, data: depth },
            range_m: PlaneF32 { width: w, height: h, data: range },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Surface;
    use crate::{TrajectoryKind, WaterPreset};

    /// Fractions of the pixels of frame `i` that see the pipe and the wreck.
    fn structure_fractions(r: &SimRenderer, i: usize) -> (f64, f64) {
        let pose = r.pose(i).world_from_cam;
        let (mut pipe, mut wreck) = (0, 0);
        for ray in &r.rays_in_cam {
            let dir = pose.rotation * ray;
            match r.scene.intersect(&pose.translation.vector, &dir, r.cfg.max_range_m, 0.0).map(|h| h.surface) {
                Some(Surface::Pipe { .. }) => pipe += 1,
                Some(Surface::Wreck { .. }) => wreck += 1,
                _ => {}
            }
        }
        let n = r.rays_in_cam.len() as f64;
        (pipe as f64 / n, wreck as f64 / n)
    }

    #[test]
    fn pipe_and_wreck_come_into_view_on_every_trajectory() {
        for kind in [TrajectoryKind::Survey, TrajectoryKind::Loop, TrajectoryKind::Hover] {
            let cfg = SimConfig { width: 40, height: 30, max_range_m: 12.0, ..SimConfig::preset(WaterPreset::Clear, kind) };
            let r = SimRenderer::new(&cfg).unwrap();
            let step = (r.len() / 12).max(1);
            let seen: Vec<(f64, f64)> = (0..r.len()).step_by(step).map(|i| structure_fractions(&r, i)).collect();
            let best_pipe = seen.iter().map(|s| s.0).fold(0.0, f64::max);
            let best_wreck = seen.iter().map(|s| s.1).fold(0.0, f64::max);
            assert!(best_pipe > 0.03, "{kind:?}: pipe covers at most {best_pipe} of a frame");
            assert!(best_wreck > 0.03, "{kind:?}: wreck covers at most {best_wreck} of a frame");
            if kind == TrajectoryKind::Loop {
                // Seen at the start and again at the end: a loop-closure landmark.
                assert!(structure_fractions(&r, 0).1 > 0.01 && structure_fractions(&r, r.len() - 1).1 > 0.01);
            }
        }
    }

    #[test]
    fn lamps_light_the_near_field_and_sunlight_is_even() {
        let base = SimConfig { frames: 1, width: 48, height: 36, noise_sigma: 0.0, vignetting: 0.0, max_range_m: 10.0, ..SimConfig::default() };
        let sun = SimRenderer::new(&base).unwrap().render(0);
        let lamps = SimRenderer::new(&SimConfig { lamps: true, ..base.clone() }).unwrap().render(0);
        let row_mean = |img: &ImageRgb8, y: usize| (0..img.width).map(|x| img.pixel(x, y)[1] as f64).sum::<f64>() / img.width as f64;
        // With lamps J falls off with distance: the near (bottom) rows are much brighter than
        // the far (top) ones; under the sun J hardly depends on range.
        let (near, far) = (35, 8);
        assert!(row_mean(&lamps.clear, near) > 3.0 * row_mean(&lamps.clear, far).max(1.0), "lamps {} vs {}", row_mean(&lamps.clear, near), row_mean(&lamps.clear, far));
        assert!(row_mean(&sun.clear, far) > 0.5 * row_mean(&sun.clear, near));
        // The veiling light is darker on a lamp-lit dive.
        assert!(SimConfig { lamps: true, ..base.clone() }.medium().b_inf[1] < base.medium().b_inf[1]);
    }

    /// A small, noiseless, unvignetted one-frame config.
    fn small(water: WaterPreset) -> SimConfig {
        SimConfig { frames: 3, width: 48, height: 36, noise_sigma: 0.0, vignetting: 0.0, max_range_m: 10.0, ..SimConfig::preset(water, TrajectoryKind::Survey) }
    }

    /// Green channel of an image, as numbers.
    fn green(img: &ImageRgb8) -> Vec<f64> {
        img.data.chunks(3).map(|p| p[1] as f64).collect()
    }

    fn mean(v: &[f64]) -> f64 {
        v.iter().sum::<f64>() / v.len() as f64
    }

    fn std_dev(v: &[f64]) -> f64 {
        let m = mean(v);
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len() as f64).sqrt()
    }

    #[test]
    fn lamp_glow_is_off_at_strength_0_and_lights_the_water_inside_the_cones() {
        let lamps = SimConfig { lamps: true, ..small(WaterPreset::Coastal) };
        let off = SimRenderer::new(&lamps).unwrap().render(0);
        // Strength 0 is the uniform veiling light of the model, nothing added.
        let m = lamps.medium();
        for k in 0..48 * 36 {
            let r = if off.range_m.data[k] > 0.0 { off.range_m.data[k] as f64 } else { f64::INFINITY };
            let j = [0, 1, 2].map(|c| off.clear.data[k * 3 + c] as f64 / 255.0);
            let expected = water::form_image(j, r, &m);
            for (c, e) in expected.iter().enumerate() {
                assert!((off.rgb.data[k * 3 + c] as f64 / 255.0 - e).abs() <= 1.0 / 255.0 + 1e-9, "pixel {k} channel {c}");
            }
        }
        let on = SimRenderer::new(&SimConfig { lamp_backscatter: 1.0, ..lamps.clone() }).unwrap().render(0);
        assert_eq!((&on.clear, &on.depth_m, &on.range_m), (&off.clear, &off.depth_m, &off.range_m), "the glow is in rgb only");
        let glow: Vec<f64> = green(&on.rgb).iter().zip(green(&off.rgb)).map(|(a, b)| a - b).collect();
        // Strength 1 in coastal water: a few tens of grey levels, nothing saturated.
        let g = mean(&glow);
        assert!((15.0..45.0).contains(&g), "mean glow {g} levels");
        assert!(glow.iter().all(|&d| d >= 0.0) && on.rgb.data.iter().all(|&v| v < 255));
        // Twice the strength, about twice the glow.
        let twice = SimRenderer::new(&SimConfig { lamp_backscatter: 2.0, ..lamps.clone() }).unwrap().render(0);
        let g2 = mean(&green(&twice.rgb)) - mean(&green(&off.rgb));
        assert!((g2 / g - 2.0).abs() < 0.1, "{g2} vs {g}");

        // A 150-degree view looking level: of the rays that see open water (no seabed), those
        // whose samples from 1 m on lie (nearly) inside a lamp's inner cone glow; those whose
        // samples all lie outside both outer cones stay exactly as without the glow.
        let wide = SimConfig { hfov_deg: 150.0, pitch_down_deg: 0.0, ..lamps.clone() };
        let off = SimRenderer::new(&wide).unwrap();
        let on = SimRenderer::new(&SimConfig { lamp_backscatter: 1.0, ..wide }).unwrap();
        let (off, rays, on) = (off.render(0), &on.rays_in_cam, on.render(0));
        let cone = |ray: &Vector3<f64>, t: f64| {
            Lamps::default().lamps.iter().map(|l| {
                let to = ray * t - l.pos_in_cam;
                crate::noise::smoothstep(l.cos_outer, l.cos_inner, to.normalize().dot(&l.dir_in_cam))
            })
            .fold(0.0, f64::max)
        };
        let (mut inside, mut outside) = (Vec::new(), Vec::new());
        for (k, ray) in rays.iter().enumerate() {
            if off.range_m.data[k] > 0.0 {
                continue;
            }
            let samples: Vec<(f64, f64)> = (0..water::LAMP_SCATTER_STEPS)
                .map(|i| {
                    let t = 0.5 * (water::lamp_scatter_edge_m(i) + water::lamp_scatter_edge_m(i + 1));
                    (t, cone(ray, t))
                })
                .collect();
            let glow = on.rgb.data[k * 3 + 1] as f64 - off.rgb.data[k * 3 + 1] as f64;
            if samples.iter().all(|&(t, c)| t < 1.0 || c >= 0.9) {
                inside.push(glow);
            } else if samples.iter().all(|&(_, c)| c == 0.0) {
                outside.push(glow);
            }
        }
        assert!(inside.len() >= 10 && outside.len() >= 10, "{} inside, {} outside", inside.len(), outside.len());
        let (gi, go) = (mean(&inside), mean(&outside));
        assert!(gi > 20.0 && go == 0.0, "glow inside the cones {gi} levels, outside {go}");
    }

    #[test]
    fn lamp_glow_is_fixed_in_the_image_and_cached_glow_matches_fresh() {
        // Sky-only pixels (no hit) see the full glow: the same in every frame as the vehicle
        // moves, since the lamps move with the camera.
        let cfg = SimConfig { lamps: true, lamp_backscatter: 1.0, pitch_down_deg: 0.0, ..small(WaterPreset::Coastal) };
        let r = SimRenderer::new(&cfg).unwrap();
        let (a, b) = (r.render(0), r.render(2));
        let top: Vec<usize> = (0..48 * 4).filter(|&k| a.range_m.data[k] == 0.0 && b.range_m.data[k] == 0.0).collect();
        assert!(top.len() > 48, "{} sky pixels", top.len());
        for &k in &top {
            assert_eq!(a.rgb.data[k * 3..k * 3 + 3], b.rgb.data[k * 3..k * 3 + 3], "pixel {k}");
        }
        // The per-pixel cache is the fresh profile of the same ray.
        let l = r.lamps_in_cam.as_ref().unwrap();
        let m = cfg.medium();
        for k in [0, 700, 48 * 36 - 1] {
            let fresh = l.scatter_profile(&Vector3::zeros(), &r.rays_in_cam[k], &water::scattering_per_m(cfg.water, &m.beta_b), &m.beta_d);
            assert_eq!(fresh, r.glow_cache[k]);
        }
    }

    /// Pixels whose rgb differs by more than 2 levels in some channel.
    fn changed(a: &ImageRgb8, b: &ImageRgb8) -> Vec<usize> {
        (0..a.width * a.height).filter(|&k| (0..3).any(|c| (a.data[k * 3 + c] as i32 - b.data[k * 3 + c] as i32).abs() > 2)).collect()
    }

    #[test]
    fn marine_snow_is_in_rgb_only_scales_with_density_and_shines_under_lamps() {
        for lamps in [false, true] {
            let base = SimConfig { lamps, width: 96, height: 72, ..small(WaterPreset::Coastal) };
            let none = SimRenderer::new(&base).unwrap().render(1);
            let r150 = SimRenderer::new(&SimConfig { snow_per_m3: 150.0, ..base.clone() }).unwrap();
            let r600 = SimRenderer::new(&SimConfig { snow_per_m3: 600.0, ..base.clone() }).unwrap();
            let (s150, s600) = (r150.render(1), r600.render(1));
            for s in [&s150, &s600] {
                assert_eq!((&s.clear, &s.depth_m, &s.range_m), (&none.clear, &none.depth_m, &none.range_m), "snow is water, not scene");
            }
            let (n150, n600) = (r150.snow(1).len(), r600.snow(1).len());
            // The frustum from 0.15 to 3 m holds about 13 m^3: some 2000 particles at 150/m^3.
            assert!((1200..3000).contains(&n150), "{n150} particles");
            let ratio = n600 as f64 / n150 as f64;
            assert!((3.5..4.5).contains(&ratio), "4x the density, {ratio}x the particles");
            let (c150, c600) = (changed(&s150.rgb, &none.rgb), changed(&s600.rgb, &none.rgb));
            assert!(c150.len() > 20 && c600.len() > 2 * c150.len(), "lamps {lamps}: {} and {} pixels changed", c150.len(), c600.len());
            // Every changed pixel is covered by a particle nearer than the seabed there.
            let splats = r150.snow(1);
            for &k in &c150 {
                let (u, v) = ((k % 96) as f64, (k / 96) as f64);
                let seabed = if none.range_m.data[k] > 0.0 { none.range_m.data[k] as f64 } else { f64::INFINITY };
                assert!(splats.iter().any(|s| s.range_m < seabed && snow::coverage(s, u, v) > 0.0), "lamps {lamps}: pixel {k} changed with no particle on it");
            }
            // Lamp-lit particles shine (the nearest saturate); in sunlight they are dim specks.
            let rise: Vec<f64> = c150.iter().map(|&k| s150.rgb.data[k * 3 + 1] as f64 - none.rgb.data[k * 3 + 1] as f64).collect();
            let saturated = c150.iter().filter(|&&k| s150.rgb.data[k * 3 + 1] == 255).count();
            // (Most particles are under a pixel at 96x72: their mean rise is small.)
            let mut top = rise.clone();
            top.sort_by(|a, b| b.total_cmp(a));
            let (mean_rise, top_rise) = (mean(&rise), mean(&top[..10]));
            if lamps {
                assert!(mean_rise > 6.0 && top_rise > 100.0 && saturated > 0, "lamp-lit snow: rise {mean_rise} levels, top ten {top_rise}, {saturated} saturated");
            } else {
                assert!(mean_rise < 5.0 && top_rise < 40.0 && saturated == 0, "sunlit snow: rise {mean_rise} levels, top ten {top_rise}, {saturated} saturated");
            }
        }
    }

    #[test]
    fn seabed_texture_lowers_the_seabed_contrast_and_keeps_its_tint() {
        // Detail energy (mean absolute step between neighbouring pixels, green channel of the
        // image without water) falls with the texture; the mean tint stays; 1 is as before.
        let base = SimConfig { width: 96, height: 72, ..small(WaterPreset::Coastal) };
        let steps = |texture: f64| {
            let r = SimRenderer::new(&SimConfig { seabed_texture: texture, ..base.clone() }).unwrap();
            let f = r.render(1);
            let g = green(&f.clear);
            let d: Vec<f64> = g.chunks(96).flat_map(|row| row.windows(2).map(|w| (w[1] - w[0]).abs()).collect::<Vec<_>>()).collect();
            (mean(&d), mean(&g), f.rgb)
        };
        let (full, tint_full, rgb_full) = steps(1.0);
        let (tenth, tint_tenth, _) = steps(0.1);
        assert!(tenth < 0.6 * full, "detail {tenth} at a tenth, {full} in full");
        assert!((tint_tenth - tint_full).abs() < 0.15 * tint_full, "tint {tint_tenth} vs {tint_full}");
        assert_eq!(SimRenderer::new(&base).unwrap().render(1).rgb, rgb_full);
        assert!(SimRenderer::new(&SimConfig { seabed_texture: 1.2, ..base }).is_err());
    }

    #[test]
    fn marine_snow_is_fixed_in_the_world() {
        // A particle seen in frame 1, moved by the common drift (a few mm per frame), is where
        // frame 2's pose puts it in frame 2's image, give or take its wobble (at most 1.1 mm a
        // frame); the camera moves 5 cm a frame, so a camera-fixed or re-drawn snow fails this.
        let cfg = SimConfig { lamps: true, snow_per_m3: 600.0, width: 96, height: 72, ..small(WaterPreset::Coastal) };
        let r = SimRenderer::new(&cfg).unwrap();
        let none = SimRenderer::new(&SimConfig { snow_per_m3: 0.0, ..cfg.clone() }).unwrap();
        let (cam, f2, n2) = (r.camera(), r.render(2), none.render(2));
        let cam2_from_world = r.pose(2).world_from_cam.inverse();
        let later = r.snow(2);
        let drift_m = r.snow.as_ref().unwrap().drift_mps() / cfg.fps;
        let (mut checked, mut found, mut moved) = (0, 0, 0.0);
        for s in r.snow(1).iter().filter(|s| (0.3..1.5).contains(&s.range_m) && s.alpha > 0.2) {
            let predicted = s.particle.p_in_world + drift_m;
            let p = (cam2_from_world * nalgebra::Point3::from(predicted)).coords;
            let Some(uv) = cam.project(&p) else { continue };
            let (u, v) = (uv.x.round(), uv.y.round());
            if !(0.0..96.0).contains(&u) || !(0.0..72.0).contains(&v) {
                continue;
            }
            let k = v as usize * 96 + u as usize;
            if n2.range_m.data[k] > 0.0 && (n2.range_m.data[k] as f64) < p.norm() {
                continue; // behind the seabed now
            }
            checked += 1;
            // The same particle in frame 2's list, where the reprojection puts it.
            let twin = later.iter().find(|t| t.particle.id == s.particle.id).expect("still in view");
            let wobble_m = (twin.particle.p_in_world - predicted).norm();
            assert!(wobble_m < 0.0012, "moved {wobble_m} m besides the drift");
            let tolerance_px = 0.0012 * cam.fx / p.z;
            assert!((twin.u - uv.x).abs() < tolerance_px && (twin.v - uv.y).abs() < tolerance_px, "reprojected ({}, {}) vs ({}, {})", uv.x, uv.y, twin.u, twin.v);
            moved += ((twin.u - s.u).powi(2) + (twin.v - s.v).powi(2)).sqrt();
            if (0..3).any(|c| f2.rgb.data[k * 3 + c] as i32 - n2.rgb.data[k * 3 + c] as i32 > 10) {
                found += 1;
            }
        }
        assert!(checked >= 10, "{checked} particles checked");
        assert!(found as f64 >= 0.9 * checked as f64, "{found} of {checked} particles where the reprojection puts them");
        // And they did move in the image (parallax), by more than the tolerance above.
        assert!(moved / checked as f64 > 0.5, "mean image motion {} px", moved / checked as f64);
        // Any frame renders alone: the same particles whatever was rendered before.
        assert_eq!(SimRenderer::new(&cfg).unwrap().render(2).rgb, f2.rgb);
    }

    #[test]
    fn turbidity_burst_fades_the_view_and_leaves_other_frames_alone() {
        // 6 s at 10 fps; the burst from 1 s to 5 s holds from 1.8 s to 4.2 s.
        let plain = SimConfig { frames: 60, ..small(WaterPreset::Coastal) };
        let burst = SimConfig { burst: Some(crate::Burst { start_s: 1.0, duration_s: 4.0, factor: 8.0 }), ..plain.clone() };
        let (a, b) = (SimRenderer::new(&plain).unwrap(), SimRenderer::new(&burst).unwrap());
        assert_eq!(b.medium(), a.medium(), "the written medium is the base one");
        for i in [0, 10, 50, 59] {
            assert_eq!(a.render(i), b.render(i), "frame {i} is outside the burst");
        }
        let contrast = |r: &SimRenderer, i: usize| std_dev(&green(&r.render(i).rgb));
        let (before, hold, after) = (contrast(&b, 5), contrast(&b, 30), contrast(&b, 55));
        assert!(hold < 0.3 * before && hold < 0.3 * after, "green contrast {before} -> {hold} -> {after}");
        assert!(contrast(&a, 30) > 0.7 * before, "without the burst frame 30 keeps its contrast");
        // The rise is gradual: frame 12 (1.2 s, half way up) lies in between.
        let rising = contrast(&b, 12);
        assert!(rising < before && rising > hold, "{before} {rising} {hold}");
        // With lamps and the glow the burst frames take the fresh (uncached) glow path.
        let lit = SimConfig { lamps: true, lamp_backscatter: 1.0, ..burst.clone() };
        let (l, lp) = (SimRenderer::new(&lit).unwrap(), SimRenderer::new(&SimConfig { burst: None, ..lit.clone() }).unwrap());
        assert_eq!(l.render(55), lp.render(55));
        // The glow is smooth; the seabed's contrast in the lower third fades as without lamps.
        let lower = |i: usize| std_dev(&green(&l.render(i).rgb)[48 * 24..]);
        assert!(lower(30) < 0.6 * lower(55), "lamp-lit lower-third contrast {} -> {}", lower(55), lower(30));
    }
}
