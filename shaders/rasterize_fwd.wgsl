// file: rasterize_fwd.wgsl
// Stage `rasterize_fwd` (mirror of src/render/forward.rs): each pixel's thread walks its
// tile's list front to back with the CPU's arithmetic (blend.rs::alpha_parts, the same
// termination test), accumulating Σ T·α·c in place, the final transmittance and the last
// contributor. Per-Gaussian sums Σ(T·α)², Σ T·α and the pixel count are accumulated per
// batch in workgroup memory, then added to the [N, 4] statistics with one atomic per pair.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> splats: array<f32>;         // [N, 12]
@group(0) @binding(2) var<storage, read> chans: array<f32>;          // [N, C]
@group(0) @binding(3) var<storage, read> tile_offsets: array<u32>;   // [TX·TY + 1]
@group(0) @binding(4) var<storage, read> vals: array<u32>;           // [M] sorted Gaussian ids
@group(0) @binding(5) var<storage, read_write> img: array<f32>;      // [H, W, C]
@group(0) @binding(6) var<storage, read_write> final_t: array<f32>;  // [H, W]
@group(0) @binding(7) var<storage, read_write> last: array<u32>;     // [H, W]
@group(0) @binding(8) var<storage, read_write> stats: array<AF32>;   // [N, 4]

var<workgroup> acc_w2: array<atomic<u32>, 256>;
var<workgroup> acc_w: array<atomic<u32>, 256>;
var<workgroup> acc_n: array<atomic<u32>, 256>;
// Pixels of the tile that stopped blending (or lie outside the image).
var<workgroup> n_done: atomic<u32>;
var<workgroup> sh_done: u32;

fn shared_add(which: u32, slot: u32, v: f32) {
    if (which == 0u) {
        var old = atomicLoad(&acc_w2[slot]);
        loop {
            let r = atomicCompareExchangeWeak(&acc_w2[slot], old, bitcast<u32>(bitcast<f32>(old) + v));
            if (r.exchanged) { break; }
            old = r.old_value;
        }
    } else {
        var old = atomicLoad(&acc_w[slot]);
        loop {
            let r = atomicCompareExchangeWeak(&acc_w[slot], old, bitcast<u32>(bitcast<f32>(old) + v));
            if (r.exchanged) { break; }
            old = r.old_value;
        }
    }
}

@compute @workgroup_size(16, 16)
fn main(th: TileThread) {
    let lin = th.lin;
    let me = pixel_of(th);
    let inside = me.inside;
    let p = me.p;
    if (lin == 0u) {
        atomicStore(&n_done, 0u);
    }
    let range = tile_range(lin, me.tile);
    if (!inside) {
        atomicAdd(&n_done, 1u);
    } else {
        for (var q = 0u; q < P.nc; q++) {
            img[p * P.nc + q] = 0.0;
        }
    }
    let pix = me.centre;
    var t = 1.0;
    var done = !inside;
    var last_j = 0u;
    for (var b = range.x; b < range.y; b += 256u) {
        let n_b = min(256u, range.y - b);
        if (lin < n_b) {
            load_splat(lin, vals[b + lin]);
        }
        atomicStore(&acc_w2[lin], 0u);
        atomicStore(&acc_w[lin], 0u);
        atomicStore(&acc_n[lin], 0u);
        workgroupBarrier();
        for (var j = 0u; j < n_b; j++) {
            if (done) {
                continue;
            }
            let g = staged(j);
            let e = alpha_parts(g, g.mean.x - pix.x, g.mean.y - pix.y, P.alpha_max, P.cutoff);
            let alpha = e.x;
            if (alpha == 0.0) {
                continue;
            }
            let next_t = t * (1.0 - alpha);
            if (next_t <= T_THRESHOLD) {
                done = true;
                atomicAdd(&n_done, 1u);
                continue;
            }
            let wgt = alpha * t;
            let gid = staged_id(j);
            for (var q = 0u; q < P.nc; q++) {
                img[p * P.nc + q] += wgt * chans[gid * P.nc + q];
            }
            shared_add(0u, j, wgt * wgt);
            shared_add(1u, j, wgt);
            atomicAdd(&acc_n[j], 1u);
            t = next_t;
            last_j = b - range.x + j + 1u;
        }
        workgroupBarrier();
        if (lin < n_b) {
            let n = atomicLoad(&acc_n[lin]);
            if (n > 0u) {
                let gid = staged_id(lin);
                stats_add(gid * 4u, bitcast<f32>(atomicLoad(&acc_w2[lin])));
                stats_add(gid * 4u + 1u, bitcast<f32>(atomicLoad(&acc_w[lin])));
                stats_add(gid * 4u + 2u, f32(n));
            }
        }
        // Also the barrier before the next batch overwrites the staged Gaussians.
        if (lin == 0u) {
            sh_done = atomicLoad(&n_done);
        }
        if (workgroupUniformLoad(&sh_done) == 256u) {
            break;
        }
    }
    if (inside) {
        final_t[p] = t;
        last[p] = last_j;
    }
}
