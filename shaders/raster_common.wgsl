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
