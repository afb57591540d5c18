// file: project.wgsl
// Stage `project` (mirror of src/render/project.rs::project_one) and the per-Gaussian channel
// values (cpu.rs::channels: SH colour, depth, features), one thread per Gaussian.
// Also writes the Gaussian's tile count (isect.rs::TileGrid::tile_rect) for the prefix sum,
// and its radius into the statistics (slot 3).

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> geom: array<f32>;          // [N, 11] mean, quat, scale, opacity
@group(0) @binding(2) var<storage, read> colors: array<f32>;        // [N, color_stride] rgb | dc + rest
@group(0) @binding(3) var<storage, read> feats: array<f32>;         // [N, F]
@group(0) @binding(4) var<storage, read_write> splats: array<f32>;  // [N, 12]
@group(0) @binding(5) var<storage, read_write> chans: array<f32>;   // [N, C]
@group(0) @binding(6) var<storage, read_write> counts: array<u32>;  // [N + 1]
@group(0) @binding(7) var<storage, read_write> stats: array<f32>;   // [N, 4]

fn cull(i: u32) {
    for (var k = 0u; k < SPLAT_STRIDE; k++) {
        splats[i * SPLAT_STRIDE + k] = 0.0;
    }
    for (var q = 0u; q < P.nc; q++) {
        chans[i * P.nc + q] = 0.0;
    }
    counts[i] = 0u;
}

@compute @workgroup_size(256)
fn main(f: Flat) {
    let i = item_of(f);
    if (i == P.n) {
        counts[i] = 0u;
    }
    if (i >= P.n) {
        return;
    }
    let g3 = load_gaussian(i);
    let opacity = g3.opacity;
    if (!(is_finite(opacity) && opacity >= ALPHA_THRESHOLD)) {
        cull(i);
        return;
    }
    let st = proj_state(g3.mean, g3.quat, g3.scale);
    if (!st.ok) {
        cull(i);
        return;
    }
    let a = st.cov2d.x;
    let b = st.cov2d.y;
    let d = st.cov2d.z;
    let det = a * d - b * b;
    if (!(det > 0.0 && is_finite(det))) {
        cull(i);
        return;
    }
    let conic = vec3<f32>(d / det, -b / det, a / det);
    let z = st.p_cam.z;
    let mean2d = vec2<f32>(P.fx * st.p_cam.x / z + P.cx, P.fy * st.p_cam.y / z + P.cy);
    let power = log(255.0 * opacity);
    let extent = vec2<f32>(sqrt(2.0 * power * a), sqrt(2.0 * power * d));
    let mid = 0.5 * (a + d);
    let lambda_max = mid + sqrt(max(mid * mid - det, 0.0));
    let radius = sqrt(2.0 * power * lambda_max);
    let on_screen = mean2d.x + extent.x > 0.0 && mean2d.x - extent.x < P.width_f
        && mean2d.y + extent.y > 0.0 && mean2d.y - extent.y < P.height_f;
    let finite = is_finite(conic.x) && is_finite(conic.y) && is_finite(conic.z)
        && is_finite(mean2d.x) && is_finite(mean2d.y) && is_finite(radius);
    if (!(on_screen && finite)) {
        cull(i);
        return;
    }
    let o = i * SPLAT_STRIDE;
    splats[o] = mean2d.x;
    splats[o + 1u] = mean2d.y;
    splats[o + 2u] = conic.x;
    splats[o + 3u] = conic.y;
    splats[o + 4u] = conic.z;
    splats[o + 5u] = z;
    splats[o + 6u] = opacity;
    splats[o + 7u] = power;
    splats[o + 8u] = extent.x;
    splats[o + 9u] = extent.y;
    splats[o + 10u] = radius;
    splats[o + 11u] = 1.0;

    // isect.rs::TileGrid::tile_rect
    let x0 = max(floor((mean2d.x - extent.x) / 16.0), 0.0);
    let x1 = min(floor((mean2d.x + extent.x) / 16.0), f32(P.tiles_x) - 1.0);
    let y0 = max(floor((mean2d.y - extent.y) / 16.0), 0.0);
    let y1 = min(floor((mean2d.y + extent.y) / 16.0), f32(P.tiles_y) - 1.0);
    var count = 0u;
    if (x0 <= x1 && y0 <= y1) {
        count = (u32(x1) - u32(x0) + 1u) * (u32(y1) - u32(y0) + 1u);
        stats[i * 4u + 3u] = radius;
    }
    counts[i] = count;

    // Channels: [r, g, b, z, f_0 .. f_{F-1}], non-finite values zeroed.
    var rgb: vec3<f32>;
    let cb = i * P.color_stride;
    let dc = vec3<f32>(colors[cb], colors[cb + 1u], colors[cb + 2u]);
    if (P.color_mode == 0u) {
        rgb = dc;
    } else {
        var y = sh_basis(P.sh_degree, view_dir(g3.mean, st.r).xyz);
        rgb = dc;
        let nb = (P.sh_degree + 1u) * (P.sh_degree + 1u);
        for (var k = 1u; k < nb; k++) {
            rgb += y[k] * sh_coeff(cb, k);
        }
        rgb = max(rgb, vec3<f32>(0.0));
    }
    let co = i * P.nc;
    chans[co] = finite_or_zero(rgb.x);
    chans[co + 1u] = finite_or_zero(rgb.y);
    chans[co + 2u] = finite_or_zero(rgb.z);
    chans[co + 3u] = z;
    for (var f = 0u; f < P.nf; f++) {
        chans[co + 4u + f] = finite_or_zero(feats[i * P.nf + f]);
    }
}
