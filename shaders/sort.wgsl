// file: sort.wgsl
// One pass of a stable LSD radix sort (4 bits) of (key_hi, key_lo, value) triples by 4 bits
// of key_lo (word 0) or key_hi (word 1). `count`: per-block digit histograms, digit-major,
// so that one exclusive scan gives every (digit, block) its output offset; `scatter`: each
// element's rank among the equal digits of its block (a packed workgroup scan), so equal
// keys keep their order.

struct SortParams {
    shift: u32,
    word: u32,
    nblocks: u32,
    _p: u32,
}

@group(0) @binding(0) var<uniform> S: SortParams;
@group(0) @binding(1) var<storage, read> num: array<u32>;        // element count at num[count_index]
@group(0) @binding(2) var<storage, read> in_hi: array<u32>;
@group(0) @binding(3) var<storage, read> in_lo: array<u32>;
@group(0) @binding(4) var<storage, read> in_val: array<u32>;
@group(0) @binding(5) var<storage, read_write> hist: array<u32>;  // [16, nblocks]
@group(0) @binding(6) var<storage, read_write> out_hi: array<u32>;
@group(0) @binding(7) var<storage, read_write> out_lo: array<u32>;
@group(0) @binding(8) var<storage, read_write> out_val: array<u32>;

var<workgroup> counts: array<atomic<u32>, 16>;

// `num` holds the scanned tile counts [N + 1]; its last entry is the number of pairs M.
fn element_count() -> u32 {
    return min(num[arrayLength(&num) - 1u], arrayLength(&in_hi));
}

fn digit(i: u32) -> u32 {
    var k = in_lo[i];
    if (S.word == 1u) {
        k = in_hi[i];
    }
    return (k >> S.shift) & 15u;
}

@compute @workgroup_size(256)
fn count(f: Flat) {
    let b = block_of(f);
    let i = item_of(f);
    let lid = f.lid;
    if (lid < 16u) {
        atomicStore(&counts[lid], 0u);
    }
    workgroupBarrier();
    if (i < element_count()) {
        atomicAdd(&counts[digit(i)], 1u);
    }
    workgroupBarrier();
    if (lid < 16u && b < S.nblocks) {
        hist[lid * S.nblocks + b] = atomicLoad(&counts[lid]);
    }
}

@compute @workgroup_size(256)
fn scatter(f: Flat) {
    let b = block_of(f);
    let i = item_of(f);
    let valid = i < element_count();
    var d = 16u;
    if (valid) {
        d = digit(i);
    }
    var rank = 0u;
    for (var p = 0u; p < 8u; p++) {
        let v = select(0u, 1u, d == 2u * p) | select(0u, 0x10000u, d == 2u * p + 1u);
        let incl = block_scan(f.lid, v);
        if ((d >> 1u) == p) {
            rank = ((incl - v) >> (16u * (d & 1u))) & 0xffffu;
        }
    }
    if (valid) {
        let dst = hist[d * S.nblocks + b] + rank;
        out_hi[dst] = in_hi[i];
        out_lo[dst] = in_lo[i];
        out_val[dst] = in_val[i];
    }
}
