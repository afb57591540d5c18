//! Stages 2 and 3, `isect_tiles` and `tile_ranges`: list every (tile, Gaussian) pair whose
//! tile overlaps the Gaussian's opacity-aware bounding box, sort the list by tile then depth,
//! and find each tile's range in it.
//!
//! Reads `[N]` [`Splat2d`]; writes `[M]` intersections (M = number of pairs) and `[TX·TY + 1]`
//! tile offsets. Memory is O(N + M): there is never a per-pixel list of Gaussians.

use rayon::prelude::*;

use super::project::Splat2d;
use crate::render::constants::TILE_SIZE;

/// The tile grid of an image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TileGrid {
    /// Image width W, pixels.
    pub width: u32,
    /// Image height H, pixels.
    pub height: u32,
    /// Tiles per row, ceil(W / 16).
    pub tiles_x: u32,
    /// Tiles per column, ceil(H / 16).
    pub tiles_y: u32,
}

impl TileGrid {
    /// The grid of a `width x height` image.
    pub fn new(width: u32, height: u32) -> Self {
        TileGrid {
            width,
            height,
            tiles_x: width.div_ceil(TILE_SIZE),
            tiles_y: height.div_ceil(TILE_SIZE),
        }
    }

    /// Number of tiles TX·TY.
    pub fn num_tiles(&self) -> usize {
        (self.tiles_x * self.tiles_y) as usize
    }

    /// Inclusive tile rectangle `(x0, y0, x1, y1)` covered by a splat's bounding box, or
    /// `None` when it misses the image.
    pub fn tile_rect(&self, s: &Splat2d) -> Option<(u32, u32, u32, u32)> {
        if !s.valid {
            return None;
        }
        let t = TILE_SIZE as f32;
        let lo = |c: f32, e: f32| ((c - e) / t).floor().max(0.0);
        let hi = |c: f32, e: f32, n: u32| ((c + e) / t).floor().min(n as f32 - 1.0);
        let (x0, x1) = (lo(s.mean2d[0], s.extent[0]), hi(s.mean2d[0], s.extent[0], self.tiles_x));
        let (y0, y1) = (lo(s.mean2d[1], s.extent[1]), hi(s.mean2d[1], s.extent[1], self.tiles_y));
        if !(x0 <= x1 && y0 <= y1) {
            return None;
        }
        Some((x0 as u32, y0 as u32, x1 as u32, y1 as u32))
    }
}

/// The sorted intersection list, `[M]` each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Intersections {
    /// Sort key of each pair: bits 63..32 = tile id (`ty·TX + tx`), bits 31..0 = the f32
    /// bit pattern of the camera-space depth (positive, so integer order = depth order).
    pub keys: Vec<u64>,
    /// Canonical Gaussian index of each pair (ties of equal keys are ordered by it).
    pub gaussian: Vec<u32>,
}

/// Stage `isect_tiles`: all (tile, Gaussian) pairs, sorted by (tile, depth, Gaussian index).
pub fn isect_tiles(grid: &TileGrid, splats: &[Splat2d]) -> Intersections {
    let _span = tracing::debug_span!("render.isect_tiles", n = splats.len()).entered();
    let counts: Vec<u32> = splats
        .par_iter()
        .map(|s| grid.tile_rect(s).map_or(0, |(x0, y0, x1, y1)| (x1 - x0 + 1) * (y1 - y0 + 1)))
        .collect();
    let mut offsets = Vec::with_capacity(splats.len() + 1);
    let mut total = 0usize;
    offsets.push(0);
    for c in &counts {
        total += *c as usize;
        offsets.push(total);
    }
    let mut pairs = vec![(0u64, 0u32); total];
    let mut rest: &mut [(u64, u32)] = &mut pairs;
    let mut chunks = Vec::with_capacity(splats.len());
    for c in &counts {
        let (head, tail) = rest.split_at_mut(*c as usize);
        chunks.push(head);
        rest = tail;
    }
    chunks.into_par_iter().enumerate().for_each(|(i, out)| {
        let s = &splats[i];
        let Some((x0, y0, x1, y1)) = grid.tile_rect(s) else { return };
        let depth_bits = s.depth.to_bits() as u64;
        let mut k = 0;
        for ty in y0..=y1 {
            for tx in x0..=x1 {
                let tile = (ty * grid.tiles_x + tx) as u64;
                out[k] = ((tile << 32) | depth_bits, i as u32);
                k += 1;
            }
        }
    });
    pairs.par_sort_unstable();
    let (keys, gaussian) = pairs.into_iter().unzip();
    Intersections { keys, gaussian }
}

/// Stage `tile_ranges`: `[TX·TY + 1]` offsets; tile t's pairs are `offsets[t]..offsets[t+1]`
/// of the sorted intersection `keys`.
pub fn tile_ranges(keys: &[u64], num_tiles: usize) -> Vec<usize> {
    let mut offsets = vec![0usize; num_tiles + 1];
    let mut i = 0;
    for (t, slot) in offsets.iter_mut().enumerate().skip(1) {
        while i < keys.len() && ((keys[i] >> 32) as usize) < t {
            i += 1;
        }
        *slot = i;
    }
    offsets[num_tiles] = keys.len();
    offsets
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splat(x: f32, y: f32, ext: f32, depth: f32) -> Splat2d {
        Splat2d { mean2d: [x, y], extent: [ext, ext], depth, valid: true, ..Splat2d::default() }
    }

    #[test]
    fn pairs_cover_bounding_boxes_sorted_by_tile_then_depth() {
        let grid = TileGrid::new(40, 20); // 3 x 2 tiles
        assert_eq!((grid.tiles_x, grid.tiles_y), (3, 2));
        let splats = [
            splat(24.0, 8.0, 5.0, 3.0),  // tile (1,0) only
            splat(15.0, 15.0, 2.0, 1.0), // tiles (0,0),(1,0),(0,1),(1,1)
            splat(39.0, 19.0, 1.0, 2.0), // tile (2,1)
            Splat2d::default(),          // culled
            splat(-50.0, 5.0, 2.0, 1.0), // off-screen
        ];
        let isect = isect_tiles(&grid, &splats);
        let tiles: Vec<u64> = isect.keys.iter().map(|k| k >> 32).collect();
        assert_eq!(tiles, vec![0, 1, 1, 3, 4, 5]);
        assert_eq!(isect.gaussian, vec![1, 1, 0, 1, 1, 2]);
        let offsets = tile_ranges(&isect.keys, grid.num_tiles());
        assert_eq!(offsets, vec![0, 1, 3, 3, 4, 5, 6]);
    }

    #[test]
    fn tile_ranges_of_empty_list() {
        assert_eq!(tile_ranges(&[], 3), vec![0, 0, 0, 0]);
    }
}
