//! Surface colours of the scene: procedural albedo at the hit point with detail from metres
//! down to millimetres (sand grain, shell fragments, pitted rock with encrusting growth,
//! algae patches of three kinds, a concrete-coated pipe with marine growth, a rusted wreck
//! with plate seams, rivets and barnacles), band-limited by the pixel footprint so nothing
//! aliases or flickers.

use super::noise::{fbm, fbm3, gnoise, gnoise3, lerp, smoothstep, spots};
use super::scene::{Hit, Scene, Surface};

impl Scene {
    /// Albedo (linear RGB, [0, 1]) at a hit, detail limited to what a pixel of
    /// `footprint_m` metres on the surface resolves.
    pub fn albedo(&self, hit: &Hit, footprint_m: f64) -> [f64; 3] {
        let w = footprint_m.max(1e-5);
        match hit.surface {
            Surface::Seabed => self.seabed_albedo(hit, w),
            Surface::Pipe { along_m, around_m } => self.pipe_albedo(along_m, around_m, hit.normal.z, w),
            Surface::Wreck { part, u, v } => self.wreck_albedo(part, u, v, hit.normal.z, w),
        }
    }

    fn seabed_albedo(&self, hit: &Hit, w: f64) -> [f64; 3] {
        let s = &self.seeds;
        let (x, y) = (hit.point.x + 0.31 * hit.point.z, hit.point.y - 0.27 * hit.point.z);
        let rock = self.heightfield().rockiness(hit.point.x, hit.point.y);

        // Shared fine detail: grain-scale to decimetre variation.
        let detail = fbm(x, y, s[0], 0.5, 10, 0.66, w);

        // Sand: two tints drifting over metres, grains, shell fragments, darker organic film.
        let mut color = {
            let tint = 0.5 + 0.5 * gnoise(x / 7.0, y / 7.0, s[1]);
            let a = [0.68, 0.60, 0.45];
            let b = [0.50, 0.46, 0.39];
            let mut c = [lerp(a[0], b[0], tint), lerp(a[1], b[1], tint), lerp(a[2], b[2], tint)];
            let film = smoothstep(0.15, 0.75, gnoise(x / 1.7, y / 1.7, s[2]));
            let k = (1.0 + 0.30 * detail) * (1.0 - 0.28 * film);
            let bright_grains = spots(x, y, s[3], 0.011, 0.45, w);
            let dark_grains = spots(x + 0.004, y, s[4], 0.008, 0.4, w);
            let shells = spots(x, y, s[5], 0.07, 0.06, w);
            for (ch, v) in c.iter_mut().enumerate() {
                *v = *v * k * (1.0 + 0.35 * bright_grains - 0.45 * dark_grains);
                *v = lerp(*v, [0.86, 0.83, 0.76][ch], 0.6 * shells);
            }
            c
        };

        if rock > 0.0 {
            // Rock flanks can be steep: 3D noise so the texture does not stretch.
            let p = [hit.point.x, hit.point.y, hit.point.z];
            // From pale granite to dark basalt, varying from rock to rock.
            let tone = (0.5 + 0.6 * gnoise(x / 0.7, y / 0.7, s[6])).clamp(0.0, 1.0);
            let base = [lerp(0.62, 0.30, tone), lerp(0.59, 0.28, tone), lerp(0.54, 0.25, tone)];
            let grain = fbm3(p, s[7], 0.25, 8, 0.68, w);
            // Pitted, weathered surface: dark hollows where a mid-scale noise is low.
            let pits = smoothstep(0.15, 0.55, -gnoise3(p[0] / 0.05, p[1] / 0.05, p[2] / 0.05, s[8])) * smoothstep(0.5, 1.0, 0.05 / (2.0 * w));
            let k = (1.0 + 0.5 * grain) * (1.0 - 0.35 * pits);
            let mut c = [base[0] * k, base[1] * k, base[2] * k];
            // Encrusting growth (coralline pink, sponge orange) in patches.
            let crust = smoothstep(0.25, 0.6, gnoise3(p[0] / 0.12, p[1] / 0.12, p[2] / 0.12, s[9]));
            let crust_color = if gnoise(x / 1.5, y / 1.5, s[9] ^ 0x3) < 0.0 { [0.60, 0.33, 0.36] } else { [0.74, 0.56, 0.30] };
            for ch in 0..3 {
                c[ch] = lerp(c[ch], crust_color[ch] * (1.0 + 0.3 * grain), 0.6 * crust);
                color[ch] = lerp(color[ch], c[ch], rock);
            }
        }

        // Algae patches: green weed, brown kelp-like film, red coralline; more on rocks.
        let patch = 0.5 + 0.5 * (0.7 * gnoise(x / 3.2, y / 3.2, s[10]) + 0.3 * gnoise(x / 0.8, y / 0.8, s[11]));
        let cover = smoothstep(0.5, 0.8, patch + 0.25 * rock);
        if cover > 0.0 {
            let kind = gnoise(x / 5.0, y / 5.0, s[12]);
            let green = [0.26, 0.36, 0.15];
            let brown = [0.36, 0.29, 0.14];
            let red = [0.46, 0.22, 0.20];
            let base = if kind < -0.15 {
                let t = smoothstep(-0.45, -0.15, kind);
                [lerp(red[0], green[0], t), lerp(red[1], green[1], t), lerp(red[2], green[2], t)]
            } else {
                let t = smoothstep(-0.15, 0.3, kind);
                [lerp(green[0], brown[0], t), lerp(green[1], brown[1], t), lerp(green[2], brown[2], t)]
            };
            // Filaments: ridged noise along a drifting direction.
            let strands = 1.0 - fbm(x * 2.3, y * 0.8, s[13], 0.12, 6, 0.7, w).abs();
            let k = 0.45 + 0.8 * strands * (1.0 + 0.25 * detail);
            let density = cover * (0.35 + 0.55 * smoothstep(-0.4, 0.5, gnoise(x / 0.25, y / 0.25, s[14])));
            for ch in 0..3 {
                color[ch] = lerp(color[ch], base[ch] * k, density);
            }
        }
        if self.seabed_texture != 1.0 {
            // Featureless sand: every variation drawn towards a mid sand tint.
            const MID_SAND: [f64; 3] = [0.59, 0.53, 0.42];
            for ch in 0..3 {
                color[ch] = MID_SAND[ch] + self.seabed_texture * (color[ch] - MID_SAND[ch]);
            }
        }
        [color[0].clamp(0.0, 1.0), color[1].clamp(0.0, 1.0), color[2].clamp(0.0, 1.0)]
    }

    fn pipe_albedo(&self, along: f64, around: f64, up: f64, w: f64) -> [f64; 3] {
        let s = &self.seeds;
        let detail = fbm(along, around, s[0] ^ 0x11, 0.4, 9, 0.62, w);
        let aggregate = spots(along, around, s[3] ^ 0x11, 0.02, 0.5, w);
        let k = (1.0 + 0.25 * detail) * (1.0 - 0.25 * aggregate);
        let mut c = [0.56 * k, 0.55 * k, 0.51 * k];
        // Field joints every 12 m (dark wrap) and yellow survey bands every 4 m.
        let j = along.rem_euclid(12.2);
        if j < 0.35 {
            c = [0.16 * k, 0.15 * k, 0.14 * k];
        } else if along.rem_euclid(4.0) < 0.25 {
            c = [0.80 * k, 0.62 * k, 0.12 * k];
        }
        // Marine growth, thicker on top.
        let growth = smoothstep(0.2, 0.6, 0.5 + 0.5 * gnoise(along / 0.9, around / 0.5, s[15]) + 0.3 * up);
        let g = [0.30 * (1.0 + 0.4 * detail), 0.34 * (1.0 + 0.4 * detail), 0.16];
        let barnacles = spots(along, around, s[5] ^ 0x11, 0.03, 0.4, w);
        for ch in 0..3 {
            c[ch] = lerp(c[ch], g[ch], 0.8 * growth);
            c[ch] = lerp(c[ch], 0.82, 0.7 * barnacles * growth);
        }
        [c[0].clamp(0.0, 1.0), c[1].clamp(0.0, 1.0), c[2].clamp(0.0, 1.0)]
    }

    fn wreck_albedo(&self, part: u8, u: f64, v: f64, up: f64, w: f64) -> [f64; 3] {
        let s = &self.seeds;
        let detail = fbm(u, v, s[0] ^ 0x22, 0.5, 10, 0.65, w);
        // Rust from orange to near black, streaked downwards on the sides.
        let streak = fbm(u * 6.0, v * 0.6, s[6] ^ 0x22, 0.6, 5, 0.6, w);
        let rust = 0.5 + 0.5 * gnoise(u / 0.8, v / 0.8, s[1] ^ 0x22) + 0.25 * streak;
        let (a, b) = ([0.55, 0.30, 0.16], [0.20, 0.13, 0.10]);
        let t = rust.clamp(0.0, 1.0);
        let k = 1.0 + 0.35 * detail;
        let mut c = [lerp(a[0], b[0], t) * k, lerp(a[1], b[1], t) * k, lerp(a[2], b[2], t) * k];
        if part != 2 {
            // Plate seams every 0.6 m with rivets along them.
            let su = (u / 0.6).fract().abs().min(1.0 - (u / 0.6).fract().abs());
            let sv = (v / 0.45).fract().abs().min(1.0 - (v / 0.45).fract().abs());
            let seam_u = 1.0 - smoothstep(0.0, 0.025, su);
            let seam_v = 1.0 - smoothstep(0.0, 0.03, sv);
            let resolvable = smoothstep(0.5, 1.0, 0.015 / w);
            let seam = seam_u.max(seam_v) * resolvable;
            let rivet = spots(u + 0.3, v + 0.3, s[7] ^ 0x22, 0.05, 0.9, w) * seam;
            for ch in c.iter_mut() {
                *ch *= 1.0 - 0.45 * seam + 0.6 * rivet;
            }
        }
        // Fouling on upward faces, barnacles everywhere.
        let fouling = smoothstep(0.3, 0.8, up) * smoothstep(0.2, 0.6, 0.5 + 0.5 * gnoise(u / 0.5, v / 0.5, s[12] ^ 0x22));
        let green = [0.24 * k, 0.36 * k, 0.14 * k];
        let barnacles = spots(u, v, s[5] ^ 0x22, 0.025, 0.3, w);
        for ch in 0..3 {
            c[ch] = lerp(c[ch], green[ch], 0.85 * fouling);
            c[ch] = lerp(c[ch], 0.8, 0.8 * barnacles);
        }
        [c[0].clamp(0.0, 1.0), c[1].clamp(0.0, 1.0), c[2].clamp(0.0, 1.0)]
    }
}
