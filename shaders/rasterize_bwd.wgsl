// file: rasterize_bwd.wgsl
// Stage `rasterize_bwd` (mirror of src/render/backward.rs): each pixel's thread walks its
// tile's list back to front from its last contributor, recovering each earlier
// transmittance as T / (1 − α), with the CPU's per-pixel arithmetic. Per-Gaussian gradients
// `[N, 6 + C]` (mean2d, conic, opacity, channels) are added to the global buffer with
// float atomics (or a compare-exchange loop), one per (pixel, pair, nonzero slot).

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> splats: array<f32>;         // [N, 12]
@group(0) @binding(2) var<storage, read> chans: array<f32>;          // [N, C]
@group(0) @binding(3) var<storage, read> tile_offsets: array<u32>;   // [TX·TY + 1]
@group(0) @binding(4) var<storage, read> vals: array<u32>;           // [M]
@group(0) @binding(5) var<storage, read> final_t: array<f32>;        // [H, W]
@group(0) @binding(6) var<storage, read> last: array<u32>;           // [H, W]
@group(0) @binding(7) var<storage, read> v_pix: array<f32>;          // [H, W, C + 1]: dL/d channels, dL/d alpha
@group(0) @binding(8) var<storage, read_write> scratch: array<f32>;  // [H, W, C] Σ c·w behind
@group(0) @binding(9) var<storage, read_write> grads: array<AF32>;   // [N, 6 + C]

// blend.rs::alpha_vjp: (v_mean2d, v_conic, v_opacity) packed as two vec3s.
fn alpha_vjp(g: Splat, raw: f32, vis: f32, dx: f32, dy: f32, v_alpha: f32) -> array<vec3<f32>, 2> {
    var d = 0.0;
    if (P.cutoff == 0u) {
        if (raw < P.alpha_max) {
            d = 1.0;
        }
    } else {
        let t = ramp(raw);
        if (raw * smoothstep01(t) < P.alpha_max) {
            var sd = 0.0;
            if (t > 0.0 && t < 1.0) {
                sd = 6.0 * t * (1.0 - t);
            }
            d = smoothstep01(t) + raw * sd / ALPHA_THRESHOLD;
        }
    }
    let v_raw = v_alpha * d;
    let v_opacity = vis * v_raw;
    let v_sigma = -raw * v_raw;
    let v_conic = vec3<f32>(0.5 * dx * dx * v_sigma, dx * dy * v_sigma, 0.5 * dy * dy * v_sigma);
    let v_mean = vec2<f32>(v_sigma * (g.conic.x * dx + g.conic.y * dy), v_sigma * (g.conic.y * dx + g.conic.z * dy));
    return array<vec3<f32>, 2>(vec3<f32>(v_mean, v_conic.x), vec3<f32>(v_conic.yz, v_opacity));
}

@compute @workgroup_size(16, 16)
fn main(th: TileThread) {
    let me = pixel_of(th);
    let nc = P.nc;
    let stride = 6u + nc;
    let range = tile_range(th.lin, me.tile);
    var my_last = 0u;
    var t = 1.0;
    var ft = 1.0;
    var v_a_pix = 0.0;
    if (me.inside) {
        my_last = last[me.p];
        t = final_t[me.p];
        ft = t;
        v_a_pix = v_pix[me.p * (nc + 1u) + nc];
        for (var q = 0u; q < nc; q++) {
            scratch[me.p * nc + q] = 0.0;
        }
    }
    let n_used = tile_max(th.lin, my_last);
    let pix = me.centre;
    // Batches back to front: [b0, b0 + n_b) relative to the tile's start.
    var end = n_used;
    while (end > 0u) {
        let b0 = select(0u, end - 256u, end > 256u);
        let n_b = end - b0;
        if (th.lin < n_b) {
            load_splat(th.lin, vals[range.x + b0 + th.lin]);
        }
        workgroupBarrier();
        for (var jj = 0u; jj < n_b; jj++) {
            let j = n_b - 1u - jj;
            if (b0 + j >= my_last) {
                continue;
            }
            let g = staged(j);
            let dx = g.mean.x - pix.x;
            let dy = g.mean.y - pix.y;
            let e = alpha_parts(g, dx, dy, P.alpha_max, P.cutoff);
            let alpha = e.x;
            if (alpha == 0.0) {
                continue;
            }
            let gid = staged_id(j);
            let ra = 1.0 / (1.0 - alpha);
            t *= ra;
            let wgt = alpha * t;
            var v_a = ft * ra * v_a_pix;
            for (var q = 0u; q < nc; q++) {
                let vp = v_pix[me.p * (nc + 1u) + q];
                let ch = chans[gid * nc + q];
                let bq = scratch[me.p * nc + q];
                let vc = wgt * vp;
                if (vc != 0.0) {
                    grads_add(gid * stride + 6u + q, vc);
                }
                v_a += (ch * t - bq * ra) * vp;
                scratch[me.p * nc + q] = bq + ch * wgt;
            }
            let v = alpha_vjp(g, e.y, e.z, dx, dy, v_a);
            grads_add(gid * stride, v[0].x);
            grads_add(gid * stride + 1u, v[0].y);
            grads_add(gid * stride + 2u, v[0].z);
            grads_add(gid * stride + 3u, v[1].x);
            grads_add(gid * stride + 4u, v[1].y);
            grads_add(gid * stride + 5u, v[1].z);
        }
        workgroupBarrier();
        end = b0;
    }
}
