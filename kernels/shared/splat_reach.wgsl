// Shared by rasterize.wgsl and rasterize_backward.wgsl (`//!include splat_reach.wgsl`, pasted
// in by build.rs; it needs their `SplatVecs` and `TILE`): whether a subgroup can skip a splat,
// and which pixels a thread of the pair kernels takes. The ballot helpers are ballot.wgsl.

// Whether splat `s` can reach a pixel of the box `lo`..`hi` (pixel coordinates as the hit
// test takes them): a pixel it blends has q <= q_max (the hit test's bound), so the least q
// over the box must be within that bound. q is a convex quadratic in the offset from the
// mean: its least value over the box is 0 with the mean inside, else on an edge, where it is
// the edge's 1-D quadratic at its vertex clamped to the edge. Compared with a margin for
// rounding. A splat no pixel of a subgroup can reach is skipped by the whole subgroup, which
// changes nothing: it would blend nowhere.
fn reaches(s: SplatVecs, lo: vec2<f32>, hi: vec2<f32>) -> bool {
    let a = s.a.z;
    let b = s.a.w;
    let c = s.b.x;
    if (!(a > 0.0 && c > 0.0)) {
        return true;
    }
    let d_lo = lo - s.a.xy;
    let d_hi = hi - s.a.xy;
    if (all(d_lo <= vec2<f32>(0.0)) && all(d_hi >= vec2<f32>(0.0))) {
        return true;
    }
    // Horizontal edges (dy fixed): dx at the vertex -b dy / a, clamped.
    let dx0 = clamp(-b * d_lo.y / a, d_lo.x, d_hi.x);
    let dx1 = clamp(-b * d_hi.y / a, d_lo.x, d_hi.x);
    // Vertical edges (dx fixed): dy at the vertex -b dx / c, clamped.
    let dy0 = clamp(-b * d_lo.x / c, d_lo.y, d_hi.y);
    let dy1 = clamp(-b * d_hi.x / c, d_lo.y, d_hi.y);
    let q0 = a * dx0 * dx0 + 2.0 * b * dx0 * d_lo.y + c * d_lo.y * d_lo.y;
    let q1 = a * dx1 * dx1 + 2.0 * b * dx1 * d_hi.y + c * d_hi.y * d_hi.y;
    let q2 = a * d_lo.x * d_lo.x + 2.0 * b * d_lo.x * dy0 + c * dy0 * dy0;
    let q3 = a * d_hi.x * d_hi.x + 2.0 * b * d_hi.x * dy1 + c * dy1 * dy1;
    let q_min = min(min(q0, q1), min(q2, q3));
    return !(q_min * 0.999 - 1e-3 > s.b.w * 1.0001 + 1e-3);
}

// Beyond any pixel coordinate (a lane left out of a subgroup's pixel box).
const BIG: f32 = 1e30;

// The subgroup's ballot of which splats of a batch of `count` (lane l's is `own`) can reach a
// pixel of the subgroup's box: the box of every lane's pixels `lo`..`hi` (one pixel, or a
// lane's pair), lanes `left_out` not counted. Called in uniform control flow.
fn batch_reach(own: SplatVecs, count: u32, lane: u32, lo: vec2<f32>, hi: vec2<f32>, left_out: bool) -> vec4<u32> {
    let box_lo = vec2<f32>(subgroupMin(select(lo.x, BIG, left_out)), subgroupMin(select(lo.y, BIG, left_out)));
    let box_hi = vec2<f32>(subgroupMax(select(hi.x, -BIG, left_out)), subgroupMax(select(hi.y, -BIG, left_out)));
    return subgroupBallot(lane < count && reaches(own, box_lo, box_hi));
}

// The pixel pair of thread `t_index` of a 128-thread workgroup (the pair kernels): pair_y and
// the row below. Eight consecutive threads take a 4x4 block (4 columns, 2 pairs of rows), the
// blocks row-major in the tile: a subgroup of 8 lanes covers 4x4 pixels, 32 lanes 16x4. On
// lavapipe's 8 lanes the square block is reached by fewer splats than an 8x2 strip: both
// rasterisers took 0.95-0.97x the time.
fn pair_x(wg: vec3<u32>, t_index: u32) -> u32 {
    return wg.x * TILE + ((t_index / 8u) % 4u) * 4u + t_index % 4u;
}
fn pair_y(wg: vec3<u32>, t_index: u32) -> u32 {
    return wg.y * TILE + 2u * ((t_index / 32u) * 2u + (t_index % 8u) / 4u);
}
