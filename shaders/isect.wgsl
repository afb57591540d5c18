// file: isect.wgsl
// Stages `isect_tiles` (emit) and `tile_ranges` (mirrors of src/render/isect.rs).
// emit: one thread per Gaussian writes its (tile, depth bits, index) pairs at its prefix-sum
// offset, in Gaussian order, so that the stable radix sort orders ties by index as the CPU.
// ranges: one thread per list position i in 0..=M writes offsets[t] = i for the tiles t
// between the tiles of pairs i - 1 and i.

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> splats: array<f32>;          // [N, 12]
@group(0) @binding(2) var<storage, read> offsets: array<u32>;         // [N + 1] exclusive scan of counts
@group(0) @binding(3) var<storage, read_write> key_hi: array<u32>;    // [cap] tile id
@group(0) @binding(4) var<storage, read_write> key_lo: array<u32>;    // [cap] depth bits
@group(0) @binding(5) var<storage, read_write> vals: array<u32>;      // [cap] Gaussian index
@group(0) @binding(6) var<storage, read_write> tile_offsets: array<u32>; // [num_tiles + 1]

@compute @workgroup_size(256)
fn emit(f: Flat) {
    let i = item_of(f);
    if (i >= P.n) {
        return;
    }
    let start = offsets[i];
    let count = offsets[i + 1u] - start;
    if (count == 0u) {
        return;
    }
    let o = i * SPLAT_STRIDE;
    let mean = vec2<f32>(splats[o], splats[o + 1u]);
    let extent = vec2<f32>(splats[o + 8u], splats[o + 9u]);
    let depth_bits = bitcast<u32>(splats[o + 5u]);
    let x0 = u32(max(floor((mean.x - extent.x) / 16.0), 0.0));
    let x1 = u32(min(floor((mean.x + extent.x) / 16.0), f32(P.tiles_x) - 1.0));
    let y0 = u32(max(floor((mean.y - extent.y) / 16.0), 0.0));
    let y1 = u32(min(floor((mean.y + extent.y) / 16.0), f32(P.tiles_y) - 1.0));
    var k = start;
    for (var ty = y0; ty <= y1; ty++) {
        for (var tx = x0; tx <= x1; tx++) {
            if (k < P.pair_cap) {
                key_hi[k] = ty * P.tiles_x + tx;
                key_lo[k] = depth_bits;
                vals[k] = i;
            }
            k++;
        }
    }
}

@compute @workgroup_size(256)
fn ranges(f: Flat) {
    let i = item_of(f);
    let m = min(offsets[P.n], P.pair_cap);
    if (i > m) {
        return;
    }
    var lo = 0u;
    if (i > 0u) {
        lo = key_hi[i - 1u] + 1u;
    }
    var hi = P.num_tiles;
    if (i < m) {
        hi = key_hi[i];
    }
    for (var t = lo; t <= hi; t++) {
        tile_offsets[t] = i;
    }
}
