// The medium planes' upstream gradient of a mapper step, one invocation per pixel (CPU
// reference: `Mapper::step_on`: the renderer's dL/dmedium plus the loss's own dL/dc_med
// (`total_loss`, the medium-variation term), then `MediumPrior::loss_and_grad`
// (src/map/medium_estimate.rs; f32 here, f64 there), then `fold_single_coefficient` when one
// coefficient serves both terms). Adds in place into the rasteriser backward's medium
// gradients, which `medium.interpolate_adjoint_rows` then reads.

struct PriorParams {
    n_pixels: u32,
    // The held coefficients of channel c: bit c beta_D, bit 3 + c beta_B, bit 6 + c B_inf.
    held: u32,
    // 1: sigma_bs is tied to sigma_att (fold its gradient into sigma_att).
    single: u32,
    pad0: u32,
    // weight / pixels, 1 / rel_std^2, 1 / b_inf_std^2
    k: f32,
    inv_s2: f32,
    inv_sb2: f32,
    pad1: f32,
    ln_beta_d: vec4<f32>,
    ln_beta_b: vec4<f32>,
    b_inf: vec4<f32>,
}

var<immediate> params: PriorParams;

@group(0) @binding(0) var<storage, read> c_med: array<f32>;
@group(0) @binding(1) var<storage, read> sigma_att: array<f32>;
@group(0) @binding(2) var<storage, read> sigma_bs: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad_c_med: array<f32>;
@group(0) @binding(4) var<storage, read_write> grad_sigma_att: array<f32>;
@group(0) @binding(5) var<storage, read_write> grad_sigma_bs: array<f32>;
@group(0) @binding(6) var<storage, read> d_c_med: array<f32>;

@compute @workgroup_size(256)
fn medium_upstream(@builtin(global_invocation_id) gid: vec3<u32>) {
    let p = gid.x;
    if (p >= params.n_pixels) {
        return;
    }
    for (var c = 0u; c < 3u; c++) {
        let i = 3u * p + c;
        var gc = grad_c_med[i] + d_c_med[i];
        var ga = grad_sigma_att[i];
        var gb = grad_sigma_bs[i];
        if ((params.held & (1u << c)) != 0u) {
            let va = max(sigma_att[i], 1e-12);
            ga += params.k * (log(va) - params.ln_beta_d[c]) * params.inv_s2 / va;
        }
        if ((params.held & (1u << (3u + c))) != 0u) {
            let vb = max(sigma_bs[i], 1e-12);
            gb += params.k * (log(vb) - params.ln_beta_b[c]) * params.inv_s2 / vb;
        }
        if ((params.held & (1u << (6u + c))) != 0u) {
            gc += params.k * (c_med[i] - params.b_inf[c]) * params.inv_sb2;
        }
        if (params.single != 0u) {
            ga += gb;
            gb = 0.0;
        }
        grad_c_med[i] = gc;
        grad_sigma_att[i] = ga;
        grad_sigma_bs[i] = gb;
    }
}
