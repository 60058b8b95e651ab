// Projection with the EWA Jacobian, one thread per Gaussian (CPU reference:
// `project_gaussians` / `project_splat` / `tile_rect`, src/map/render/project.rs, same
// order of operations). Writes each splat (12 floats, three vec4s for the rasterisers: mean2d,
// conic.xy | conic.z, z, opacity, q_max | colour, 0; `SPLAT_FLOATS` of src/map/vulkan), its
// tile rectangle and its tile count (0 when culled).

const ALPHA_MIN: f32 = 0.003921568627450980; // 1/255
const SH_C0: f32 = 0.28209479177387814;
const SH_C1: f32 = 0.4886025119029199;
const PARAMS: u32 = 23u;
const SPLAT_FLOATS: u32 = 12u;

// Camera, pose and settings (`ProjectionSetup<f32>` plus the grid), flat scalars.
struct Setup {
    r00: f32, r01: f32, r02: f32,
    r10: f32, r11: f32, r12: f32,
    r20: f32, r21: f32, r22: f32,
    tx: f32, ty: f32, tz: f32,
    cam_x: f32, cam_y: f32, cam_z: f32,
    fx: f32, fy: f32, cx: f32, cy: f32,
    lim_x0: f32, lim_x1: f32, lim_y0: f32, lim_y1: f32,
    near_z: f32, blur: f32,
    n: u32, width: u32, height: u32, tile_size: u32, tiles_x: u32, tiles_y: u32, pad: u32,
}

@group(0) @binding(0) var<storage, read> setup: Setup;
// 23 floats per Gaussian: mean, log_scale, rotation (w, x, y, z), opacity_logit, f_dc, f_rest.
@group(0) @binding(1) var<storage, read> params: array<f32>;
@group(0) @binding(2) var<storage, read_write> splats: array<f32>;
@group(0) @binding(3) var<storage, read_write> rects: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read_write> tiles_touched: array<u32>;

fn quat_to_mat3(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    // Columns of the row-major [[1-2(yy+zz), 2(xy-wz), 2(xz+wy)], ...].
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

fn culled(i: u32) {
    for (var k = 0u; k < SPLAT_FLOATS; k = k + 1u) {
        splats[i * SPLAT_FLOATS + k] = 0.0;
    }
    rects[i] = vec4<u32>(0u);
    tiles_touched[i] = 0u;
}

// Logistic sigmoid written so neither branch overflows (as `math::sigmoid`).
fn sigmoid(x: f32) -> f32 {
    if (x >= 0.0) {
        return 1.0 / (1.0 + exp(-x));
    }
    let e = exp(x);
    return e / (1.0 + e);
}

fn is_finite(v: f32) -> bool {
    return abs(v) <= 3.4028234e38;
}

// One axis of the tile rectangle: pixel range [lo, hi] or lo > hi when empty.
fn axis(m: f32, r_in: f32, n: u32) -> vec2<f32> {
    let r = r_in * 1.0001 + 1e-3;
    let lo = max(ceil(m - r), 0.0);
    let hi = min(floor(m + r), f32(n) - 1.0);
    return vec2<f32>(lo, hi);
}

@compute @workgroup_size(256)
fn project_forward(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x;
    if (i >= setup.n) {
        return;
    }
    let b = i * PARAMS;
    let mean = vec3<f32>(params[b], params[b + 1u], params[b + 2u]);
    let log_scale = vec3<f32>(params[b + 3u], params[b + 4u], params[b + 5u]);
    let q = vec4<f32>(params[b + 6u], params[b + 7u], params[b + 8u], params[b + 9u]);
    let opacity_logit = params[b + 10u];
    let q_norm = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    if (!(q_norm > 0.0)) {
        culled(i);
        return;
    }
    let rq = quat_to_mat3(q / q_norm);
    let scale = exp(log_scale);
    // M = R diag(scale); Sigma_w = M M^T.
    let m = mat3x3<f32>(rq[0] * scale.x, rq[1] * scale.y, rq[2] * scale.z);
    let sigma_w = m * transpose(m);
    // r as columns of the row-major setup.
    let r = mat3x3<f32>(
        vec3<f32>(setup.r00, setup.r10, setup.r20),
        vec3<f32>(setup.r01, setup.r11, setup.r21),
        vec3<f32>(setup.r02, setup.r12, setup.r22),
    );
    let mean_c = r * mean + vec3<f32>(setup.tx, setup.ty, setup.tz);
    let z = mean_c.z;
    if (!(z >= setup.near_z)) {
        culled(i);
        return;
    }
    let sigma_c = r * sigma_w * transpose(r);
    let rx = mean_c.x / z;
    let ry = mean_c.y / z;
    let txz = vec2<f32>(min(max(rx, setup.lim_x0), setup.lim_x1), min(max(ry, setup.lim_y0), setup.lim_y1));
    let j0 = vec3<f32>(setup.fx / z, 0.0, -setup.fx * txz.x / z);
    let j1 = vec3<f32>(0.0, setup.fy / z, -setup.fy * txz.y / z);
    // js = J Sigma_c (rows); Sigma_c is symmetric so row a of J Sigma_c = Sigma_c * j_a.
    let js0 = vec3<f32>(
        j0.x * sigma_c[0][0] + j0.y * sigma_c[0][1] + j0.z * sigma_c[0][2],
        j0.x * sigma_c[1][0] + j0.y * sigma_c[1][1] + j0.z * sigma_c[1][2],
        j0.x * sigma_c[2][0] + j0.y * sigma_c[2][1] + j0.z * sigma_c[2][2],
    );
    let js1 = vec3<f32>(
        j1.x * sigma_c[0][0] + j1.y * sigma_c[0][1] + j1.z * sigma_c[0][2],
        j1.x * sigma_c[1][0] + j1.y * sigma_c[1][1] + j1.z * sigma_c[1][2],
        j1.x * sigma_c[2][0] + j1.y * sigma_c[2][1] + j1.z * sigma_c[2][2],
    );
    let ca = js0.x * j0.x + js0.y * j0.y + js0.z * j0.z + setup.blur;
    let cb = js0.x * j1.x + js0.y * j1.y + js0.z * j1.z;
    let cc = js1.x * j1.x + js1.y * j1.y + js1.z * j1.z + setup.blur;
    let det = ca * cc - cb * cb;
    if (!(det > 0.0)) {
        culled(i);
        return;
    }
    let v = mean - vec3<f32>(setup.cam_x, setup.cam_y, setup.cam_z);
    let dist = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
    let dir = v / dist;
    let opacity = sigmoid(opacity_logit);
    if (!(opacity >= ALPHA_MIN)) {
        culled(i);
        return;
    }
    let q_max = max(2.0 * log(255.0 * opacity), 0.0);
    let k = sqrt(q_max);
    let mean2d = vec2<f32>(setup.fx * mean_c.x / mean_c.z + setup.cx, setup.fy * mean_c.y / mean_c.z + setup.cy);
    let conic = vec3<f32>(cc / det, -cb / det, ca / det);
    let reach = vec2<f32>(k * sqrt(ca), k * sqrt(cc));
    if (!(is_finite(mean2d.x) && is_finite(mean2d.y) && is_finite(conic.x) && is_finite(conic.y) && is_finite(conic.z)
        && is_finite(reach.x) && is_finite(reach.y))) {
        culled(i);
        return;
    }
    var colour: vec3<f32>;
    for (var c = 0u; c < 3u; c = c + 1u) {
        let f_dc = params[b + 11u + c];
        let raw = 0.5 + SH_C0 * f_dc
            + SH_C1 * (-dir.y * params[b + 14u + c] + dir.z * params[b + 17u + c] - dir.x * params[b + 20u + c]);
        colour[c] = max(raw, 0.0);
    }
    let o = i * SPLAT_FLOATS;
    splats[o] = mean2d.x;
    splats[o + 1u] = mean2d.y;
    splats[o + 2u] = conic.x;
    splats[o + 3u] = conic.y;
    splats[o + 4u] = conic.z;
    splats[o + 5u] = z;
    splats[o + 6u] = opacity;
    splats[o + 7u] = q_max;
    splats[o + 8u] = colour.x;
    splats[o + 9u] = colour.y;
    splats[o + 10u] = colour.z;
    splats[o + 11u] = 0.0;
    let ax = axis(mean2d.x, reach.x, setup.width);
    let ay = axis(mean2d.y, reach.y, setup.height);
    var rect = vec4<u32>(0u);
    if (ax.x <= ax.y && ay.x <= ay.y) {
        let t = setup.tile_size;
        rect = vec4<u32>(u32(ax.x) / t, u32(ay.x) / t, u32(ax.y) / t + 1u, u32(ay.y) / t + 1u);
    }
    rects[i] = rect;
    tiles_touched[i] = (rect.z - rect.x) * (rect.w - rect.y);
}
