// file: scan.wgsl
// Exclusive prefix sum of u32 in blocks of 256 (Hillis-Steele in workgroup memory); the
// block totals are scanned by the next level and added back (`add`).

struct ScanParams {
    len: u32,
    _p0: u32,
    _p1: u32,
    _p2: u32,
}

@group(0) @binding(0) var<uniform> S: ScanParams;
@group(0) @binding(1) var<storage, read_write> data: array<u32>;
@group(0) @binding(2) var<storage, read_write> sums: array<u32>;

var<workgroup> buf: array<u32, 256>;

@compute @workgroup_size(256)
fn scan_blocks(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let b = wid.x + wid.y * nwg.x;
    let i = b * 256u + lid;
    var v = 0u;
    if (i < S.len) {
        v = data[i];
    }
    buf[lid] = v;
    workgroupBarrier();
    for (var off = 1u; off < 256u; off = off * 2u) {
        var t = 0u;
        if (lid >= off) {
            t = buf[lid - off];
        }
        workgroupBarrier();
        buf[lid] += t;
        workgroupBarrier();
    }
    if (i < S.len) {
        data[i] = buf[lid] - v;
    }
    if (lid == 255u) {
        sums[b] = buf[255];
    }
}

@compute @workgroup_size(256)
fn add_sums(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let b = wid.x + wid.y * nwg.x;
    let i = b * 256u + lid;
    if (i < S.len) {
        data[i] += sums[b];
    }
}
