// file: block_scan.wgsl
// Inclusive prefix sum of one u32 per thread over a 256-thread workgroup (Hillis-Steele in
// workgroup memory). Call from uniform control flow; `buf` is free again on return.

var<workgroup> buf: array<u32, 256>;

fn block_scan(lid: u32, v: u32) -> u32 {
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
    let r = buf[lid];
    workgroupBarrier();
    return r;
}
