//! Deterministic lattice noise for the generated scene: an integer hash, 2D gradient noise and
//! band-limited fractal sums. Band-limited means that octaves finer than the pixel footprint
//! fade to their mean, so distant texture neither aliases nor flickers from frame to frame
//! (flicker would break the brightness constancy dense optical flow relies on).
//! Pure functions of position and seed: the same inputs give the same bits on every thread.

/// Integer hash of a lattice point and a seed (a lowbias32-style finaliser).
#[inline]
pub fn hash2(ix: i32, iy: i32, seed: u32) -> u32 {
    let mut h = (ix as u32).wrapping_mul(0x8DA6_B343) ^ (iy as u32).wrapping_mul(0xD816_3841) ^ seed.wrapping_mul(0xCB1A_B31F);
    h ^= h >> 16;
    h = h.wrapping_mul(0x7FEB_352D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x846C_A68B);
    h ^= h >> 16;
    h
}

/// Uniform in [0, 1) from a hash.
#[inline]
pub fn unit(h: u32) -> f64 {
    h as f64 * (1.0 / 4_294_967_296.0)
}

/// A second independent hash of the same lattice point (for several random numbers per cell).
#[inline]
pub fn rehash(h: u32, k: u32) -> u32 {
    hash2(h as i32, k as i32, 0x68E3_1DA4)
}

const D: f64 = std::f64::consts::FRAC_1_SQRT_2;
const GRADS: [(f64, f64); 8] = [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0), (D, D), (-D, D), (D, -D), (-D, -D)];

#[inline]
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

#[inline]
pub fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a + (b - a) * t
}

#[inline]
pub fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// `floor(x)` as an integer, without a libm call (baseline x86-64 has no rounding instruction).
#[inline]
pub fn floor_i32(x: f64) -> i32 {
    let i = x as i32;
    if (i as f64) > x {
        i - 1
    } else {
        i
    }
}

/// 2D gradient (Perlin) noise with quintic fade (C2 continuous), roughly in [-1, 1], mean 0,
/// unit lattice spacing.
#[inline]
pub fn gnoise(x: f64, y: f64, seed: u32) -> f64 {
    let (ix, iy) = (floor_i32(x), floor_i32(y));
    let (fx, fy) = (x - ix as f64, y - iy as f64);
    let g = |i: i32, j: i32, dx: f64, dy: f64| {
        let (gx, gy) = GRADS[(hash2(ix.wrapping_add(i), iy.wrapping_add(j), seed) >> 29) as usize];
        gx * dx + gy * dy
    };
    let n00 = g(0, 0, fx, fy);
    let n10 = g(1, 0, fx - 1.0, fy);
    let n01 = g(0, 1, fx, fy - 1.0);
    let n11 = g(1, 1, fx - 1.0, fy - 1.0);
    let u = fade(fx);
    let v = fade(fy);
    1.45 * lerp(lerp(n00, n10, u), lerp(n01, n11, u), v)
}

/// Integer hash of a 3D lattice point.
#[inline]
pub fn hash3(ix: i32, iy: i32, iz: i32, seed: u32) -> u32 {
    hash2(ix, iy ^ (iz.wrapping_mul(0x2C1B_3C6D_u32 as i32)), seed)
}

const G3: [(f64, f64, f64); 12] = [
    (1.0, 1.0, 0.0),
    (-1.0, 1.0, 0.0),
    (1.0, -1.0, 0.0),
    (-1.0, -1.0, 0.0),
    (1.0, 0.0, 1.0),
    (-1.0, 0.0, 1.0),
    (1.0, 0.0, -1.0),
    (-1.0, 0.0, -1.0),
    (0.0, 1.0, 1.0),
    (0.0, -1.0, 1.0),
    (0.0, 1.0, -1.0),
    (0.0, -1.0, -1.0),
];

/// 3D gradient (Perlin) noise, roughly in [-1, 1]: for surfaces that are not horizontal
/// (rock flanks), where planar noise would stretch.
pub fn gnoise3(x: f64, y: f64, z: f64, seed: u32) -> f64 {
    let (ix, iy, iz) = (floor_i32(x), floor_i32(y), floor_i32(z));
    let (fx, fy, fz) = (x - ix as f64, y - iy as f64, z - iz as f64);
    let g = |i: i32, j: i32, k: i32| {
        let h = hash3(ix.wrapping_add(i), iy.wrapping_add(j), iz.wrapping_add(k), seed);
        let (gx, gy, gz) = G3[((h >> 16) % 12) as usize];
        gx * (fx - i as f64) + gy * (fy - j as f64) + gz * (fz - k as f64)
    };
    let (u, v, w) = (fade(fx), fade(fy), fade(fz));
    let x00 = lerp(g(0, 0, 0), g(1, 0, 0), u);
    let x10 = lerp(g(0, 1, 0), g(1, 1, 0), u);
    let x01 = lerp(g(0, 0, 1), g(1, 0, 1), u);
    let x11 = lerp(g(0, 1, 1), g(1, 1, 1), u);
    1.1 * lerp(lerp(x00, x10, v), lerp(x01, x11, v), w)
}

/// Band-limited fractal sum of 3D gradient noise (see [`fbm`]).
pub fn fbm3(p: [f64; 3], seed: u32, lambda_m: f64, octaves: u32, gain: f64, footprint_m: f64) -> f64 {
    let mut q = [p[0] / lambda_m, p[1] / lambda_m, p[2] / lambda_m];
    let mut lambda = lambda_m;
    let mut amp = 1.0;
    let mut sum = 0.0;
    for o in 0..octaves {
        let w = octave_weight(lambda, footprint_m);
        if w <= 0.0 {
            break;
        }
        sum += amp * w * gnoise3(q[0], q[1], q[2], seed.wrapping_add(o.wrapping_mul(0x9E37_79B9)));
        // Rotate about the (1, 1, 1) diagonal-ish by swapping and mixing axes, double, shift.
        q = [2.0 * (ROT_C * q[0] - ROT_S * q[2]) + 7.13, 2.0 * (ROT_S * q[0] + ROT_C * q[2]) - 3.71, 2.0 * q[1] + 11.9];
        lambda *= 0.5;
        amp *= gain;
    }
    sum
}

// Successive octaves are rotated by ~37 degrees and shifted so lattice axes do not line up.
const ROT_C: f64 = 0.798_635_510_047_292_9;
const ROT_S: f64 = 0.601_815_023_152_048_3;

/// How much of an octave of wavelength `lambda_m` survives at pixel footprint `footprint_m`:
/// 1 above four footprints, 0 below two (the Nyquist limit), smooth in between.
#[inline]
pub fn octave_weight(lambda_m: f64, footprint_m: f64) -> f64 {
    smoothstep(1.0, 2.0, lambda_m / (2.0 * footprint_m))
}

/// Band-limited fractal sum of gradient noise. `lambda_m` is the wavelength of the first
/// octave in metres; each next octave halves it and scales the amplitude by `gain`. Octaves
/// the footprint cannot resolve are dropped (their mean is 0). Result roughly in [-1, 1] times
/// the sum of amplitudes.
pub fn fbm(x: f64, y: f64, seed: u32, lambda_m: f64, octaves: u32, gain: f64, footprint_m: f64) -> f64 {
    let (mut px, mut py) = (x / lambda_m, y / lambda_m);
    let mut lambda = lambda_m;
    let mut amp = 1.0;
    let mut sum = 0.0;
    for o in 0..octaves {
        let w = octave_weight(lambda, footprint_m);
        if w <= 0.0 {
            break;
        }
        sum += amp * w * gnoise(px, py, seed.wrapping_add(o.wrapping_mul(0x9E37_79B9)));
        let (rx, ry) = (ROT_C * px - ROT_S * py, ROT_S * px + ROT_C * py);
        px = 2.0 * rx + 17.31;
        py = 2.0 * ry - 9.17;
        lambda *= 0.5;
        amp *= gain;
    }
    sum
}

/// Sparse round spots on a jittered grid of `cell_m` (shell fragments, grains, rivets): 1 inside
/// a spot, 0 outside, with probability `density` that a cell holds one of radius up to 0.35
/// cells. Below the footprint a spot fades to its mean coverage.
pub fn spots(x: f64, y: f64, seed: u32, cell_m: f64, density: f64, footprint_m: f64) -> f64 {
    let (gx, gy) = (x / cell_m, y / cell_m);
    let (ix, iy) = (floor_i32(gx), floor_i32(gy));
    let (cx, cy) = (ix as f64, iy as f64);
    let h = hash2(ix, iy, seed);
    if unit(h) >= density {
        return 0.0;
    }
    // Radius and position from the bytes of a second hash.
    let h2 = rehash(h, 1);
    let byte = |k: u32| ((h2 >> (8 * k)) & 0xFF) as f64 * (1.0 / 255.0);
    let r = 0.15 + 0.2 * byte(0);
    let ox = r + (1.0 - 2.0 * r) * byte(1);
    let oy = r + (1.0 - 2.0 * r) * byte(2);
    let d = ((gx - cx - ox).powi(2) + (gy - cy - oy).powi(2)).sqrt();
    let sharp = 1.0 - smoothstep(r * 0.7, r, d);
    // Mean coverage of the cell by the spot, used where the spot is unresolved.
    let mean = std::f64::consts::PI * r * r * 0.85;
    let w = octave_weight(2.0 * r * cell_m, footprint_m);
    w * sharp + (1.0 - w) * mean
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradient_noise_is_bounded_continuous_and_seeded() {
        let mut max: f64 = 0.0;
        let mut mean = 0.0;
        let n = 20_000;
        for i in 0..n {
            let x = i as f64 * 0.137 - 500.0;
            let y = i as f64 * 0.0913 + 3.0;
            let v = gnoise(x, y, 5);
            max = max.max(v.abs());
            mean += v / n as f64;
            // Lipschitz-continuous: a tiny step changes the value a tiny bit.
            assert!((gnoise(x + 1e-6, y, 5) - v).abs() < 1e-4);
        }
        assert!(max <= 1.05 && max > 0.5, "{max}");
        assert!(mean.abs() < 0.05, "{mean}");
        assert_ne!(gnoise(0.3, 0.7, 1), gnoise(0.3, 0.7, 2));
        let mut max3: f64 = 0.0;
        for i in 0..5000 {
            let (x, y, z) = (i as f64 * 0.173, i as f64 * 0.071 - 9.0, i as f64 * 0.0391);
            let v = gnoise3(x, y, z, 4);
            max3 = max3.max(v.abs());
            assert!((gnoise3(x, y, z + 1e-6, 4) - v).abs() < 1e-4);
        }
        assert!(max3 <= 1.1 && max3 > 0.4, "{max3}");
        assert_eq!(gnoise(12.0, -3.0, 9), 0.0, "zero at lattice points");
    }

    #[test]
    fn fbm_drops_octaves_below_the_footprint() {
        // With a footprint larger than the first wavelength nothing is resolvable.
        assert_eq!(fbm(1.3, 2.7, 3, 0.01, 8, 0.5, 1.0), 0.0);
        // A fine footprint keeps detail: values differ at a quarter-wavelength spacing.
        let a = fbm(1.3, 2.7, 3, 0.04, 6, 0.6, 1e-4);
        let b = fbm(1.31, 2.7, 3, 0.04, 6, 0.6, 1e-4);
        assert!((a - b).abs() > 1e-3);
        let s = spots(0.5, 0.5, 1, 0.1, 1.0, 1.0);
        assert!((0.0..=1.0).contains(&s));
    }
}
