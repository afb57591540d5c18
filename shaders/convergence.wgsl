// file: convergence.wgsl
// Convergence tests on a finished forward pass (mirror of forward.rs::failing_pairs and
// cpu.rs::centre_pass). `fail_pairs`: per tile, each failing pixel's thread marks every
// Gaussian blended into it (list position < last contributor, α > 0, and T·α at least
// P.min_weight, with the forward pass's transmittance T). `centre`: one thread
// per Gaussian tests the pixel under its projected centre. Output [N]: 1 = passes.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> splats: array<f32>;          // [N, 12]
@group(0) @binding(2) var<storage, read> tile_offsets: array<u32>;    // [TX·TY + 1]
@group(0) @binding(3) var<storage, read> vals: array<u32>;            // [M]
@group(0) @binding(4) var<storage, read> last: array<u32>;            // [H, W]
@group(0) @binding(5) var<storage, read> pixel_pass: array<u32>;      // [H, W] 1 = passes
@group(0) @binding(6) var<storage, read_write> fail: array<atomic<u32>>; // [N]

@compute @workgroup_size(16, 16)
fn fail_pairs(th: TileThread) {
    let lin = th.lin;
    let me = pixel_of(th);
    let range = tile_range(lin, me.tile);
    var my_last = 0u;
    if (me.inside && pixel_pass[me.p] == 0u) {
        my_last = last[me.p];
    }
    let n_used = tile_max(lin, my_last);
    let pix = me.centre;
    var tr = 1.0;
    for (var b0 = 0u; b0 < n_used; b0 += 256u) {
        let n_b = min(256u, n_used - b0);
        if (lin < n_b) {
            load_splat(lin, vals[range.x + b0 + lin]);
        }
        workgroupBarrier();
        for (var j = 0u; j < n_b; j++) {
            if (b0 + j >= my_last) {
                break;
            }
            let g = staged(j);
            let e = alpha_parts(g, g.mean.x - pix.x, g.mean.y - pix.y, P.alpha_max, P.cutoff);
            if (e.x > 0.0) {
                if (e.x * tr >= P.min_weight) {
                    atomicMax(&fail[staged_id(j)], 1u);
                }
                tr *= 1.0 - e.x;
            }
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn centre(f: Flat) {
    let i = item_of(f);
    if (i >= P.n) {
        return;
    }
    let o = i * SPLAT_STRIDE;
    let x = floor(splats[o]);
    let y = floor(splats[o + 1u]);
    var ok = splats[o + 11u] != 0.0 && x >= 0.0 && y >= 0.0 && x < P.width_f && y < P.height_f;
    if (ok) {
        ok = pixel_pass[u32(y) * P.img_w + u32(x)] != 0u;
    }
    atomicStore(&fail[i], select(1u, 0u, ok));
}
