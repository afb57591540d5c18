// file: common.wgsl
// Shared declarations of the rasterizer's kernels (prepended to every shader module).
// Mirrors src/render/constants.rs and src/render/blend.rs: the same thresholds, the same
// Cephes-style exp and the same left-to-right evaluation order, so that the GPU makes the
// CPU's skip decisions.

const TILE: u32 = 16u;
const ALPHA_THRESHOLD: f32 = 0.003921569; // 1/255
const T_THRESHOLD: f32 = 1e-4;
const COV_BLUR: f32 = 0.3;
const SPLAT_STRIDE: u32 = 12u;

// One uniform block for every kernel of a render (see gpu/params.rs for the packing).
struct Params {
    rot0: vec4<f32>,
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    trans: vec4<f32>,
    center: vec4<f32>,
    bg: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    lim_x0: f32,
    lim_x1: f32,
    lim_y0: f32,
    lim_y1: f32,
    width_f: f32,
    height_f: f32,
    near: f32,
    far: f32,
    alpha_max: f32,
    img_w: u32,
    img_h: u32,
    tiles_x: u32,
    tiles_y: u32,
    n: u32,
    nc: u32,
    nf: u32,
    sh_degree: u32,
    color_mode: u32,
    cutoff: u32,
    color_stride: u32,
    pair_cap: u32,
    num_tiles: u32,
    // convergence `fail_pairs`: a pixel counts for a Gaussian when T·α >= this (0: any α > 0)
    min_weight: f32,
}

// A projected Gaussian as the rasterizers read it.
struct Splat {
    mean: vec2<f32>,
    conic: vec3<f32>,
    opacity: f32,
    power: f32,
}

fn is_finite(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) != 0x7f800000u;
}

// exp(x) for x <= 0: blend.rs::exp_neg, operation for operation, except that n = round(x·log2 e)
// and 2ⁿ are computed with round() and ldexp() instead of the 1.5·2²³ trick, which shader
// compilers may reassociate away (SPIR-V float operations are not exact).
fn exp_neg(x_in: f32) -> f32 {
    var x = -87.0;
    if (x_in > -87.0) {
        x = min(x_in, 0.0);
    }
    let n = round(x * 1.442695);
    let r = x - n * 0.6933594 - n * -2.1219444e-4;
    let p = ((((1.9875691e-4 * r + 1.3981999e-3) * r + 8.333452e-3) * r + 4.1665796e-2) * r
        + 1.6666665e-1) * r + 0.5;
    let e = r * r * p + r + 1.0;
    return ldexp(e, i32(n));
}

fn ramp(raw: f32) -> f32 {
    return clamp((raw - ALPHA_THRESHOLD) / ALPHA_THRESHOLD, 0.0, 1.0);
}

fn smoothstep01(t: f32) -> f32 {
    return t * t * (3.0 - 2.0 * t);
}

// blend.rs::alpha_parts: (alpha, raw, vis), alpha == 0 when the pair does not contribute.
fn alpha_parts(g: Splat, dx: f32, dy: f32, alpha_max: f32, cutoff: u32) -> vec3<f32> {
    let sigma = 0.5 * (g.conic.x * dx * dx + g.conic.z * dy * dy) + g.conic.y * dx * dy;
    let vis = exp_neg(-sigma);
    let raw = g.opacity * vis;
    let inside = sigma >= 0.0 && sigma <= g.power && raw >= ALPHA_THRESHOLD;
    var alpha = min(raw, alpha_max);
    if (cutoff == 1u) {
        alpha = min(raw * smoothstep01(ramp(raw)), alpha_max);
    }
    if (!(inside && alpha > 0.0)) {
        alpha = 0.0;
    }
    return vec3<f32>(alpha, raw, vis);
}
