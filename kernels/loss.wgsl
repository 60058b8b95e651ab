// The mapping losses (Eq. 12-14) and their gradients with respect to the rendered images
// (CPU reference: `total_loss` and its terms in src/map/loss.rs, the same formulas, the same
// order of additions per pixel). One invocation per pixel, 1-D grid of 256-wide workgroups.
//
//   count_valid         tracked pixels valid for the depth terms -> valid_count (a u32 atomic
//                       add per subgroup: integer sums, exact and order-free)
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
// 0 L1, 1 Mahalanobis, 2 KL, 3 smoothness, 4 accuracy, 5 SSIM map, 6 medium variation, 7 squared
// colour error for the PSNR): `subgroupAdd` within each subgroup, then invocation 0 adds the
// subgroups' sums in subgroup order (one barrier); the host adds the workgroups' sums in
// workgroup order. The SSIM passes keep RGB in vectors (no per-channel arrays indexed at run
// time, which lavapipe spills to memory). No float atomics:
// the results are bit-identical from run to run on one device.

struct LossParams {
    width: u32,
    height: u32,
    // 1: the KL's spread is one-sided (LossConfig::kl_one_sided)
    kl_one_sided: u32,
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
// SSIM scratch: the five moments (then the row-filtered partials) and the partials, RGB in
// vec4 slots: moments_a[5 p + k] / moments_a[3 p + k], moments_b[3 p + k].
@group(0) @binding(9) var<storage, read_write> moments_a: array<vec4<f32>>;
@group(0) @binding(10) var<storage, read_write> moments_b: array<vec4<f32>>;
// Medium planes' c_med (RGB per pixel) and dL/dc_med.
@group(0) @binding(11) var<storage, read> c_med: array<f32>;
@group(0) @binding(12) var<storage, read_write> d_c_med: array<f32>;
// Per-workgroup c_med sums (4 per group), then the mean (4 floats after the groups).
@group(0) @binding(13) var<storage, read_write> c_med_sums: array<vec4<f32>>;

// Per-subgroup sums of a reduction (at most 256 subgroups of one lane; 64 of four).
var<workgroup> red_a: array<vec4<f32>, 256>;
var<workgroup> red_b: array<vec4<f32>, 256>;

// Sums two vec4 over the workgroup in a fixed order: `subgroupAdd` within each subgroup, then
// invocation 0 adds the subgroups' sums in subgroup order (returned to invocation 0 only).
// Every invocation of the workgroup must call it (one barrier).
fn reduce_pair(lid: u32, lane: u32, sg_id: u32, sg_count: u32, a: vec4<f32>, b: vec4<f32>) -> array<vec4<f32>, 2> {
    let sa = subgroupAdd(a);
    let sb = subgroupAdd(b);
    if (lane == 0u) {
        red_a[sg_id] = sa;
        red_b[sg_id] = sb;
    }
    workgroupBarrier();
    var out = array<vec4<f32>, 2>(vec4<f32>(0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        for (var i = 0u; i < sg_count; i++) {
            out[0] += red_a[i];
            out[1] += red_b[i];
        }
    }
    return out;
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
fn count_valid(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(subgroup_invocation_id) lane: u32) {
    let p = gid.x;
    var v = 0u;
    if (p < params.width * params.height && valid_track(p)) {
        v = 1u;
    }
    let total = subgroupAdd(v);
    if (lane == 0u && total > 0u) {
        atomicAdd(&valid_count[0], total);
    }
}

fn rgb(buf_index: u32) -> vec3<f32> {
    return vec3<f32>(target_image[buf_index], target_image[buf_index + 1u], target_image[buf_index + 2u]);
}

fn rendered_rgb(p: u32) -> vec3<f32> {
    return vec3<f32>(colour[3u * p], colour[3u * p + 1u], colour[3u * p + 2u]);
}

// Largest absolute channel difference of two observed pixels.
fn colour_step(p: u32, q: u32) -> f32 {
    let d = abs(rgb(3u * p) - rgb(3u * q));
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
fn loss_pixels(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>,
               @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let w = params.width;
    let h = params.height;
    let n = w * h;
    let p = gid.x;
    var sa = vec4<f32>(0.0);
    var sb = vec4<f32>(0.0);
    if (p < n) {
        // L1: mean over pixels and channels.
        let g1 = params.l1_weight / f32(3u * n);
        let e = rendered_rgb(p) - rgb(3u * p);
        let l1 = abs(e.x) + abs(e.y) + abs(e.z);
        let se = e.x * e.x + e.y * e.y + e.z * e.z;
        let d_l1 = g1 * sign(e);
        up_colour[3u * p] = d_l1.x;
        up_colour[3u * p + 1u] = d_l1.y;
        up_colour[3u * p + 2u] = d_l1.z;
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
                let narrower = params.kl_one_sided != 0u && v < t.y;
                let v_eff = select(v, t.y, narrower);
                kl = 0.5 * (log(t.y / v_eff) + (v_eff + r * r) / t.y - 1.0);
                dd += gk * r / t.y;
                if (s.y >= 0.0 && !narrower) {
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
        sb = vec4<f32>(acc, se, 0.0, 0.0);
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, sa, sb);
    if (lid == 0u) {
        let base = wid.x * TERMS;
        partials[base] = sums[0].x;
        partials[base + 1u] = sums[0].y;
        partials[base + 2u] = sums[0].z;
        partials[base + 3u] = sums[0].w;
        partials[base + 4u] = sums[1].x;
        partials[base + 7u] = sums[1].y;
    }
}

// Horizontal zero-padded 'same' filter of the moment sources of pixel p (taps in order), as
// five RGB vectors: x, y, x^2, y^2, xy -> moments_a[5 p + k].
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
    var mx = vec3<f32>(0.0);
    var my = vec3<f32>(0.0);
    var exx = vec3<f32>(0.0);
    var eyy = vec3<f32>(0.0);
    var exy = vec3<f32>(0.0);
    for (var t = 0; t < 11; t++) {
        let sx = x + t - RADIUS;
        if (sx < 0 || sx >= i32(w)) {
            continue;
        }
        let g = window[t];
        let q = row + u32(sx);
        let u = rendered_rgb(q);
        let v = rgb(3u * q);
        mx += g * u;
        my += g * v;
        exx += g * (u * u);
        eyy += g * (v * v);
        exy += g * (u * v);
    }
    moments_a[5u * p] = vec4<f32>(mx, 0.0);
    moments_a[5u * p + 1u] = vec4<f32>(my, 0.0);
    moments_a[5u * p + 2u] = vec4<f32>(exx, 0.0);
    moments_a[5u * p + 3u] = vec4<f32>(eyy, 0.0);
    moments_a[5u * p + 4u] = vec4<f32>(exy, 0.0);
}

// Vertical filter of the moments, then the SSIM map and its partials dS/dmu_x, dS/dE_xx,
// dS/dE_xy -> moments_b[3 p + k], per channel.
@compute @workgroup_size(256)
fn ssim_cols(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>,
             @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let w = params.width;
    let h = params.height;
    let n = w * h;
    let p = gid.x;
    var ssim = 0.0;
    if (p < n) {
        let y = i32(p / w);
        let x = p % w;
        var mx = vec3<f32>(0.0);
        var my = vec3<f32>(0.0);
        var exx = vec3<f32>(0.0);
        var eyy = vec3<f32>(0.0);
        var exy = vec3<f32>(0.0);
        for (var t = 0; t < 11; t++) {
            let sy = y + t - RADIUS;
            if (sy < 0 || sy >= i32(h)) {
                continue;
            }
            let g = window[t];
            let q = 5u * (u32(sy) * w + x);
            mx += g * moments_a[q].xyz;
            my += g * moments_a[q + 1u].xyz;
            exx += g * moments_a[q + 2u].xyz;
            eyy += g * moments_a[q + 3u].xyz;
            exy += g * moments_a[q + 4u].xyz;
        }
        let a1 = 2.0 * mx * my + SSIM_C1;
        let a2 = 2.0 * (exy - mx * my) + SSIM_C2;
        let b1 = mx * mx + my * my + SSIM_C1;
        let b2 = (exx - mx * mx) + (eyy - my * my) + SSIM_C2;
        let inv_b = 1.0 / (b1 * b2);
        let s = a1 * a2 * inv_b;
        ssim = s.x + s.y + s.z;
        moments_b[3u * p] = vec4<f32>(2.0 * my * (a2 - a1) * inv_b - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2), 0.0);
        moments_b[3u * p + 1u] = vec4<f32>(-s / b2, 0.0);
        moments_b[3u * p + 2u] = vec4<f32>(2.0 * a1 * inv_b, 0.0);
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, vec4<f32>(ssim, 0.0, 0.0, 0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        partials[wid.x * TERMS + 5u] = sums[0].x;
    }
}

// Horizontal filter of the partials (the transposed zero-padded filter is the same filter)
// -> moments_a[3 p + k].
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
    var f0 = vec4<f32>(0.0);
    var f1 = vec4<f32>(0.0);
    var f2 = vec4<f32>(0.0);
    for (var t = 0; t < 11; t++) {
        let sx = x + t - RADIUS;
        if (sx < 0 || sx >= i32(w)) {
            continue;
        }
        let g = window[t];
        let q = 3u * (row + u32(sx));
        f0 += g * moments_b[q];
        f1 += g * moments_b[q + 1u];
        f2 += g * moments_b[q + 2u];
    }
    moments_a[3u * p] = f0;
    moments_a[3u * p + 1u] = f1;
    moments_a[3u * p + 2u] = f2;
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
    var f0 = vec3<f32>(0.0);
    var f1 = vec3<f32>(0.0);
    var f2 = vec3<f32>(0.0);
    for (var t = 0; t < 11; t++) {
        let sy = y + t - RADIUS;
        if (sy < 0 || sy >= i32(h)) {
            continue;
        }
        let g = window[t];
        let q = 3u * (u32(sy) * w + x);
        f0 += g * moments_a[q].xyz;
        f1 += g * moments_a[q + 1u].xyz;
        f2 += g * moments_a[q + 2u].xyz;
    }
    let scale = -params.ssim_weight / f32(3u * n);
    let u = rendered_rgb(p);
    let v = rgb(3u * p);
    let d = scale * (f0 + 2.0 * u * f1 + v * f2);
    up_colour[3u * p] += d.x;
    up_colour[3u * p + 1u] += d.y;
    up_colour[3u * p + 2u] += d.z;
}

@compute @workgroup_size(256)
fn medium_sums(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>,
               @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let p = gid.x;
    var s = vec4<f32>(0.0);
    if (p < params.width * params.height) {
        s = vec4<f32>(c_med[3u * p], c_med[3u * p + 1u], c_med[3u * p + 2u], 0.0);
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, s, vec4<f32>(0.0));
    if (lid == 0u) {
        c_med_sums[wid.x] = sums[0];
    }
}

// One workgroup: invocation i adds groups i, i + 256, ... in order, then the workgroup sum;
// the mean goes after the groups.
@compute @workgroup_size(256)
fn medium_mean(@builtin(local_invocation_index) lid: u32,
               @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let n = params.width * params.height;
    let groups = (n + WG - 1u) / WG;
    var s = vec4<f32>(0.0);
    for (var g = lid; g < groups; g += WG) {
        s += c_med_sums[g];
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, s, vec4<f32>(0.0));
    if (lid == 0u) {
        c_med_sums[groups] = sums[0] / f32(n);
    }
}

@compute @workgroup_size(256)
fn medium_variation(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>,
                    @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let n = params.width * params.height;
    let p = gid.x;
    var value = 0.0;
    if (p < n) {
        let mean = c_med_sums[(n + WG - 1u) / WG].xyz;
        let g = params.mv_weight * (2.0 / f32(n));
        let e = vec3<f32>(c_med[3u * p], c_med[3u * p + 1u], c_med[3u * p + 2u]) - mean;
        value = e.x * e.x + e.y * e.y + e.z * e.z;
        let d = g * e;
        d_c_med[3u * p] = d.x;
        d_c_med[3u * p + 1u] = d.y;
        d_c_med[3u * p + 2u] = d.z;
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, vec4<f32>(value, 0.0, 0.0, 0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        partials[wid.x * TERMS + 6u] = sums[0].x;
    }
}

// --- CPU-device variants of the SSIM filters (`GpuLoss::sliding_ssim`) -------------------
// The filters above load their 11 taps' sources for every pixel; on a CPU device (lavapipe)
// every such load is a loop over the lanes. These give each invocation a segment of SEG
// pixels of one row (`*_rows_sliding`: lanes on consecutive rows) or of one column
// (`*_cols_sliding`: lanes on consecutive columns) and slide the window along it, loading each
// source once. A tap outside the image holds zeros and adds exactly nothing, so every sum has
// the same terms in the same order as above: the same bits on lavapipe (the H100's compiler
// gives the last bits of dL/dC otherwise, within tolerance). `ssim_cols_sliding` leaves each
// pixel's SSIM (its channels' sum) in moments_b[3 p].w; `ssim_sum` adds it up by workgroups
// of 256 pixels exactly as `ssim_cols` does.

const SEG: u32 = 32u;

// Invocation i's segment: along row `line` (lanes on consecutive rows) or column `line`
// (lanes on consecutive columns), positions first..end; none past the last.
struct Segment {
    valid: bool,
    line: u32,
    first: u32,
    end: u32,
}

fn segment(i: u32, lines: u32, len: u32) -> Segment {
    let first = i / lines * SEG;
    return Segment(i < (len + SEG - 1u) / SEG * lines, i % lines, first, min(first + SEG, len));
}

// Whether position first + t - 6 (slot t before the first shift) lies in 0..len.
fn slot_in(first: u32, t: u32, len: u32) -> bool {
    return first + t >= 6u && first + t - 6u < len;
}

fn taps() -> array<f32, 11> {
    var g: array<f32, 11>;
    for (var t = 0u; t < 11u; t++) {
        g[t] = window[t];
    }
    return g;
}

@compute @workgroup_size(64)
fn ssim_rows_sliding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let seg = segment(gid.x, params.height, w);
    if (!seg.valid) {
        return;
    }
    let x0 = seg.first;
    let x1 = seg.end;
    let row = seg.line * w;
    let g = taps();
    // Slot t: the sources at x - 5 + t once shifted for pixel x.
    var su: array<vec3<f32>, 11>;
    var sv: array<vec3<f32>, 11>;
    for (var t = 1u; t < 11u; t++) {
        if (slot_in(x0, t, w)) {
            let sx = x0 + t - 6u;
            su[t] = rendered_rgb(row + sx);
            sv[t] = rgb(3u * (row + sx));
        }
    }
    for (var x = x0; x < x1; x++) {
        for (var t = 0u; t < 10u; t++) {
            su[t] = su[t + 1u];
            sv[t] = sv[t + 1u];
        }
        su[10] = vec3<f32>(0.0);
        sv[10] = vec3<f32>(0.0);
        if (x + 5u < w) {
            su[10] = rendered_rgb(row + x + 5u);
            sv[10] = rgb(3u * (row + x + 5u));
        }
        var mx = vec3<f32>(0.0);
        var my = vec3<f32>(0.0);
        var exx = vec3<f32>(0.0);
        var eyy = vec3<f32>(0.0);
        var exy = vec3<f32>(0.0);
        for (var t = 0u; t < 11u; t++) {
            let u = su[t];
            let v = sv[t];
            mx += g[t] * u;
            my += g[t] * v;
            exx += g[t] * (u * u);
            eyy += g[t] * (v * v);
            exy += g[t] * (u * v);
        }
        let p = row + x;
        moments_a[5u * p] = vec4<f32>(mx, 0.0);
        moments_a[5u * p + 1u] = vec4<f32>(my, 0.0);
        moments_a[5u * p + 2u] = vec4<f32>(exx, 0.0);
        moments_a[5u * p + 3u] = vec4<f32>(eyy, 0.0);
        moments_a[5u * p + 4u] = vec4<f32>(exy, 0.0);
    }
}

@compute @workgroup_size(64)
fn ssim_cols_sliding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    let seg = segment(gid.x, w, h);
    if (!seg.valid) {
        return;
    }
    let x = seg.line;
    let y0 = seg.first;
    let y1 = seg.end;
    let g = taps();
    var rmx: array<vec3<f32>, 11>;
    var rmy: array<vec3<f32>, 11>;
    var rxx: array<vec3<f32>, 11>;
    var ryy: array<vec3<f32>, 11>;
    var rxy: array<vec3<f32>, 11>;
    for (var t = 1u; t < 11u; t++) {
        if (slot_in(y0, t, h)) {
            let sy = y0 + t - 6u;
            let q = 5u * (sy * w + x);
            rmx[t] = moments_a[q].xyz;
            rmy[t] = moments_a[q + 1u].xyz;
            rxx[t] = moments_a[q + 2u].xyz;
            ryy[t] = moments_a[q + 3u].xyz;
            rxy[t] = moments_a[q + 4u].xyz;
        }
    }
    for (var y = y0; y < y1; y++) {
        for (var t = 0u; t < 10u; t++) {
            rmx[t] = rmx[t + 1u];
            rmy[t] = rmy[t + 1u];
            rxx[t] = rxx[t + 1u];
            ryy[t] = ryy[t + 1u];
            rxy[t] = rxy[t + 1u];
        }
        rmx[10] = vec3<f32>(0.0);
        rmy[10] = vec3<f32>(0.0);
        rxx[10] = vec3<f32>(0.0);
        ryy[10] = vec3<f32>(0.0);
        rxy[10] = vec3<f32>(0.0);
        if (y + 5u < h) {
            let q = 5u * ((y + 5u) * w + x);
            rmx[10] = moments_a[q].xyz;
            rmy[10] = moments_a[q + 1u].xyz;
            rxx[10] = moments_a[q + 2u].xyz;
            ryy[10] = moments_a[q + 3u].xyz;
            rxy[10] = moments_a[q + 4u].xyz;
        }
        var mx = vec3<f32>(0.0);
        var my = vec3<f32>(0.0);
        var exx = vec3<f32>(0.0);
        var eyy = vec3<f32>(0.0);
        var exy = vec3<f32>(0.0);
        for (var t = 0u; t < 11u; t++) {
            mx += g[t] * rmx[t];
            my += g[t] * rmy[t];
            exx += g[t] * rxx[t];
            eyy += g[t] * ryy[t];
            exy += g[t] * rxy[t];
        }
        let a1 = 2.0 * mx * my + SSIM_C1;
        let a2 = 2.0 * (exy - mx * my) + SSIM_C2;
        let b1 = mx * mx + my * my + SSIM_C1;
        let b2 = (exx - mx * mx) + (eyy - my * my) + SSIM_C2;
        let inv_b = 1.0 / (b1 * b2);
        let s = a1 * a2 * inv_b;
        let p = y * w + x;
        moments_b[3u * p] = vec4<f32>(2.0 * my * (a2 - a1) * inv_b - 2.0 * mx * s * (1.0 / b1 - 1.0 / b2), s.x + s.y + s.z);
        moments_b[3u * p + 1u] = vec4<f32>(-s / b2, 0.0);
        moments_b[3u * p + 2u] = vec4<f32>(2.0 * a1 * inv_b, 0.0);
    }
}

// The SSIM map's sum by workgroups of 256 pixels (after `ssim_cols_sliding`).
@compute @workgroup_size(256)
fn ssim_sum(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>,
            @builtin(subgroup_invocation_id) lane: u32, @builtin(subgroup_id) sg_id: u32, @builtin(num_subgroups) sg_count: u32) {
    let p = gid.x;
    var ssim = 0.0;
    if (p < params.width * params.height) {
        ssim = moments_b[3u * p].w;
    }
    let sums = reduce_pair(lid, lane, sg_id, sg_count, vec4<f32>(ssim, 0.0, 0.0, 0.0), vec4<f32>(0.0));
    if (lid == 0u) {
        partials[wid.x * TERMS + 5u] = sums[0].x;
    }
}

@compute @workgroup_size(64)
fn ssim_back_rows_sliding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let seg = segment(gid.x, params.height, w);
    if (!seg.valid) {
        return;
    }
    let x0 = seg.first;
    let x1 = seg.end;
    let row = seg.line * w;
    let g = taps();
    var r0: array<vec4<f32>, 11>;
    var r1: array<vec4<f32>, 11>;
    var r2: array<vec4<f32>, 11>;
    for (var t = 1u; t < 11u; t++) {
        if (slot_in(x0, t, w)) {
            let sx = x0 + t - 6u;
            let q = 3u * (row + sx);
            r0[t] = moments_b[q];
            r1[t] = moments_b[q + 1u];
            r2[t] = moments_b[q + 2u];
        }
    }
    for (var x = x0; x < x1; x++) {
        for (var t = 0u; t < 10u; t++) {
            r0[t] = r0[t + 1u];
            r1[t] = r1[t + 1u];
            r2[t] = r2[t + 1u];
        }
        r0[10] = vec4<f32>(0.0);
        r1[10] = vec4<f32>(0.0);
        r2[10] = vec4<f32>(0.0);
        if (x + 5u < w) {
            let q = 3u * (row + x + 5u);
            r0[10] = moments_b[q];
            r1[10] = moments_b[q + 1u];
            r2[10] = moments_b[q + 2u];
        }
        var f0 = vec4<f32>(0.0);
        var f1 = vec4<f32>(0.0);
        var f2 = vec4<f32>(0.0);
        for (var t = 0u; t < 11u; t++) {
            f0 += g[t] * r0[t];
            f1 += g[t] * r1[t];
            f2 += g[t] * r2[t];
        }
        let p = row + x;
        moments_a[3u * p] = f0;
        moments_a[3u * p + 1u] = f1;
        moments_a[3u * p + 2u] = f2;
    }
}

@compute @workgroup_size(64)
fn ssim_back_cols_sliding(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    let seg = segment(gid.x, w, h);
    if (!seg.valid) {
        return;
    }
    let x = seg.line;
    let y0 = seg.first;
    let y1 = seg.end;
    let g = taps();
    var r0: array<vec3<f32>, 11>;
    var r1: array<vec3<f32>, 11>;
    var r2: array<vec3<f32>, 11>;
    for (var t = 1u; t < 11u; t++) {
        if (slot_in(y0, t, h)) {
            let sy = y0 + t - 6u;
            let q = 3u * (sy * w + x);
            r0[t] = moments_a[q].xyz;
            r1[t] = moments_a[q + 1u].xyz;
            r2[t] = moments_a[q + 2u].xyz;
        }
    }
    let scale = -params.ssim_weight / f32(3u * w * h);
    for (var y = y0; y < y1; y++) {
        for (var t = 0u; t < 10u; t++) {
            r0[t] = r0[t + 1u];
            r1[t] = r1[t + 1u];
            r2[t] = r2[t + 1u];
        }
        r0[10] = vec3<f32>(0.0);
        r1[10] = vec3<f32>(0.0);
        r2[10] = vec3<f32>(0.0);
        if (y + 5u < h) {
            let q = 3u * ((y + 5u) * w + x);
            r0[10] = moments_a[q].xyz;
            r1[10] = moments_a[q + 1u].xyz;
            r2[10] = moments_a[q + 2u].xyz;
        }
        var f0 = vec3<f32>(0.0);
        var f1 = vec3<f32>(0.0);
        var f2 = vec3<f32>(0.0);
        for (var t = 0u; t < 11u; t++) {
            f0 += g[t] * r0[t];
            f1 += g[t] * r1[t];
            f2 += g[t] * r2[t];
        }
        let p = y * w + x;
        let u = rendered_rgb(p);
        let v = rgb(3u * p);
        let d = scale * (f0 + 2.0 * u * f1 + v * f2);
        up_colour[3u * p] += d.x;
        up_colour[3u * p + 1u] += d.y;
        up_colour[3u * p + 2u] += d.z;
    }
}
