//! Stage 4, `rasterize_fwd`: front-to-back alpha blending of each tile's depth-sorted
//! Gaussians (reference for `gpu::rasterize_fwd`).
//!
//! Mapping: rayon over tiles; within a tile the GPU runs one thread per pixel walking the
//! tile's list front to back; the CPU runs the same per-pixel arithmetic Gaussian-major
//! (see `rasterize_tile`), which gives the same bits and skips pixels outside each ellipse. Reads `[N]` [`Splat2d`],
//! `[N, C]` channel values, the sorted `[M]` intersections and `[TX·TY+1]` tile offsets.
//! Writes `[H, W, C]` blended channels (Σ T·α·c, no background), `[H, W]` final
//! transmittance and last contributor, and `[M]` per-pair statistics (accumulated per tile
//! in pixel order, no atomics), which [`super::cpu`] reduces per Gaussian in list order.

use rayon::prelude::*;

use super::blend::{Cutoff, eval_alpha, for_each_row};
use super::constants::{T_THRESHOLD, TILE_SIZE};
use super::isect::{Intersections, TileGrid};
use super::project::Splat2d;

/// Per-(tile, Gaussian) statistics of one forward pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PairStats {
    /// Σ over the tile's pixels of (T·α)².
    pub sum_w2: f32,
    /// Σ over the tile's pixels of T·α.
    pub sum_w: f32,
    /// Number of the tile's pixels the Gaussian was blended into.
    pub n_pixels: u32,
    /// Number of those pixels whose `pixel_pass` entry is false.
    pub n_fail: u32,
}

/// Output of [`rasterize_fwd`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FwdImages {
    /// `[H, W, C]` Σ T·α·c over the blended Gaussians (no background).
    pub channels: Vec<f32>,
    /// `[H, W]` transmittance after the last blended Gaussian (1 − alpha).
    pub final_t: Vec<f32>,
    /// `[H, W]` one past the tile-list position (relative to the tile's start) of the last
    /// Gaussian blended into the pixel; 0 when none. The backward pass starts there.
    pub last_contributor: Vec<u32>,
    /// `[M]` statistics of each intersection (same order as the list).
    pub stats: Vec<PairStats>,
}

/// Inputs shared by the forward and backward rasterizers.
#[derive(Debug, Clone, Copy)]
pub struct RasterInputs<'a> {
    /// The tile grid.
    pub grid: TileGrid,
    /// `[N]` projected Gaussians (canonical index).
    pub splats: &'a [Splat2d],
    /// `[N, C]` per-Gaussian channel values (colour, depth, features).
    pub channels: &'a [f32],
    /// C, channels per Gaussian.
    pub num_channels: usize,
    /// The sorted intersections `[M]`.
    pub isect: &'a Intersections,
    /// `[TX·TY + 1]` tile offsets into the intersections.
    pub offsets: &'a [usize],
    /// Upper clamp of alpha.
    pub alpha_max: f32,
    /// Alpha cutoff mode.
    pub cutoff: Cutoff,
}

/// A tile's Gaussians gathered into contiguous storage, front to back.
pub(crate) struct TileList {
    pub(crate) splats: Vec<Splat2d>,
    pub(crate) channels: Vec<f32>,
}

impl RasterInputs<'_> {
    /// Pixel rectangle `(x0, y0, x1, y1)` (exclusive ends) of tile `t`.
    pub(crate) fn tile_pixels(&self, t: usize) -> (u32, u32, u32, u32) {
        let (tx, ty) = (t as u32 % self.grid.tiles_x, t as u32 / self.grid.tiles_x);
        let (x0, y0) = (tx * TILE_SIZE, ty * TILE_SIZE);
        (x0, y0, (x0 + TILE_SIZE).min(self.grid.width), (y0 + TILE_SIZE).min(self.grid.height))
    }

    pub(crate) fn gather(&self, t: usize) -> TileList {
        let ids = &self.isect.gaussian[self.offsets[t]..self.offsets[t + 1]];
        let c = self.num_channels;
        let mut channels = Vec::with_capacity(ids.len() * c);
        for &g in ids {
            channels.extend_from_slice(&self.channels[g as usize * c..(g as usize + 1) * c]);
        }
        TileList { splats: ids.iter().map(|&g| self.splats[g as usize]).collect(), channels }
    }

    fn check(&self) {
        let n = self.splats.len();
        assert_eq!(self.channels.len(), n * self.num_channels, "channels must be [N, C]");
        assert_eq!(self.isect.keys.len(), self.isect.gaussian.len(), "intersections [M]");
        assert_eq!(self.offsets.len(), self.grid.num_tiles() + 1, "offsets [TX·TY + 1]");
    }
}

/// Blend one tile. Gaussian-major: each Gaussian, front to back, updates the pixels of
/// its footprint ([`for_each_row`]); every pixel still sees its Gaussians in list order and
/// does exactly the arithmetic of the per-pixel loop of the GPU kernel, so the results are
/// the same bits, while only ~the ellipse area is visited instead of the whole tile.
fn rasterize_tile(inp: &RasterInputs, t: usize, pixel_pass: Option<&[bool]>) -> TileOut {
    let list = inp.gather(t);
    let c = inp.num_channels;
    let w = inp.grid.width as usize;
    let (x0, y0, x1, y1) = inp.tile_pixels(t);
    let tw = (x1 - x0) as usize;
    let n_px = tw * (y1 - y0) as usize;
    let mut out = TileOut {
        channels: vec![0.0; n_px * c],
        final_t: vec![1.0; n_px],
        last: vec![0; n_px],
        stats: vec![PairStats::default(); list.splats.len()],
    };
    let mut done = vec![false; n_px];
    let mut n_done = 0;
    for (j, g) in list.splats.iter().enumerate() {
        if n_done == n_px {
            break;
        }
        let ch = &list.channels[j * c..(j + 1) * c];
        let mut s = PairStats::default();
        for_each_row(g, x0, y0, x1, y1, |y, xa, xb| {
            let py = y as f32 + 0.5;
            let row = (y - y0) as usize * tw;
            for x in xa..xb {
                let k = row + (x - x0) as usize;
                if done[k] {
                    continue;
                }
                let Some(e) = eval_alpha(g, x as f32 + 0.5, py, inp.alpha_max, inp.cutoff) else {
                    continue;
                };
                let t = out.final_t[k];
                let next_t = t * (1.0 - e.alpha);
                if next_t <= T_THRESHOLD {
                    done[k] = true;
                    n_done += 1;
                    continue;
                }
                let wgt = e.alpha * t;
                for (a, v) in out.channels[k * c..(k + 1) * c].iter_mut().zip(ch) {
                    *a += wgt * v;
                }
                s.sum_w2 += wgt * wgt;
                s.sum_w += wgt;
                s.n_pixels += 1;
                let pass = pixel_pass.is_none_or(|p| p[y as usize * w + x as usize]);
                s.n_fail += u32::from(!pass);
                out.final_t[k] = next_t;
                out.last[k] = j as u32 + 1;
            }
        });
        out.stats[j] = s;
    }
    out
}

struct TileOut {
    channels: Vec<f32>,
    final_t: Vec<f32>,
    last: Vec<u32>,
    stats: Vec<PairStats>,
}

/// Stage `rasterize_fwd`. `pixel_pass` (`[H, W]`, optional) only feeds
/// [`PairStats::n_fail`].
pub fn rasterize_fwd(inp: &RasterInputs, pixel_pass: Option<&[bool]>) -> FwdImages {
    inp.check();
    let _span = tracing::debug_span!("render.rasterize_fwd", m = inp.isect.keys.len()).entered();
    let (w, h, c) = (inp.grid.width as usize, inp.grid.height as usize, inp.num_channels);
    let tiles: Vec<TileOut> = (0..inp.grid.num_tiles())
        .into_par_iter()
        .map(|t| rasterize_tile(inp, t, pixel_pass))
        .collect();
    let mut img = FwdImages {
        channels: vec![0.0; w * h * c],
        final_t: vec![0.0; w * h],
        last_contributor: vec![0; w * h],
        stats: Vec::with_capacity(inp.isect.keys.len()),
    };
    for (t, tile) in tiles.into_iter().enumerate() {
        let (x0, y0, x1, y1) = inp.tile_pixels(t);
        let tw = (x1 - x0) as usize;
        for (r, y) in (y0..y1).enumerate() {
            let dst = y as usize * w + x0 as usize;
            img.final_t[dst..dst + tw].copy_from_slice(&tile.final_t[r * tw..(r + 1) * tw]);
            img.last_contributor[dst..dst + tw].copy_from_slice(&tile.last[r * tw..(r + 1) * tw]);
            img.channels[dst * c..(dst + tw) * c]
                .copy_from_slice(&tile.channels[r * tw * c..(r + 1) * tw * c]);
        }
        img.stats.extend_from_slice(&tile.stats);
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::isect::{isect_tiles, tile_ranges};

    fn splat(x: f32, y: f32, var: f32, opacity: f32, depth: f32) -> Splat2d {
        let power = (255.0 * opacity).ln();
        let ext = (2.0 * power * var).sqrt();
        Splat2d {
            mean2d: [x, y],
            conic: [1.0 / var, 0.0, 1.0 / var],
            depth,
            opacity,
            power,
            extent: [ext, ext],
            radius: ext,
            valid: true,
        }
    }

    #[test]
    fn blends_front_to_back_against_per_pixel_reference() {
        let grid = TileGrid::new(37, 21);
        let splats = vec![
            splat(10.0, 10.0, 30.0, 0.8, 2.0),
            splat(14.0, 12.0, 20.0, 0.6, 1.0),
            splat(30.0, 5.0, 8.0, 0.99, 3.0),
        ];
        let channels = vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let isect = isect_tiles(&grid, &splats);
        let offsets = tile_ranges(&isect.keys, grid.num_tiles());
        let inp = RasterInputs {
            grid,
            splats: &splats,
            channels: &channels,
            num_channels: 3,
            isect: &isect,
            offsets: &offsets,
            alpha_max: 0.99,
            cutoff: Cutoff::Hard,
        };
        let out = rasterize_fwd(&inp, None);
        let order = [1usize, 0, 2]; // by depth
        for y in 0..21 {
            for x in 0..37 {
                let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                let mut t = 1.0f32;
                let mut acc = [0.0f32; 3];
                for &g in &order {
                    if let Some(e) = eval_alpha(&splats[g], px, py, 0.99, Cutoff::Hard) {
                        for ch in 0..3 {
                            acc[ch] += e.alpha * t * channels[g * 3 + ch];
                        }
                        t *= 1.0 - e.alpha;
                    }
                }
                let i = y * 37 + x;
                assert!((out.final_t[i] - t).abs() < 1e-6, "T at ({x}, {y})");
                for ch in 0..3 {
                    assert!(
                        (out.channels[i * 3 + ch] - acc[ch]).abs() < 1e-6,
                        "channel at ({x}, {y})"
                    );
                }
            }
        }
        assert_eq!(
            out.last_contributor[10 * 37 + 10],
            2,
            "both front Gaussians blended at (10, 10)"
        );
        assert_eq!(out.last_contributor[20 * 37 + 36], 0, "nothing reaches the corner");
    }

    #[test]
    fn stops_before_transmittance_drops_to_threshold() {
        let grid = TileGrid::new(16, 16);
        let splats: Vec<Splat2d> =
            (0..6).map(|i| splat(8.0, 8.0, 100.0, 1.0, 1.0 + i as f32)).collect();
        let channels = vec![1.0; 6];
        let isect = isect_tiles(&grid, &splats);
        let offsets = tile_ranges(&isect.keys, grid.num_tiles());
        let inp = RasterInputs {
            grid,
            splats: &splats,
            channels: &channels,
            num_channels: 1,
            isect: &isect,
            offsets: &offsets,
            alpha_max: 0.99,
            cutoff: Cutoff::Hard,
        };
        let out = rasterize_fwd(&inp, None);
        // α = 0.99 at the centre: T = 1e-2 after one, 1e-4 after two → the second is skipped.
        let i = 8 * 16 + 8;
        assert_eq!(out.last_contributor[i], 1);
        assert!((out.final_t[i] - 0.01).abs() < 1e-6);
    }
}
