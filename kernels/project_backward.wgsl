// Projection backward, one thread per Gaussian (CPU reference: `project_backward` /
// `project_splat_backward` / `projection_tape`, src/map/render/{project_bwd,project}.rs, the
// same order of operations): the splat gradient of each Gaussian (from `reduce_isect_grads`)
// back through the conic inverse, the EWA projection, the covariance, the quaternion
// normalisation, the perspective mean, the SH colour and the sigmoid opacity. ADDS into the
// 23 parameter gradients of the Gaussian and its densification statistics (norm of the
// scaled screen-space gradient, pixels, views), as the CPU reference does; a Gaussian that
// touched no pixel is left alone (it adds zeros).
//
// Matrices are the CPU's row-major `[[T; 3]; 3]` as `array<vec3<f32>, 3>` (element [row][col]).

const SH_C0: f32 = 0.28209479177387814;
const SH_C1: f32 = 0.4886025119029199;
const PARAMS: u32 = 23u;
const GRAD_FLOATS: u32 = 12u;

// The `Setup` struct of project_forward.wgsl (`projection_setup_words`).
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

// 23 floats per Gaussian: mean, log_scale, rotation (w, x, y, z), opacity_logit, f_dc, f_rest.
@group(0) @binding(0) var<storage, read> params: array<f32>;
@group(0) @binding(1) var<storage, read> setup: Setup;
// Per Gaussian: 12 floats (the fields of `SplatGrad`) and the pixel count.
@group(0) @binding(2) var<storage, read> splat_grads: array<f32>;
@group(0) @binding(3) var<storage, read> splat_pixels: array<u32>;
// 23 floats per Gaussian, the layout of `params`.
@group(0) @binding(4) var<storage, read_write> grads: array<f32>;
@group(0) @binding(5) var<storage, read_write> densify_grad_norm: array<f32>;
@group(0) @binding(6) var<storage, read_write> pixels_touched: array<u32>;
@group(0) @binding(7) var<storage, read_write> views: array<u32>;

alias Mat3 = array<vec3<f32>, 3>;

fn mat3_mul(a_in: Mat3, b_in: Mat3) -> Mat3 {
    var a = a_in;
    var b = b_in;
    var o: Mat3;
    for (var i = 0u; i < 3u; i = i + 1u) {
        for (var j = 0u; j < 3u; j = j + 1u) {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    return o;
}

fn mat3_transpose(a: Mat3) -> Mat3 {
    return Mat3(vec3<f32>(a[0].x, a[1].x, a[2].x), vec3<f32>(a[0].y, a[1].y, a[2].y), vec3<f32>(a[0].z, a[1].z, a[2].z));
}

fn quat_to_mat3(q: vec4<f32>) -> Mat3 {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    return Mat3(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
        vec3<f32>(2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
        vec3<f32>(2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

fn quat_to_mat3_backward(q: vec4<f32>, g: Mat3) -> vec4<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let dw = -z * g[0].y + y * g[0].z + z * g[1].x - x * g[1].z - y * g[2].x + x * g[2].y;
    let dx = y * g[0].y + z * g[0].z + y * g[1].x - 2.0 * x * g[1].y - w * g[1].z + z * g[2].x + w * g[2].y - 2.0 * x * g[2].z;
    let dy = -2.0 * y * g[0].x + x * g[0].y + w * g[0].z + x * g[1].x + z * g[1].z - w * g[2].x + z * g[2].y - 2.0 * y * g[2].z;
    let dz = -2.0 * z * g[0].x - w * g[0].y + x * g[0].z + w * g[1].x - 2.0 * z * g[1].y + y * g[1].z + x * g[2].x + y * g[2].y;
    return vec4<f32>(2.0 * dw, 2.0 * dx, 2.0 * dy, 2.0 * dz);
}

fn sigmoid(x: f32) -> f32 {
    if (x >= 0.0) {
        return 1.0 / (1.0 + exp(-x));
    }
    let e = exp(x);
    return e / (1.0 + e);
}

@compute @workgroup_size(256)
fn project_backward(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) groups: vec3<u32>) {
    let i = gid.y * groups.x * 256u + gid.x;
    if (i >= setup.n) {
        return;
    }
    // No early returns below: a Gaussian without a gradient (no pixel touched, or culled)
    // still loads and stores, adding zeros (`valid`). On a CPU device (lavapipe) each buffer
    // access walks the vector's lanes, branching on each lane's mask: a sparse mask (most
    // Gaussians hidden, as at 320x240 with 100k) made those branches unpredictable and this
    // kernel 2.5x slower than with every lane active.
    let pixels = splat_pixels[i];
    let touched = pixels != 0u;
    let gb = i * GRAD_FLOATS;
    let g_mean2d = vec2<f32>(splat_grads[gb], splat_grads[gb + 1u]);
    let g_conic = vec3<f32>(splat_grads[gb + 2u], splat_grads[gb + 3u], splat_grads[gb + 4u]);
    let g_opacity = splat_grads[gb + 5u];
    let g_colour = vec3<f32>(splat_grads[gb + 6u], splat_grads[gb + 7u], splat_grads[gb + 8u]);
    let g_z = splat_grads[gb + 9u];
    let g_densify = vec2<f32>(splat_grads[gb + 10u], splat_grads[gb + 11u]);
    // Densification statistics, whether or not the projection has a gradient.
    densify_grad_norm[i] = densify_grad_norm[i] + select(0.0, sqrt(g_densify.x * g_densify.x + g_densify.y * g_densify.y), touched);
    pixels_touched[i] = pixels_touched[i] + pixels;
    views[i] = views[i] + select(0u, 1u, touched);

    // The projection tape (`projection_tape`).
    let b = i * PARAMS;
    let mean = vec3<f32>(params[b], params[b + 1u], params[b + 2u]);
    let log_scale = vec3<f32>(params[b + 3u], params[b + 4u], params[b + 5u]);
    let q = vec4<f32>(params[b + 6u], params[b + 7u], params[b + 8u], params[b + 9u]);
    let opacity_logit = params[b + 10u];
    let q_norm = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    var valid = touched && q_norm > 0.0;
    let qn = q / q_norm;
    let rq = quat_to_mat3(qn);
    let scale = exp(log_scale);
    let m = Mat3(rq[0] * scale, rq[1] * scale, rq[2] * scale);
    let sigma_w = mat3_mul(m, mat3_transpose(m));
    let r = Mat3(
        vec3<f32>(setup.r00, setup.r01, setup.r02),
        vec3<f32>(setup.r10, setup.r11, setup.r12),
        vec3<f32>(setup.r20, setup.r21, setup.r22),
    );
    let mean_c = vec3<f32>(
        r[0].x * mean.x + r[0].y * mean.y + r[0].z * mean.z + setup.tx,
        r[1].x * mean.x + r[1].y * mean.y + r[1].z * mean.z + setup.ty,
        r[2].x * mean.x + r[2].y * mean.y + r[2].z * mean.z + setup.tz,
    );
    let z = mean_c.z;
    valid = valid && z >= setup.near_z;
    var sigma_c = mat3_mul(mat3_mul(r, sigma_w), mat3_transpose(r));
    let rx = mean_c.x / z;
    let ry = mean_c.y / z;
    let txz = vec2<f32>(min(max(rx, setup.lim_x0), setup.lim_x1), min(max(ry, setup.lim_y0), setup.lim_y1));
    let inside = vec2<bool>(rx >= setup.lim_x0 && rx <= setup.lim_x1, ry >= setup.lim_y0 && ry <= setup.lim_y1);
    var j: array<vec3<f32>, 2>;
    j[0] = vec3<f32>(setup.fx / z, 0.0, -setup.fx * txz.x / z);
    j[1] = vec3<f32>(0.0, setup.fy / z, -setup.fy * txz.y / z);
    var js: array<vec3<f32>, 2>;
    for (var a = 0u; a < 2u; a = a + 1u) {
        for (var c = 0u; c < 3u; c = c + 1u) {
            js[a][c] = j[a][0] * sigma_c[0][c] + j[a][1] * sigma_c[1][c] + j[a][2] * sigma_c[2][c];
        }
    }
    let ca = js[0].x * j[0].x + js[0].y * j[0].y + js[0].z * j[0].z + setup.blur;
    let cb = js[0].x * j[1].x + js[0].y * j[1].y + js[0].z * j[1].z;
    let cc = js[1].x * j[1].x + js[1].y * j[1].y + js[1].z * j[1].z + setup.blur;
    let det = ca * cc - cb * cb;
    valid = valid && det > 0.0;
    let v = mean - vec3<f32>(setup.cam_x, setup.cam_y, setup.cam_z);
    let dist = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
    let dir = v / dist;

    // Conic (C/det, -B/det, A/det) back to Sigma_2d = [[A, B], [B, C]].
    let det2 = det * det;
    let d_a = (-g_conic.x * cc * cc + g_conic.y * cb * cc - g_conic.z * cb * cb) / det2;
    let d_b = (2.0 * g_conic.x * cb * cc - g_conic.y * (ca * cc + cb * cb) + 2.0 * g_conic.z * ca * cb) / det2;
    let d_c = (-g_conic.x * cb * cb + g_conic.y * cb * ca - g_conic.z * ca * ca) / det2;
    var g2: array<vec2<f32>, 2>;
    g2[0] = vec2<f32>(d_a, d_b / 2.0);
    g2[1] = vec2<f32>(d_b / 2.0, d_c);
    // dL/dJ = 2 G2 J W; dL/dW = J^T G2 J.
    var jw: array<vec3<f32>, 2>;
    for (var rr = 0u; rr < 2u; rr = rr + 1u) {
        for (var c = 0u; c < 3u; c = c + 1u) {
            jw[rr][c] = j[rr][0] * sigma_c[0][c] + j[rr][1] * sigma_c[1][c] + j[rr][2] * sigma_c[2][c];
        }
    }
    var g_j: array<vec3<f32>, 2>;
    for (var rr = 0u; rr < 2u; rr = rr + 1u) {
        for (var c = 0u; c < 3u; c = c + 1u) {
            g_j[rr][c] = 2.0 * (g2[rr][0] * jw[0][c] + g2[rr][1] * jw[1][c]);
        }
    }
    var g_w: Mat3;
    for (var rr = 0u; rr < 3u; rr = rr + 1u) {
        for (var c = 0u; c < 3u; c = c + 1u) {
            g_w[rr][c] = j[0][rr] * (g2[0][0] * j[0][c] + g2[0][1] * j[1][c]) + j[1][rr] * (g2[1][0] * j[0][c] + g2[1][1] * j[1][c]);
        }
    }
    // W = R Sigma_w R^T -> dL/dSigma_w = R^T gW R; Sigma_w = M M^T -> dL/dM = 2 gSigma_w M.
    let g_sigma_w = mat3_mul(mat3_mul(mat3_transpose(r), g_w), r);
    let g_m0 = mat3_mul(g_sigma_w, m);
    let g_m = Mat3(g_m0[0] * 2.0, g_m0[1] * 2.0, g_m0[2] * 2.0);
    // M = Rq diag(scale).
    var g_rq: Mat3;
    var g_log_scale = vec3<f32>(0.0);
    var rq_v = rq;
    var g_m_v = g_m;
    for (var col = 0u; col < 3u; col = col + 1u) {
        var g_scale = 0.0;
        for (var row = 0u; row < 3u; row = row + 1u) {
            g_rq[row][col] = g_m_v[row][col] * scale[col];
            g_scale = g_scale + g_m_v[row][col] * rq_v[row][col];
        }
        g_log_scale[col] = g_scale * scale[col];
    }
    let g_qn = quat_to_mat3_backward(qn, g_rq);
    let qdot = g_qn.x * qn.x + g_qn.y * qn.y + g_qn.z * qn.z + g_qn.w * qn.w;
    let g_rotation = (g_qn - qn * qdot) / q_norm;

    // Camera-frame mean: the Jacobian, the projected mean, and the direct depth gradient.
    let x = mean_c.x;
    let y = mean_c.y;
    let fx = setup.fx;
    let fy = setup.fy;
    let z2 = z * z;
    var g_mean_c = vec3<f32>(0.0);
    g_mean_c.z = g_mean_c.z + (-g_j[0].x * fx / z2 - g_j[1].y * fy / z2);
    // J[0][2] = -fx txz / z with txz = x/z inside the clamp, a constant outside it.
    {
        let g = g_j[0].z;
        if (inside.x) {
            g_mean_c.x = g_mean_c.x + (-g * fx / z2);
            g_mean_c.z = g_mean_c.z + 2.0 * g * fx * txz.x / z2;
        } else {
            g_mean_c.z = g_mean_c.z + g * fx * txz.x / z2;
        }
    }
    {
        let g = g_j[1].z;
        if (inside.y) {
            g_mean_c.y = g_mean_c.y + (-g * fy / z2);
            g_mean_c.z = g_mean_c.z + 2.0 * g * fy * txz.y / z2;
        } else {
            g_mean_c.z = g_mean_c.z + g * fy * txz.y / z2;
        }
    }
    g_mean_c.x = g_mean_c.x + g_mean2d.x * fx / z;
    g_mean_c.y = g_mean_c.y + g_mean2d.y * fy / z;
    g_mean_c.z = g_mean_c.z + (-(g_mean2d.x * fx * x + g_mean2d.y * fy * y) / z2 + g_z);
    // R^T g_mean_c.
    var g_mean = vec3<f32>(
        r[0].x * g_mean_c.x + r[1].x * g_mean_c.y + r[2].x * g_mean_c.z,
        r[0].y * g_mean_c.x + r[1].y * g_mean_c.y + r[2].y * g_mean_c.z,
        r[0].z * g_mean_c.x + r[1].z * g_mean_c.y + r[2].z * g_mean_c.z,
    );

    // SH colour, clamped at 0.
    var g_f_dc = vec3<f32>(0.0);
    var g_f_rest: array<f32, 9>;
    for (var k = 0u; k < 9u; k = k + 1u) {
        g_f_rest[k] = 0.0;
    }
    var g_dir = vec3<f32>(0.0);
    for (var c = 0u; c < 3u; c = c + 1u) {
        let f_dc = params[b + 11u + c];
        let f1 = params[b + 14u + c];
        let f2 = params[b + 17u + c];
        let f3 = params[b + 20u + c];
        let colour_raw = 0.5 + SH_C0 * f_dc + SH_C1 * (-dir.y * f1 + dir.z * f2 - dir.x * f3);
        if (colour_raw < 0.0) {
            continue;
        }
        let gcol = g_colour[c];
        g_f_dc[c] = SH_C0 * gcol;
        g_f_rest[c] = -SH_C1 * dir.y * gcol;
        g_f_rest[3u + c] = SH_C1 * dir.z * gcol;
        g_f_rest[6u + c] = -SH_C1 * dir.x * gcol;
        g_dir.x = g_dir.x + (-SH_C1 * f3 * gcol);
        g_dir.y = g_dir.y + (-SH_C1 * f1 * gcol);
        g_dir.z = g_dir.z + SH_C1 * f2 * gcol;
    }
    let proj = g_dir.x * dir.x + g_dir.y * dir.y + g_dir.z * dir.z;
    g_mean = g_mean + (g_dir - dir * proj) / dist;

    let o = sigmoid(opacity_logit);
    let g_opacity_logit = g_opacity * o * (1.0 - o);

    grads[b] = grads[b] + select(0.0, g_mean.x, valid);
    grads[b + 1u] = grads[b + 1u] + select(0.0, g_mean.y, valid);
    grads[b + 2u] = grads[b + 2u] + select(0.0, g_mean.z, valid);
    grads[b + 3u] = grads[b + 3u] + select(0.0, g_log_scale.x, valid);
    grads[b + 4u] = grads[b + 4u] + select(0.0, g_log_scale.y, valid);
    grads[b + 5u] = grads[b + 5u] + select(0.0, g_log_scale.z, valid);
    grads[b + 6u] = grads[b + 6u] + select(0.0, g_rotation.x, valid);
    grads[b + 7u] = grads[b + 7u] + select(0.0, g_rotation.y, valid);
    grads[b + 8u] = grads[b + 8u] + select(0.0, g_rotation.z, valid);
    grads[b + 9u] = grads[b + 9u] + select(0.0, g_rotation.w, valid);
    grads[b + 10u] = grads[b + 10u] + select(0.0, g_opacity_logit, valid);
    grads[b + 11u] = grads[b + 11u] + select(0.0, g_f_dc.x, valid);
    grads[b + 12u] = grads[b + 12u] + select(0.0, g_f_dc.y, valid);
    grads[b + 13u] = grads[b + 13u] + select(0.0, g_f_dc.z, valid);
    for (var k = 0u; k < 9u; k = k + 1u) {
        grads[b + 14u + k] = grads[b + 14u + k] + select(0.0, g_f_rest[k], valid);
    }
}
