// The mapping losses (Eq. 12-14) and their gradients with respect to the rendered images
// (CPU reference: `total_loss` and its terms in src/map/loss.rs, the same formulas, the same
// order of additions per pixel). One invocation per pixel, 1-D grid of 256-wide workgroups.
//
//   count_valid         tracked pixels valid for the depth terms -> valid_count (u32 atomics:
//                       integer sums, exact and order-free)
//   loss_pixels         L1 (dL/dC, overwrites up_colour), Mahalanobis + KL + smoothness
//                       (dL/dD, dL/dV) and accuracy (dL/dA) into up_scalars (overwrites)
//   ssim_rows           horizontal 11-tap filter of the 15 moment sources (x, y, x^2, y^2, xy
//                       per channel) -> moments_a
//   ssim_cols           vertical filter -> the SSIM map and its 9 partials (dS/dmu_x,
//                       dS/dE_xx, dS/dE_xy per channel) -> moments_b
//   ssim_back_rows      horizontal filter of the partials -> moments_a
//   ssim_back_cols      vertical filter, then dSSIM/dx added into up_colour
//   medium_sums         per-workgroup sums of c_med -> medium_sums[group]
//   medium_mean         one workgroup: the sums in a fixed order -> the mean after the groups
//   medium_variation    dL/dc_med (overwrites d_c_med)
//
// Loss values: each workgroup writes its partial sums to partials[group * 8 + term] (terms:
// 0 L1, 1 Mahalanobis, 2 KL, 3 smoothness, 4 accuracy, 5 SSIM map, 6 medium variation) by a
// tree reduction in workgroup memory; the host adds them in group order. No float atomics:
// the results are bit-identical from run to run on one device.

struct LossParams {
    width: u32,
    height: u32,
    pad0: u32,
    pad1: u32,
    // photometric_weight (1 - lambda)
    l1_weight: f32,
    // photometric_weight lambda
    ssim_weight: f32,
    maha_weight: f32,
    kl_weight: f32,
    kl_floor: f32,
    max_track_var: f32,
    smooth_weight: f32,
    smooth_gamma: f32,
    smooth_eps: f32,
    acc_weight: f32,
    acc_scale: f32,
    acc_ln_beta: f32,
    mv_weight: f32,
    pad2: f32,
    pad3: f32,
    pad4: f32,
}

var<immediate> params: LossParams;

const WG: u32 = 256u;
const RADIUS: i32 = 5;
const TERMS: u32 = 8u;
const SSIM_C1: f32 = 0.0001;
const SSIM_C2: f32 = 0.0009;

// Rendered colour (RGB per pixel) and [depth, depth variance, alpha, final T] per pixel.
@group(0) @binding(0) var<storage, read> colour: array<f32>;
@group(0) @binding(1) var<storage, read> scalars: array<vec4<f32>>;
// Observed image (RGB) and the tracker's [inverse depth, variance] per pixel.
@group(0) @binding(2) var<storage, read> target_image: array<f32>;
@group(0) @binding(3) var<storage, read> track: array<vec2<f32>>;
// Upstream gradients of the renderer: dL/dC (RGB), [dL/dD, dL/dV, dL/dA, 0].
@group(0) @binding(4) var<storage, read_write> up_colour: array<f32>;
@group(0) @binding(5) var<storage, read_write> up_scalars: array<vec4<f32>>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;
@group(0) @binding(7) var<storage, read_write> valid_count: array<atomic<u32>>;
// The normalised 11-tap Gaussian window (`ssim_kernel`).
@group(0) @binding(8) var<storage, read> window: array<f32>;
@group(0) @binding(9) var<storage, read_write> moments_a: array<f32>;
@group(0) @binding(10) var<storage, read_write> moments_b: array<f32>;
// Medium planes' c_med (RGB per pixel) and dL/dc_med.
@group(0) @binding(11) var<storage, read> c_med: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_c_med: array<f32>;
// Per-workgroup c_med sums (4 per group), then the mean (4 floats after the groups).
@group(0) @binding(13) var<storage, read_write> c_med_sums: array<vec4<f32>>;

var<workgroup> red_a: array<vec4<f32>, 256>;
var<workgroup> red_b: array<vec4<f32>, 256>;
var<workgroup> red_count: array<u32, 256>;

// Tree reduction of two vec4 per invocation over the workgroup (fixed order); every
// invocation of the workgroup must call it.
fn reduce_pair(lid: u32, a: vec4<f32>, b: vec4<f32>) {
    red_a[lid] = a;
    red_b[lid] = b;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s >> 1u) {
        if (lid < s) {
            red_a[lid] = red_a[lid] + red_a[lid + s];
            red_b[lid] = red_b[lid] + red_b[lid + s];
        }
        workgroupBarrier();
    }
}

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// The tracked pixel's (depth, variance) and whether it is valid for the depth terms.
fn valid_track(p: u32) -> bool {
    let t = track[p];
    return finite(t.x) && finite(t.y) && t.y > 0.0 && t.y <= params.max_track_var;
}

@compute @workgroup_size(256)
fn count_valid(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let p = gid.x;
    var v = 0u;
    if (p < params.width * params.height && valid_track(p)) {
        v = 1u;
    }
    red_count[lid] = v;
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s = s >> 1u) {
        if (lid < s) {
            red_count[lid] = red_count[lid] + red_count[lid + s];
        }
        workgroupBarrier();
    }
    if (lid == 0u && red_count[0] > 0u) {
        atomicAdd(&valid_count[0], red_count[0]);
    }
}

// Largest absolute channel difference of two observed pixels.
fn colour_step(p: u32, q: u32) -> f32 {
    let a = vec3<f32>(target_image[3u * p], target_image[3u * p + 1u], target_image[3u * p + 2u]);
    let b = vec3<f32>(target_image[3u * q], target_image[3u * q + 1u], target_image[3u * q + 2u]);
    let d = abs(a - b);
    return max(max(d.x, d.y), d.z);
}

// Edge p -> q of the smoothness term: (penalty, w_pq psi'(D_q - D_p)).
fn edge(p: u32, q: u32) -> vec2<f32> {
    let wgt = exp(-params.smooth_gamma * colour_step(p, q));
    let diff = scalars[q].x - scalars[p].x;
    let eps = params.smooth_eps;
    let root = sqrt(diff * diff + eps * eps);
    return vec2<f32>(wgt * (root - eps), wgt * diff / root);
}

@compute @workgroup_size(256)
fn loss_pixels(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    let n = w * h;
    let p = gid.x;
    var sa = vec4<f32>(0.0);
    var sb = vec4<f32>(0.0);
    if (p < n) {
        // L1: mean over pixels and channels.
        let g1 = params.l1_weight / f32(3u * n);
        var l1 = 0.0;
        for (var c = 0u; c < 3u; c++) {
            let e = colour[3u * p + c] - target_image[3u * p + c];
            l1 += abs(e);
            up_colour[3u * p + c] = g1 * sign(e);
        }
        var dd = 0.0;
        var dv = 0.0;
        var maha = 0.0;
        var kl = 0.0;
        let valid = atomicLoad(&valid_count[0]);
        let s = scalars[p];
        if (valid > 0u && valid_track(p)) {
            let t = track[p];
            let r = s.x - t.x;
            if (params.maha_weight > 0.0) {
                let gm = params.maha_weight * (2.0 / f32(valid));
                maha = r * r / t.y;
                dd += gm * r / t.y;
            }
            if (params.kl_weight > 0.0) {
                let gk = params.kl_weight / f32(valid);
                let v = max(s.y, 0.0) + params.kl_floor;
                kl = 0.5 * (log(t.y / v) + (v + r * r) / t.y - 1.0);
                dd += gk * r / t.y;
                if (s.y >= 0.0) {
                    dv += gk * 0.5 * (1.0 / t.y - 1.0 / v);
                }
            }
        }
        var smooth_sum = 0.0;
        if (params.smooth_weight > 0.0) {
            let x = p % w;
            let y = p / w;
            var grad = 0.0;
            if (x + 1u < w) {
                let e = edge(p, p + 1u);
                smooth_sum += e.x;
                grad -= e.y;
            }
            if (y + 1u < h) {
                let e = edge(p, p + w);
                smooth_sum += e.x;
                grad -= e.y;
            }
            if (x > 0u) {
                grad += edge(p - 1u, p).y;
            }
            if (y > 0u) {
                grad += edge(p - w, p).y;
            }
            dd += params.smooth_weight / f32(n) * grad;
        }
        var acc = 0.0;
        var da = 0.0;
        if (params.acc_weight > 0.0) {
            let tr = 1.0 - s.z;
            let l0 = -abs(tr) / params.acc_scale;
            let l1b = params.acc_ln_beta - abs(1.0 - tr) / params.acc_scale;
            let m = max(l0, l1b);
            let u = exp(l0 - m);
            let v = exp(l1b - m);
            acc = -(m + log(u + v));
            let d_t = (u * sign(tr) - v * sign(1.0 - tr)) / (params.acc_scale * (u + v));
            da -= params.acc_weight / f32(n) * d_t;
        }
        up_scalars[p] = vec4<f32>(dd, dv, da, 0.0);
        sa = vec4<f32>(l1, maha, kl, smooth_sum);
        sb = vec4<f32>(acc, 0.0, 0.0, 0.0);
    }
    reduce_pair(lid, sa, sb);
    if (lid == 0u) {
        let base = wid.x * TERMS;
        partials[base] = red_a[0].x;
        partials[base + 1u] = red_a[0].y;
        partials[base + 2u] = red_a[0].z;
        partials[base + 3u] = red_a[0].w;
        partials[base + 4u] = red_b[0].x;
    }
}

// Horizontal zero-padded 'same' filter of the 15 moment sources of pixel p (taps in order).
@compute @workgroup_size(256)
fn ssim_rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let n = w * params.height;
    let p = gid.x;
    if (p >= n) {
        return;
    }
    let x = i32(p % w);
    let row = p - u32(x);
    var acc: array<f32, 15>;
    for (var k = 0u; k < 15u; k++) {
        acc[k] = 0.0;
    }
    for (var t = 0; t < 11; t++) {
        let sx = x + t - RADIUS;
        if (sx < 0 || sx >= i32(w)) {
            continue;
        }
        let g = window[t];
        let q = row + u32(sx);
        for (var c = 0u; c < 3u; c++) {
            let u = colour[3u * q + c];
            let v = target_image[3u * q + c];
            acc[c * 5u] += g * u;
            acc[c * 5u + 1u] += g * v;
            acc[c * 5u + 2u] += g * (u * u);
            acc[c * 5u + 3u] += g * (v * v);
            acc[c * 5u + 4u] += g * (u * v);
        }
    }
    for (var k = 0u; k < 15u; k++) {
        moments_a[p * 15u + k] = acc[k];
    }
}

// Vertical filter of the moments, then the SSIM map and its partials (9 per pixel).
@compute @workgroup_size(256)
fn ssim_cols(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    let n = w * h;
    let p = gid.x;
    var ssim = 0.0;
    if (p < n) {
        let y = i32(p / w);
        let x = p % w;
        var m: array<f32, 15>;
        for (var k = 0u; k < 15u; k++) {
            m[k] = 0.0;
        }
        for (var t = 0; t < 11; t++) {
            let sy = y + t - RADIUS;
            if (sy < 0 || sy >= i32(h)) {
                continue;
            }
            let g = window[t];
            let q = u32(sy) * w + x;
            for (var k = 0u; k < 15u; k++) {
                m[k] += g * moments_a[q * 15u + k];
            }
        }
        for (var c = 0u; c < 3u; c++) {
            let mx = m[c * 5u];
            let my = m[c * 5u + 1u];
            let exx = m[c * 5u + 2u];
            let eyy = m[c * 5u + 3u];
            let exy = m[c * 5u + 4u];
            let a1 = 2.0 * mx * my + SSIM_C1;
            let a2 = 2.0 * (exy - mx * my) + SSIM_C2;
            let b1 = mx * mx + my * my + SSIM_C1;
            let b2 = (exx - mx * mx) + (eyy - my * my) + SSIM_C2;
            let inv_b = 1.0 / (b1 * b2);
            let s = a1 * a2 * inv_b;
            ssim += s;
            moments_b[p * 9u + c * 3u] = 2.0 * my * (a2 - a1) * inv_b - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2);
            moments_b[p * 9u + c * 3u + 1u] = -s / b2;
            moments_b[p * 9u + c * 3u + 2u] = 2.0 * a1 * inv_b;
        }
    }
    reduce_pair(lid, vec4<f32>(ssim, 0.0, 0.0, 0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        partials[wid.x * TERMS + 5u] = red_a[0].x;
    }
}

// Horizontal filter of the 9 partials (the transposed zero-padded filter is the same filter).
@compute @workgroup_size(256)
fn ssim_back_rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let n = w * params.height;
    let p = gid.x;
    if (p >= n) {
        return;
    }
    let x = i32(p % w);
    let row = p - u32(x);
    var acc: array<f32, 9>;
    for (var k = 0u; k < 9u; k++) {
        acc[k] = 0.0;
    }
    for (var t = 0; t < 11; t++) {
        let sx = x + t - RADIUS;
        if (sx < 0 || sx >= i32(w)) {
            continue;
        }
        let g = window[t];
        let q = row + u32(sx);
        for (var k = 0u; k < 9u; k++) {
            acc[k] += g * moments_b[q * 9u + k];
        }
    }
    for (var k = 0u; k < 9u; k++) {
        moments_a[p * 9u + k] = acc[k];
    }
}

// Vertical filter of the row-filtered partials, then
// dL/dx += -ssim_weight / (3N) [G(dS/dmu) + 2 x G(dS/dE_xx) + y G(dS/dE_xy)].
@compute @workgroup_size(256)
fn ssim_back_cols(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    let n = w * h;
    let p = gid.x;
    if (p >= n) {
        return;
    }
    let y = i32(p / w);
    let x = p % w;
    var f: array<f32, 9>;
    for (var k = 0u; k < 9u; k++) {
        f[k] = 0.0;
    }
    for (var t = 0; t < 11; t++) {
        let sy = y + t - RADIUS;
        if (sy < 0 || sy >= i32(h)) {
            continue;
        }
        let g = window[t];
        let q = u32(sy) * w + x;
        for (var k = 0u; k < 9u; k++) {
            f[k] += g * moments_a[q * 9u + k];
        }
    }
    let scale = -params.ssim_weight / f32(3u * n);
    for (var c = 0u; c < 3u; c++) {
        let u = colour[3u * p + c];
        let v = target_image[3u * p + c];
        up_colour[3u * p + c] += scale * (f[c * 3u] + 2.0 * u * f[c * 3u + 1u] + v * f[c * 3u + 2u]);
    }
}

@compute @workgroup_size(256)
fn medium_sums(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let p = gid.x;
    var s = vec4<f32>(0.0);
    if (p < params.width * params.height) {
        s = vec4<f32>(c_med[3u * p], c_med[3u * p + 1u], c_med[3u * p + 2u], 0.0);
    }
    reduce_pair(lid, s, vec4<f32>(0.0));
    if (lid == 0u) {
        c_med_sums[wid.x] = red_a[0];
    }
}

// One workgroup: invocation i adds groups i, i + 256, ... in order, then a tree reduction;
// the mean goes after the groups.
@compute @workgroup_size(256)
fn medium_mean(@builtin(local_invocation_index) lid: u32) {
    let n = params.width * params.height;
    let groups = (n + WG - 1u) / WG;
    var s = vec4<f32>(0.0);
    for (var g = lid; g < groups; g += WG) {
        s += c_med_sums[g];
    }
    reduce_pair(lid, s, vec4<f32>(0.0));
    if (lid == 0u) {
        c_med_sums[groups] = red_a[0] / f32(n);
    }
}

@compute @workgroup_size(256)
fn medium_variation(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>) {
    let n = params.width * params.height;
    let p = gid.x;
    var value = 0.0;
    if (p < n) {
        let mean = c_med_sums[(n + WG - 1u) / WG];
        let g = params.mv_weight * (2.0 / f32(n));
        for (var c = 0u; c < 3u; c++) {
            let e = c_med[3u * p + c] - mean[c];
            value += e * e;
            d_c_med[3u * p + c] = g * e;
        }
    }
    reduce_pair(lid, vec4<f32>(value, 0.0, 0.0, 0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        partials[wid.x * TERMS + 6u] = red_a[0].x;
    }
}
