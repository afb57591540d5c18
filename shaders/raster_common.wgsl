// file: raster_common.wgsl
// Tile batches shared by the per-tile kernels: one workgroup of 16x16 threads per tile,
// one thread per pixel; the tile's depth-sorted Gaussians are staged in workgroup memory
// 256 at a time.

var<workgroup> sh_a: array<vec4<f32>, 256>;   // mean.xy, conic.xy
var<workgroup> sh_b: array<vec4<f32>, 256>;   // conic.z, opacity, power, Gaussian index (bits)
var<workgroup> sh_range: vec2<u32>;

fn load_splat(slot: u32, g: u32) {
    let o = g * SPLAT_STRIDE;
    sh_a[slot] = vec4<f32>(splats[o], splats[o + 1u], splats[o + 2u], splats[o + 3u]);
    sh_b[slot] = vec4<f32>(splats[o + 4u], splats[o + 6u], splats[o + 7u], bitcast<f32>(g));
}

fn staged(slot: u32) -> Splat {
    let a = sh_a[slot];
    let b = sh_b[slot];
    return Splat(a.xy, vec3<f32>(a.z, a.w, b.x), b.y, b.z);
}

fn staged_id(slot: u32) -> u32 {
    return bitcast<u32>(sh_b[slot].w);
}

// Entry-point builtins of the per-tile kernels.
struct TileThread {
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_id) loc: vec3<u32>,
    @builtin(local_invocation_index) lin: u32,
}

// A tile thread's pixel: its tile, whether it lies in the image, its index p = y·W + x
// and its centre (x + 0.5, y + 0.5).
struct Pixel {
    tile: u32,
    inside: bool,
    p: u32,
    centre: vec2<f32>,
}

fn pixel_of(t: TileThread) -> Pixel {
    let px = t.wid.x * TILE + t.loc.x;
    let py = t.wid.y * TILE + t.loc.y;
    return Pixel(
        t.wid.x + t.wid.y * P.tiles_x,
        px < P.img_w && py < P.img_h,
        py * P.img_w + px,
        vec2<f32>(f32(px) + 0.5, f32(py) + 0.5),
    );
}

// The tile's list range [start, end) in `vals` (uniform over the workgroup). Workgroup
// memory written by thread 0 before the call is visible to all threads after it.
fn tile_range(lin: u32, tile: u32) -> vec2<u32> {
    if (lin == 0u) {
        sh_range = vec2<u32>(tile_offsets[tile], tile_offsets[tile + 1u]);
    }
    return workgroupUniformLoad(&sh_range);
}

var<workgroup> max_last: atomic<u32>;
var<workgroup> sh_max: u32;

// The largest `my_last` over the tile's threads (uniform): how many of the tile's pairs
// any of the pixels that take part blended.
fn tile_max(lin: u32, my_last: u32) -> u32 {
    if (lin == 0u) {
        atomicStore(&max_last, 0u);
    }
    workgroupBarrier();
    atomicMax(&max_last, my_last);
    workgroupBarrier();
    if (lin == 0u) {
        sh_max = atomicLoad(&max_last);
    }
    return workgroupUniformLoad(&sh_max);
}
