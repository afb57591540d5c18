//! Stage 4, `rasterize_fwd`: front-to-back alpha blending of each tile's depth-sorted
//! Gaussians (reference for `gpu::rasterize_fwd`), and [`failing_pairs`], the per-pair
//! convergence test of the paper's Eq. 5 run on a finished forward pass.
//!
//! Mapping: rayon over strips of one tile row (each strip owns its rows of the output
//! images and its tiles' range of the `[M]` statistics, so nothing is copied or merged);
//! within a tile the GPU runs one thread per pixel walking the tile's list front to back;
//! the CPU runs the same per-pixel arithmetic Gaussian-major (see `rasterize_tile`), which
//! gives the same bits and skips pixels outside each ellipse. Reads `[N]` [`Splat2d`],
//! `[N, C]` channel values, the sorted `[M]` intersections and `[TX·TY+1]` tile offsets.
//! Writes `[H, W, C]` blended channels (Σ T·α·c, no background), `[H, W]` final
//! transmittance and last contributor, and `[M]` per-pair statistics (accumulated per tile
//! in pixel order, no atomics), which [`super`] reduces per Gaussian in list order.

use rayon::prelude::*;

use std::cell::Cell;

use super::blend::{SPAN, for_each_live_row, span_alpha};
use super::isect::{Intersections, TileGrid};
use super::project::Splat2d;
use crate::render::Cutoff;
use crate::render::constants::{T_THRESHOLD, TILE_SIZE};

/// Per-(tile, Gaussian) statistics of one forward pass.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PairStats {
    /// Σ over the tile's pixels of (T·α)².
    pub sum_w2: f32,
    /// Σ over the tile's pixels of T·α.
    pub sum_w: f32,
    /// Number of the tile's pixels the Gaussian was blended into.
    pub n_pixels: u32,
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

/// A tile's Gaussians gathered into contiguous storage, front to back (reused across the
/// tiles a worker visits).
#[derive(Default)]
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

    /// Gather tile `t`'s splats and channel values into `list` (cleared first).
    pub(crate) fn gather_into(&self, t: usize, list: &mut TileList) {
        let ids = &self.isect.gaussian[self.offsets[t]..self.offsets[t + 1]];
        let c = self.num_channels;
        list.splats.clear();
        list.splats.extend(ids.iter().map(|&g| self.splats[g as usize]));
        list.channels.clear();
        list.channels.reserve(ids.len() * c);
        for &g in ids {
            list.channels.extend_from_slice(&self.channels[g as usize * c..(g as usize + 1) * c]);
        }
    }

    /// Split `v` (`[M]`, list order) into one slice per tile row (strip) of the grid.
    pub(crate) fn split_by_strip<'v, T>(&self, mut v: &'v mut [T]) -> Vec<&'v mut [T]> {
        let tx = self.grid.tiles_x as usize;
        (0..self.grid.tiles_y as usize)
            .map(|s| {
                let len = self.offsets[(s + 1) * tx] - self.offsets[s * tx];
                let (head, tail) = std::mem::take(&mut v).split_at_mut(len);
                v = tail;
                head
            })
            .collect()
    }

    fn check(&self) {
        let n = self.splats.len();
        assert_eq!(self.channels.len(), n * self.num_channels, "channels must be [N, C]");
        assert_eq!(self.isect.keys.len(), self.isect.gaussian.len(), "intersections [M]");
        assert_eq!(self.offsets.len(), self.grid.num_tiles() + 1, "offsets [TX·TY + 1]");
    }
}

/// One strip's rows of the output images (`[16, W, C]`, `[16, W]`, `[16, W]`; fewer rows in
/// the last strip) and its tiles' pair statistics.
struct Strip<'a> {
    channels: &'a mut [f32],
    final_t: &'a mut [f32],
    last: &'a mut [u32],
    stats: &'a mut [PairStats],
}

/// Blend one tile into its strip. Gaussian-major: each Gaussian, front to back, updates the
/// pixels of its footprint ([`for_each_row`]); every pixel still sees its Gaussians in list
/// order and does exactly the arithmetic of the per-pixel loop of the GPU kernel, so the
/// results are the same bits, while only ~the ellipse area is visited instead of the whole
/// tile. The alphas of a row span come from one vectorised [`span_alpha`] call. `C` is the
/// channel count when known at compile time (4: colour and depth), 0 otherwise.
fn rasterize_tile<const C: usize>(
    inp: &RasterInputs,
    t: usize,
    strip: &mut Strip,
    list: &mut TileList,
) {
    inp.gather_into(t, list);
    let c = if C == 0 { inp.num_channels } else { C };
    let w = inp.grid.width as usize;
    let (x0, y0, x1, y1) = inp.tile_pixels(t);
    let n_px = ((x1 - x0) * (y1 - y0)) as usize;
    let strip_start = inp.offsets[t - t % inp.grid.tiles_x as usize];
    let stats = &mut strip.stats[inp.offsets[t] - strip_start..inp.offsets[t + 1] - strip_start];
    // Per tile row, bit i set when pixel x0 + i has terminated (tiles are ≤ 16 wide).
    let done: [Cell<u32>; TILE_SIZE as usize] = Default::default();
    let full = (1u32 << (x1 - x0)) - 1;
    let mut n_done = 0;
    let mut alphas = [0.0f32; SPAN];
    for (j, g) in list.splats.iter().enumerate() {
        if n_done == n_px {
            break;
        }
        let ch = &list.channels[j * c..(j + 1) * c];
        let mut s = PairStats::default();
        let live = |y: u32| done[(y - y0) as usize].get() != full;
        for_each_live_row(g, (x0, y0, x1, y1), live, |y, xa, xb| {
            let row = (y - y0) as usize;
            // Narrow the span to its pixels that are still blending; skip it when none.
            let (lo, hi) = (xa - x0, xb - x0);
            let active = (((1u32 << (hi - lo)) - 1) << lo) & !done[row].get();
            if active == 0 {
                return;
            }
            let (lo, hi) = (active.trailing_zeros(), 32 - active.leading_zeros());
            let n = (hi - lo) as usize;
            span_alpha(g, x0 + lo, n, y, inp.alpha_max, inp.cutoff, &mut alphas);
            let base = row * w + (x0 + lo) as usize;
            for (i, &alpha) in alphas[..n].iter().enumerate() {
                let bit = 1u32 << (lo as usize + i);
                if alpha == 0.0 || active & bit == 0 {
                    continue;
                }
                let k = base + i;
                let t = strip.final_t[k];
                let next_t = t * (1.0 - alpha);
                if next_t <= T_THRESHOLD {
                    done[row].set(done[row].get() | bit);
                    n_done += 1;
                    continue;
                }
                let wgt = alpha * t;
                for (a, v) in strip.channels[k * c..(k + 1) * c].iter_mut().zip(ch) {
                    *a += wgt * v;
                }
                s.sum_w2 += wgt * wgt;
                s.sum_w += wgt;
                s.n_pixels += 1;
                strip.final_t[k] = next_t;
                strip.last[k] = j as u32 + 1;
            }
        });
        stats[j] = s;
    }
}

/// Stage `rasterize_fwd`.
pub fn rasterize_fwd(inp: &RasterInputs) -> FwdImages {
    inp.check();
    let _span = tracing::debug_span!("render.rasterize_fwd", m = inp.isect.keys.len()).entered();
    let (w, h, c) = (inp.grid.width as usize, inp.grid.height as usize, inp.num_channels);
    let rows = TILE_SIZE as usize * w;
    let mut img = FwdImages {
        channels: vec![0.0; w * h * c],
        final_t: vec![1.0; w * h],
        last_contributor: vec![0; w * h],
        stats: vec![PairStats::default(); inp.isect.keys.len()],
    };
    let strips = inp.split_by_strip(&mut img.stats);
    img.channels
        .par_chunks_mut(rows * c)
        .zip(img.final_t.par_chunks_mut(rows))
        .zip(img.last_contributor.par_chunks_mut(rows))
        .zip(strips)
        .enumerate()
        .for_each_init(TileList::default, |list, (s, (((channels, final_t), last), stats))| {
            let mut strip = Strip { channels, final_t, last, stats };
            let tx = inp.grid.tiles_x as usize;
            for t in s * tx..(s + 1) * tx {
                if c == 4 {
                    rasterize_tile::<4>(inp, t, &mut strip, list);
                } else {
                    rasterize_tile::<0>(inp, t, &mut strip, list);
                }
            }
        });
    img
}

/// Convergence test of a finished forward pass (paper Eq. 5's product over covered
/// pixels): `[M]`, whether the pair's Gaussian was blended into at least one pixel of its
/// tile whose `pixel_pass` (`[H, W]`) entry is false. A pair at list position `j` of its
/// tile was blended into pixel `p` exactly when `j < last_contributor[p]` and its alpha there
/// is positive (the pixel cannot have terminated before its last contributor), so only
/// failing pixels are visited and no transmittance is recomputed.
pub fn failing_pairs(
    inp: &RasterInputs,
    last_contributor: &[u32],
    pixel_pass: &[bool],
) -> Vec<bool> {
    inp.check();
    let w = inp.grid.width as usize;
    assert_eq!(last_contributor.len(), w * inp.grid.height as usize, "last_contributor [H, W]");
    assert_eq!(pixel_pass.len(), last_contributor.len(), "pixel_pass [H, W]");
    let _span = tracing::debug_span!("render.failing_pairs", m = inp.isect.keys.len()).entered();
    let mut fail = vec![false; inp.isect.keys.len()];
    let tx = inp.grid.tiles_x as usize;
    inp.split_by_strip(&mut fail).into_par_iter().enumerate().for_each(|(s, strip)| {
        let strip_start = inp.offsets[s * tx];
        for t in s * tx..(s + 1) * tx {
            let (x0, y0, x1, y1) = inp.tile_pixels(t);
            let last_of = |p: usize| if pixel_pass[p] { 0 } else { last_contributor[p] };
            // Per tile row, bit i set when pixel x0 + i fails and something was blended.
            let mut failing = [0u32; TILE_SIZE as usize];
            let mut max_last = 0;
            for y in y0..y1 {
                for x in x0..x1 {
                    let l = last_of(y as usize * w + x as usize);
                    max_last = max_last.max(l as usize);
                    failing[(y - y0) as usize] |= u32::from(l > 0) << (x - x0);
                }
            }
            let ids = &inp.isect.gaussian[inp.offsets[t]..inp.offsets[t] + max_last];
            let out = &mut strip[inp.offsets[t] - strip_start..];
            let mut alphas = [0.0f32; SPAN];
            for (j, &g) in ids.iter().enumerate() {
                let g = &inp.splats[g as usize];
                let hit = Cell::new(false);
                let live = |y: u32| !hit.get() && failing[(y - y0) as usize] != 0;
                for_each_live_row(g, (x0, y0, x1, y1), live, |y, xa, xb| {
                    let (lo, hi) = (xa - x0, xb - x0);
                    let active = (((1u32 << (hi - lo)) - 1) << lo) & failing[(y - y0) as usize];
                    if active == 0 {
                        return;
                    }
                    let (lo, hi) = (active.trailing_zeros(), 32 - active.leading_zeros());
                    let n = (hi - lo) as usize;
                    span_alpha(g, x0 + lo, n, y, inp.alpha_max, inp.cutoff, &mut alphas);
                    let base = y as usize * w + (x0 + lo) as usize;
                    hit.set(alphas[..n].iter().enumerate().any(|(i, &a)| {
                        a > 0.0
                            && active & (1 << (lo as usize + i)) != 0
                            && j < last_of(base + i) as usize
                    }));
                });
                out[j] = hit.get();
            }
        }
    });
    fail
}

/// [`failing_pairs`] over the pixels where the pair's blending weight T·α reaches
/// `min_weight` (the covered-pixel set of the convergence test as a parameter, issue 15
/// item 4): each failing pixel walks its tile's list front to back up to its last
/// contributor, with the forward pass's alphas and transmittance (so the weights are the
/// forward's, bit for bit). Reference for the GPU `fail_pairs` kernel with a weight floor.
pub fn failing_pairs_weighted(
    inp: &RasterInputs,
    last_contributor: &[u32],
    pixel_pass: &[bool],
    min_weight: f32,
) -> Vec<bool> {
    inp.check();
    let w = inp.grid.width as usize;
    assert_eq!(last_contributor.len(), w * inp.grid.height as usize, "last_contributor [H, W]");
    assert_eq!(pixel_pass.len(), last_contributor.len(), "pixel_pass [H, W]");
    let _span = tracing::debug_span!("render.failing_pairs_weighted").entered();
    let mut fail = vec![false; inp.isect.keys.len()];
    let tx = inp.grid.tiles_x as usize;
    inp.split_by_strip(&mut fail).into_par_iter().enumerate().for_each(|(s, strip)| {
        let strip_start = inp.offsets[s * tx];
        let mut alpha = [0.0f32; SPAN];
        for t in s * tx..(s + 1) * tx {
            let (x0, y0, x1, y1) = inp.tile_pixels(t);
            let ids = &inp.isect.gaussian[inp.offsets[t]..inp.offsets[t + 1]];
            let out = &mut strip[inp.offsets[t] - strip_start..];
            for y in y0..y1 {
                for x in x0..x1 {
                    let p = y as usize * w + x as usize;
                    if pixel_pass[p] {
                        continue;
                    }
                    let mut tr = 1.0f32;
                    for (j, &g) in ids[..last_contributor[p] as usize].iter().enumerate() {
                        let g = &inp.splats[g as usize];
                        span_alpha(g, x, 1, y, inp.alpha_max, inp.cutoff, &mut alpha);
                        if alpha[0] == 0.0 {
                            continue;
                        }
                        if alpha[0] * tr >= min_weight {
                            out[j] = true;
                        }
                        tr *= 1.0 - alpha[0];
                    }
                }
            }
        }
    });
    fail
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::render::cpu::blend::eval_alpha;
    use crate::render::cpu::isect::{isect_tiles, tile_ranges};

    /// Bins `splats` into `grid`'s tiles and hands the rasterizers' inputs (α clamped at
    /// 0.99) to `f`.
    pub(in crate::render::cpu) fn with_inputs<R>(
        grid: TileGrid,
        splats: &[Splat2d],
        channels: &[f32],
        num_channels: usize,
        cutoff: Cutoff,
        f: impl FnOnce(&RasterInputs) -> R,
    ) -> R {
        let isect = isect_tiles(&grid, splats);
        let offsets = tile_ranges(&isect.keys, grid.num_tiles());
        f(&RasterInputs {
            grid,
            splats,
            channels,
            num_channels,
            isect: &isect,
            offsets: &offsets,
            alpha_max: 0.99,
            cutoff,
        })
    }

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
        let out = with_inputs(grid, &splats, &channels, 3, Cutoff::Hard, rasterize_fwd);
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
        let out = with_inputs(grid, &splats, &channels, 1, Cutoff::Hard, rasterize_fwd);
        // α = 0.99 at the centre: T = 1e-2 after one, 1e-4 after two → the second is skipped.
        let i = 8 * 16 + 8;
        assert_eq!(out.last_contributor[i], 1);
        assert!((out.final_t[i] - 0.01).abs() < 1e-6);
    }
}
