// Shared by rasterize.wgsl and rasterize_backward.wgsl (`//!include pixel_medium.wgsl`; it
// needs their `params`, `c_med`, `sigma_att` and `sigma_bs`): what a pixel reads once, its
// position, the norm of its ray per unit depth and its medium (clamped into the image for a
// thread outside it).

struct PixelMedium {
    fx: f32,
    fy: f32,
    ray_norm: f32,
    m_c: vec3<f32>,
    m_att: vec3<f32>,
    m_bs: vec3<f32>,
}

fn pixel_medium(x: u32, y: u32) -> PixelMedium {
    var p: PixelMedium;
    p.fx = f32(x);
    p.fy = f32(y);
    let xn = (p.fx - params.cx) / params.fx;
    let yn = (p.fy - params.cy) / params.fy;
    p.ray_norm = sqrt(xn * xn + yn * yn + 1.0);
    let pix = min(y, params.height - 1u) * params.width + min(x, params.width - 1u);
    p.m_c = vec3<f32>(c_med[pix * 3u], c_med[pix * 3u + 1u], c_med[pix * 3u + 2u]);
    p.m_att = vec3<f32>(sigma_att[pix * 3u], sigma_att[pix * 3u + 1u], sigma_att[pix * 3u + 2u]);
    p.m_bs = vec3<f32>(sigma_bs[pix * 3u], sigma_bs[pix * 3u + 1u], sigma_bs[pix * 3u + 2u]);
    return p;
}
