// file: threads.wgsl
// Thread ids of the one-thread-per-item kernels: 256 threads per workgroup, workgroups in a
// 2D grid (gpu/frame.rs::grid) so that large N stays under the per-dimension limit.

struct Flat {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
}

// The workgroup's index in the flattened grid.
fn block_of(f: Flat) -> u32 {
    return f.wid.x + f.wid.y * f.nwg.x;
}

// The thread's item index.
fn item_of(f: Flat) -> u32 {
    return block_of(f) * 256u + f.lid;
}
