// file: scan.wgsl
// Exclusive prefix sum of u32 in blocks of 256 (block_scan.wgsl); the block totals are
// scanned by the next level and added back (`add_sums`).

struct ScanParams {
    len: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> S: ScanParams;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

@compute @workgroup_size(256)
fn scan_blocks(f: Flat) {
    let i = item_of(f);
    var v = 0u;
    if (i < S.len) {
        v = data[i];
    }
    let incl = block_scan(f.lid, v);
    if (i < S.len) {
        data[i] = incl - v;
    }
    if (f.lid == 255u) {
        sums[block_of(f)] = incl;
    }
}

@compute @workgroup_size(256)
fn add_sums(f: Flat) {
    let i = item_of(f);
    if (i < S.len) {
        data[i] += sums[block_of(f)];
    }
}
