//! The restored (water-free) view of a captured frame ([`restore_captured`]): the image
//! formation model (paper §3, `I = J e^{-beta_D r} + B_inf (1 - e^{-beta_B r})` per channel,
//! `r` the range along the ray) inverted per pixel with the map's range and the medium field's
//! parameters for the view, fused with the map's own albedo render ([`albedo`]).
//!
//! The inversion multiplies by `e^{beta_D r}`, which grows without bound with the range (at
//! 6 m in turbid red water it is about 1000): the noise, the snow and any error in the medium
//! or the range grow with it, and the far field blows out. So the restoration stays sane:
//!
//! * the transmission gain is clamped to [`RestoreConfig::max_gain`]: a change of the captured
//!   colour moves the restored one by at most that factor;
//! * per channel, the inversion and the map's albedo are weighted by their variances: the
//!   inversion's grows with the gain and the rendered depth's uncertainty, the albedo's with
//!   the coverage and (fitted through the same water) more slowly with the gain;
//! * a channel the water left without signal (red at long range) is pulled towards the grey
//!   of the channels that kept one instead of an invented colour;
//! * where the map does not cover the pixel (alpha below [`RestoreConfig::min_alpha`]) the
//!   captured colour is kept.
//!
//! Measured on generated water (`docs/results/2026-11-28-map-report.md`): the map's albedo
//! alone (what the panels showed before) 26.1 / 21.7 / 12.5 dB against the water-free truth
//! on clear / coastal / turbid keyframes; this restoration 32.5 / 27.2 / 16.1 dB.

use duv_core::{ImageRgbF32, PinholeCamera};

use crate::render::{DepthMode, MediumPlanes, RenderOutput};

/// Why a restoration was refused.
#[derive(Debug, thiserror::Error)]
pub enum RestoreError {
    #[error("restore: {what} is {width}x{height}, the view is {view_width}x{view_height}")]
    Size { what: &'static str, width: usize, height: usize, view_width: usize, view_height: usize },
    #[error("restore: {field} = {value} {why}")]
    Config { field: &'static str, value: f32, why: &'static str },
}

/// How far the restoration trusts the map. Defaults in [`RestoreConfig::default`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RestoreConfig {
    /// The most the attenuation is undone in the inversion, as a factor on the signal (>= 1):
    /// `e^{beta_D r}` is clamped to it.
    pub max_gain: f32,
    /// Coverage (rendered alpha) below which the pixel keeps its captured colour: the map
    /// has neither range nor albedo there.
    pub min_alpha: f32,
    /// Standard deviation of a captured colour (sensor noise, 8-bit steps, snow), [0, 1] units.
    pub capture_noise: f32,
    /// Standard deviation of the map's albedo at full coverage, [0, 1] units.
    pub albedo_std: f32,
}

impl Default for RestoreConfig {
    fn default() -> Self {
        RestoreConfig { max_gain: 16.0, min_alpha: 0.5, capture_noise: 0.02, albedo_std: 0.05 }
    }
}

impl RestoreConfig {
    pub fn validate(&self) -> Result<(), RestoreError> {
        let bad = |field, value, why| Err(RestoreError::Config { field, value, why });
        if !(self.max_gain.is_finite() && self.max_gain >= 1.0) {
            return bad("max_gain", self.max_gain, "must be a finite factor >= 1");
        }
        if !(self.min_alpha.is_finite() && (0.0..1.0).contains(&self.min_alpha)) {
            return bad("min_alpha", self.min_alpha, "must be in [0, 1)");
        }
        if !(self.capture_noise.is_finite() && self.capture_noise > 0.0) {
            return bad("capture_noise", self.capture_noise, "must be > 0");
        }
        if !(self.albedo_std.is_finite() && self.albedo_std > 0.0) {
            return bad("albedo_std", self.albedo_std, "must be > 0");
        }
        Ok(())
    }

}

/// What a restoration did, over the view's pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct RestoreStats {
    /// Mean weight of the inversion of the captured colour (the rest: the map's albedo, or
    /// the captured colour where the map does not cover the pixel).
    pub mean_confidence: f64,
    /// Share of the pixel channels whose gain was clamped to `max_gain`.
    pub gain_clamped: f64,
    /// Share of the pixels the map does not cover (captured colour kept).
    pub uncovered: f64,
}

/// Views the map's albedo averaged (its noise is the capture noise over its square root).
const ALBEDO_VIEWS: f64 = 4.0;
/// The grey prior's standard deviation, in units of `albedo_std`.
const GREY_PRIOR_STDS: f64 = 4.0;

fn check(what: &'static str, w: usize, h: usize, cam: &PinholeCamera) -> Result<(), RestoreError> {
    if (w, h) != (cam.width, cam.height) {
        return Err(RestoreError::Size { what, width: w, height: h, view_width: cam.width, view_height: cam.height });
    }
    Ok(())
}

/// The water-free view of `captured` (colours in [0, 1]) seen from the pose `out` and `medium`
/// were rendered at. Per pixel and channel, two estimates of `J` are fused by their
/// variances: the inversion `J_f = (I - B_inf (1 - e^{-beta_B r})) g`, `g = min(e^{beta_D r},
/// max_gain)`, whose error grows with the gain (`s_f^2 = (s_n g)^2 + (J_f beta_D r s_r)^2`,
/// `s_n` the capture noise, `s_r` the rendered depth's relative standard deviation), and the
/// map's albedo `J_a = sum w_n c_n / alpha` (`s_a^2 = albedo_std^2 / alpha`), which many views
/// averaged. Where the map does not cover the pixel (alpha < `min_alpha`) the captured colour
/// is kept. Written into `dst` (same size; no allocation).
pub fn restore_captured(
    captured: &ImageRgbF32,
    out: &RenderOutput,
    medium: &MediumPlanes,
    camera: &PinholeCamera,
    mode: DepthMode,
    cfg: &RestoreConfig,
    dst: &mut ImageRgbF32,
) -> Result<RestoreStats, RestoreError> {
    cfg.validate()?;
    check("the captured image", captured.width, captured.height, camera)?;
    check("the render", out.width(), out.height(), camera)?;
    check("the medium", medium.width(), medium.height(), camera)?;
    check("the output", dst.width, dst.height, camera)?;
    let (mut conf_sum, mut clamped, mut uncovered) = (0.0f64, 0usize, 0usize);
    let n = camera.width * camera.height;
    let var_n = (cfg.capture_noise as f64).powi(2);
    for y in 0..camera.height {
        let yn = (y as f64 - camera.cy) / camera.fy;
        for x in 0..camera.width {
            let k = y * camera.width + x;
            let xn = (x as f64 - camera.cx) / camera.fx;
            let (d, v, a) = (out.depth.data[k], out.depth_var.data[k], out.alpha.data[k]);
            let z = match mode {
                DepthMode::InverseDepth => 1.0 / d,
                DepthMode::Depth => d,
            };
            if !(a >= cfg.min_alpha && d > 0.0 && z.is_finite()) {
                uncovered += 1;
                dst.data[k * 3..k * 3 + 3].copy_from_slice(&captured.data[k * 3..k * 3 + 3]);
                continue;
            }
            // For d = 1/z, std(z)/z = std(d)/d to first order.
            let rel_std = (v.max(0.0).sqrt() / d.abs()) as f64;
            let r = z as f64 * (xn * xn + yn * yn + 1.0).sqrt();
            let (mut j, mut var) = ([0.0f64; 3], [0.0f64; 3]);
            for c in 0..3 {
                let i = captured.data[k * 3 + c] as f64;
                let j_a = (out.restored.data[k * 3 + c] / a).clamp(0.0, 1.0) as f64;
                let beta_d = medium.sigma_att.data[k * 3 + c] as f64;
                let b = medium.c_med.data[k * 3 + c] as f64 * (1.0 - (-(medium.sigma_bs.data[k * 3 + c] as f64) * r).exp());
                let g_true = (beta_d * r).exp();
                let g = if g_true <= cfg.max_gain as f64 {
                    g_true
                } else {
                    clamped += 1;
                    cfg.max_gain as f64
                };
                let j_f = ((i - b) * g).clamp(0.0, 1.0);
                let var_f = var_n * g_true * g_true + (j_f * beta_d * r * rel_std).powi(2);
                // The albedo was fitted through about the same transmission, from several views.
                let var_a = (cfg.albedo_std as f64).powi(2) / a as f64 + var_n * g_true * g_true / ALBEDO_VIEWS;
                let w = var_a / (var_a + var_f);
                conf_sum += w / 3.0;
                j[c] = w * j_f + (1.0 - w) * j_a;
                var[c] = var_a * var_f / (var_a + var_f);
            }
            // A channel the water left without signal (red at long range) takes the grey of
            // the channels that kept one, instead of a colour nothing measured.
            let grey = (0..3).map(|c| j[c] / var[c]).sum::<f64>() / (0..3).map(|c| 1.0 / var[c]).sum::<f64>();
            let var_p = (cfg.albedo_std as f64 * GREY_PRIOR_STDS).powi(2);
            for c in 0..3 {
                dst.data[k * 3 + c] = ((j[c] / var[c] + grey / var_p) / (1.0 / var[c] + 1.0 / var_p)) as f32;
            }
        }
    }
    Ok(RestoreStats { mean_confidence: conf_sum / n.max(1) as f64, gain_clamped: clamped as f64 / (3 * n).max(1) as f64, uncovered: uncovered as f64 / n.max(1) as f64 })
}

/// The map's albedo render `sum w_n c_n` divided by its coverage where the map covers the
/// pixel (alpha >= `min_alpha`), the captured colour elsewhere: the map's own water-free view.
pub fn albedo(captured: &ImageRgbF32, out: &RenderOutput, min_alpha: f32, dst: &mut ImageRgbF32) {
    for (k, &a) in out.alpha.data.iter().enumerate() {
        for c in 0..3 {
            dst.data[k * 3 + c] = if a >= min_alpha && a > 0.0 { (out.restored.data[k * 3 + c] / a).clamp(0.0, 1.0) } else { captured.data[k * 3 + c] };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_core::PlaneF32;

    fn camera(w: usize, h: usize) -> PinholeCamera {
        PinholeCamera::new(50.0, 50.0, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0, w, h).unwrap()
    }

    /// A flat render at inverse depth `d` with variance `var` and full coverage.
    fn render(w: usize, h: usize, d: f32, var: f32, alpha: f32) -> RenderOutput {
        let mut out = RenderOutput::new(w, h);
        out.depth = PlaneF32 { width: w, height: h, data: vec![d; w * h] };
        out.depth_var = PlaneF32 { width: w, height: h, data: vec![var; w * h] };
        out.alpha = PlaneF32 { width: w, height: h, data: vec![alpha; w * h] };
        out
    }

    /// A flat seabed `z` metres away with albedo `j_true`, seen through `medium`: the captured
    /// image, and a render whose albedo is `albedo` at coverage `alpha`.
    fn scene(cam: &PinholeCamera, z: f32, j_true: [f32; 3], m: ([f32; 3], [f32; 3], [f32; 3])) -> ImageRgbF32 {
        let (beta_d, beta_b, b_inf) = m;
        let mut captured = ImageRgbF32::new(cam.width, cam.height);
        for y in 0..cam.height {
            for x in 0..cam.width {
                let (xn, yn) = ((x as f64 - cam.cx) / cam.fx, (y as f64 - cam.cy) / cam.fy);
                let r = z as f64 * (xn * xn + yn * yn + 1.0).sqrt();
                for c in 0..3 {
                    let i = j_true[c] as f64 * (-(beta_d[c] as f64) * r).exp() + b_inf[c] as f64 * (1.0 - (-(beta_b[c] as f64) * r).exp());
                    captured.data[(y * cam.width + x) * 3 + c] = i as f32;
                }
            }
        }
        captured
    }

    fn with_albedo(mut out: RenderOutput, albedo: [f32; 3]) -> RenderOutput {
        let a = out.alpha.data[0];
        out.restored = ImageRgbF32::filled(out.width(), out.height(), albedo.map(|v| v * a));
        out
    }

    #[test]
    fn inverts_the_image_formation_and_falls_back_to_the_map_where_the_water_took_the_signal() {
        let (w, h) = (16, 12);
        let cam = camera(w, h);
        let m = ([0.4f32, 0.1, 0.05], [0.3f32, 0.2, 0.1], [0.05f32, 0.3, 0.4]);
        let medium = MediumPlanes::uniform(w, h, m.2, m.0, m.1);
        let j_true = [0.6f32, 0.5, 0.3];
        let cfg = RestoreConfig::default();
        let mut dst = ImageRgbF32::new(w, h);
        let err = |dst: &ImageRgbF32, truth: [f32; 3]| dst.data.iter().enumerate().map(|(k, &v)| (v - truth[k % 3]).abs()).fold(0.0f32, f32::max);

        // 2 m away (gain at most e^0.8 = 2.2) with the true albedo: exact but for the grey
        // prior's pull (under 0.01); with an albedo 0.1 off in every channel, the inversion
        // takes back more than half of it.
        let captured = scene(&cam, 2.0, j_true, m);
        let out = with_albedo(render(w, h, 0.5, 0.0, 1.0), j_true);
        let stats = restore_captured(&captured, &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst).unwrap();
        assert!(err(&dst, j_true) < 0.01, "restored off by {}", err(&dst, j_true));
        assert!(stats.mean_confidence > 0.6 && stats.gain_clamped == 0.0 && stats.uncovered == 0.0, "{stats:?}");
        let out = with_albedo(render(w, h, 0.5, 0.0, 1.0), [0.7, 0.6, 0.4]);
        restore_captured(&captured, &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst).unwrap();
        assert!(err(&dst, j_true) < 0.05, "restored off by {}", err(&dst, j_true));

        // 20 m away red would need a gain of e^8 = 2981: it is held at max_gain, no view
        // measured red there, so red takes the grey of the measured channels (no invented
        // colour); a captured change moves the output by at most max_gain times as much.
        let far = scene(&cam, 20.0, j_true, m);
        let out = with_albedo(render(w, h, 1.0 / 20.0, 0.0, 1.0), j_true);
        let stats = restore_captured(&far, &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst).unwrap();
        assert!(stats.gain_clamped > 0.3, "{stats:?}");
        let (r, g, b) = (dst.data[0], dst.data[1], dst.data[2]);
        assert!(r >= g.min(b) - 0.02 && r <= g.max(b) + 0.02, "red {r} outside the measured green {g} and blue {b}");
        let mut nudged = far.clone();
        nudged.data.iter_mut().for_each(|v| *v += 0.01);
        let mut dst2 = ImageRgbF32::new(w, h);
        restore_captured(&nudged, &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst2).unwrap();
        let moved = dst.data.iter().zip(&dst2.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(moved <= 0.01 * cfg.max_gain, "a 0.01 change of the capture moved the output by {moved}");

        // Uncertain depth (relative std 1) and a wrong inversion (the medium twice as thick):
        // the map's albedo weighs more, the result stays within 0.06 of the truth.
        let thick = MediumPlanes::uniform(w, h, m.2, m.0.map(|b| 2.0 * b), m.1);
        let out = with_albedo(render(w, h, 0.5, 0.25, 1.0), j_true);
        let stats = restore_captured(&captured, &out, &thick, &cam, DepthMode::InverseDepth, &cfg, &mut dst).unwrap();
        assert!(err(&dst, j_true) < 0.06 && stats.mean_confidence < 0.5, "off by {}, {stats:?}", err(&dst, j_true));
        // Not covered: the captured colour as it is.
        let out = render(w, h, 0.5, 0.0, 0.3);
        let stats = restore_captured(&far, &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst).unwrap();
        assert_eq!(stats.uncovered, 1.0);
        assert_eq!(dst.data, far.data);
    }

    #[test]
    fn refuses_bad_sizes_and_settings() {
        let cam = camera(8, 8);
        let medium = MediumPlanes::new(8, 8);
        let out = render(8, 8, 0.5, 0.0, 1.0);
        let mut dst = ImageRgbF32::new(8, 8);
        let small = ImageRgbF32::new(4, 8);
        assert!(matches!(restore_captured(&small, &out, &medium, &cam, DepthMode::InverseDepth, &RestoreConfig::default(), &mut dst), Err(RestoreError::Size { .. })));
        let cfg = RestoreConfig { max_gain: 0.5, ..RestoreConfig::default() };
        assert!(matches!(restore_captured(&dst.clone(), &out, &medium, &cam, DepthMode::InverseDepth, &cfg, &mut dst), Err(RestoreError::Config { field: "max_gain", .. })));
    }
}
