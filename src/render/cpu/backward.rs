//! Stage 5, `rasterize_bwd`: gradients of the blended images w.r.t. each Gaussian's 2D
//! parameters and channel values (reference for `gpu::rasterize_bwd`).
//!
//! Mapping: rayon over tiles; within a tile each pixel (one GPU thread) walks the tile's list
//! back to front, starting at its `last_contributor` with `T = final_t` and recovering each
//! earlier transmittance as `T / (1 − α)`; the CPU runs the same per-pixel arithmetic
//! Gaussian-major (see `backward_tile`). Reads the same
//! inputs as the forward pass plus `[H, W]` final transmittance and last contributor and the
//! cotangents `[H, W, C]` (dL/d blended channels) and `[H, W]` (dL/d alpha). Per-pair
//! gradients accumulate in a tile-local `[len, 6 + C]` buffer in pixel order; the tiles'
//! buffers are then summed per Gaussian sequentially in list order, so the result does not
//! depend on the thread count.

use rayon::prelude::*;

use super::blend::{SpanEval, alpha_vjp, for_each_row, span_alpha};
use super::forward::{RasterInputs, TileList};
use super::project::Splat2dGrad;

/// Per-Gaussian gradients from [`rasterize_bwd`], `[N]` / `[N, C]`, canonical index.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BwdGrads {
    /// dL/d 2D parameters (`depth` is left 0: the depth channel's gradient is in `channels`).
    pub splats: Vec<Splat2dGrad>,
    /// `[N, C]` dL/d channel values.
    pub channels: Vec<f32>,
}

/// Gradient slots per pair: mean2d (2), conic (3), opacity (1), then C channels.
const FIXED: usize = 6;

/// Backward of one tile, Gaussian-major from the back: the Gaussians of the tile's list in
/// reverse order each update the pixels of their footprint that they were blended into
/// (`j < last_contributor`). Per pixel this is exactly the back-to-front walk of the GPU
/// thread (same operations, same order), so the results are the same bits. Returns the
/// tile's `[len, 6 + C]` per-pair gradients.
fn backward_tile(
    inp: &RasterInputs,
    t: usize,
    final_t: &[f32],
    last_contributor: &[u32],
    v_channels: &[f32],
    v_alpha: &[f32],
    list: &mut TileList,
) -> Vec<f32> {
    inp.gather_into(t, list);
    let c = inp.num_channels;
    let stride = FIXED + c;
    let w = inp.grid.width as usize;
    let (x0, y0, x1, y1) = inp.tile_pixels(t);
    let tw = (x1 - x0) as usize;
    let n_px = tw * (y1 - y0) as usize;
    let mut tr = Vec::with_capacity(n_px);
    let mut last = Vec::with_capacity(n_px);
    for y in y0..y1 {
        let i = y as usize * w + x0 as usize;
        tr.extend_from_slice(&final_t[i..i + tw]);
        last.extend_from_slice(&last_contributor[i..i + tw]);
    }
    let max_last = last.iter().copied().max().unwrap_or(0) as usize;
    let mut buf = vec![0.0f32; n_px * c];
    let mut grads = vec![0.0f32; list.splats.len() * stride];
    for j in (0..max_last).rev() {
        let g = &list.splats[j];
        let ch = &list.channels[j * c..(j + 1) * c];
        let (fixed, v_ch_slot) = grads[j * stride..(j + 1) * stride].split_at_mut(FIXED);
        let mut acc = [0.0f32; FIXED];
        let mut span = SpanEval::default();
        for_each_row(g, x0, y0, x1, y1, |y, xa, xb| {
            let py = y as f32 + 0.5;
            let row = (y - y0) as usize * tw;
            span_alpha(g, xa, (xb - xa) as usize, y, inp.alpha_max, inp.cutoff, &mut span);
            for x in xa..xb {
                let k = row + (x - x0) as usize;
                let i = (x - xa) as usize;
                if j as u32 >= last[k] || span.alpha[i] == 0.0 {
                    continue;
                }
                let e = span.lane(g, i, x as f32 + 0.5, py);
                let p = y as usize * w + x as usize;
                let v_pix = &v_channels[p * c..(p + 1) * c];
                let ft = final_t[p];
                let ra = 1.0 / (1.0 - e.alpha);
                tr[k] *= ra;
                let t = tr[k];
                let wgt = e.alpha * t;
                let b = &mut buf[k * c..(k + 1) * c];
                let mut v_a = ft * ra * v_alpha[p];
                for q in 0..c {
                    v_ch_slot[q] += wgt * v_pix[q];
                    v_a += (ch[q] * t - b[q] * ra) * v_pix[q];
                    b[q] += ch[q] * wgt;
                }
                let (vm, vc, vo) = alpha_vjp(g, &e, v_a, inp.alpha_max, inp.cutoff);
                acc[0] += vm[0];
                acc[1] += vm[1];
                acc[2] += vc[0];
                acc[3] += vc[1];
                acc[4] += vc[2];
                acc[5] += vo;
            }
        });
        fixed.copy_from_slice(&acc);
    }
    grads
}

/// Stage `rasterize_bwd`. `final_t` and `last_contributor` come from the forward pass of
/// the same inputs; `v_channels` is `[H, W, C]`, `v_alpha` `[H, W]`.
pub fn rasterize_bwd(
    inp: &RasterInputs,
    final_t: &[f32],
    last_contributor: &[u32],
    v_channels: &[f32],
    v_alpha: &[f32],
) -> BwdGrads {
    let (w, h, c) = (inp.grid.width as usize, inp.grid.height as usize, inp.num_channels);
    assert_eq!(final_t.len(), w * h, "final_t must be [H, W]");
    assert_eq!(last_contributor.len(), w * h, "last_contributor must be [H, W]");
    assert_eq!(v_channels.len(), w * h * c, "v_channels must be [H, W, C]");
    assert_eq!(v_alpha.len(), w * h, "v_alpha must be [H, W]");
    let _span = tracing::debug_span!("render.rasterize_bwd", m = inp.isect.keys.len()).entered();
    let stride = FIXED + c;
    let tiles: Vec<Vec<f32>> = (0..inp.grid.num_tiles())
        .into_par_iter()
        .map_init(TileList::default, |list, t| {
            backward_tile(inp, t, final_t, last_contributor, v_channels, v_alpha, list)
        })
        .collect();
    let n = inp.splats.len();
    let mut out = BwdGrads { splats: vec![Splat2dGrad::default(); n], channels: vec![0.0; n * c] };
    for (t, grads) in tiles.iter().enumerate() {
        let ids = &inp.isect.gaussian[inp.offsets[t]..inp.offsets[t + 1]];
        for (j, &g) in ids.iter().enumerate() {
            let s = &grads[j * stride..(j + 1) * stride];
            let o = &mut out.splats[g as usize];
            o.mean2d[0] += s[0];
            o.mean2d[1] += s[1];
            o.conic[0] += s[2];
            o.conic[1] += s[3];
            o.conic[2] += s[4];
            o.opacity += s[5];
            for (dst, v) in
                out.channels[g as usize * c..(g as usize + 1) * c].iter_mut().zip(&s[FIXED..])
            {
                *dst += v;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::Cutoff;
    use crate::render::cpu::forward::rasterize_fwd;
    use crate::render::cpu::forward::tests::with_inputs;
    use crate::render::cpu::isect::TileGrid;
    use crate::render::cpu::project::Splat2d;

    fn splat(x: f32, y: f32, conic: [f32; 3], opacity: f32, depth: f32) -> Splat2d {
        let power = (255.0 * opacity).ln();
        Splat2d {
            mean2d: [x, y],
            conic,
            depth,
            opacity,
            power,
            extent: [40.0; 2],
            radius: 40.0,
            valid: true,
        }
    }

    /// Accessor of one scalar of a splat.
    type Field = fn(&mut Splat2d) -> &mut f32;

    /// Finite differences of L = Σ v_ch·channels + Σ v_a·alpha w.r.t. every 2D parameter and
    /// channel value, with the smooth cutoff so that L is differentiable.
    #[test]
    fn gradients_match_finite_differences_in_2d() {
        let grid = TileGrid::new(24, 20);
        let splats = vec![
            splat(9.0, 8.0, [0.05, 0.01, 0.08], 0.7, 1.0),
            splat(13.0, 11.0, [0.04, -0.015, 0.06], 0.6, 2.0),
            splat(17.0, 9.0, [0.09, 0.0, 0.05], 0.5, 3.0),
        ];
        let channels = vec![0.9, 0.1, 0.3, 0.2, 0.8, 0.5, 0.4, 0.6, 0.7];
        let (w, h) = (24usize, 20usize);
        let v_ch: Vec<f32> = (0..w * h * 3).map(|i| ((i * 7919 % 13) as f32 - 6.0) * 0.1).collect();
        let v_a: Vec<f32> = (0..w * h).map(|i| ((i * 104729 % 7) as f32 - 3.0) * 0.1).collect();
        let loss = |splats: &[Splat2d], channels: &[f32]| -> f64 {
            let f = with_inputs(grid, splats, channels, 3, Cutoff::Smooth, rasterize_fwd);
            let a: f64 =
                f.final_t.iter().zip(&v_a).map(|(t, v)| (1.0 - *t as f64) * *v as f64).sum();
            a + f.channels.iter().zip(&v_ch).map(|(c, v)| *c as f64 * *v as f64).sum::<f64>()
        };
        let g = with_inputs(grid, &splats, &channels, 3, Cutoff::Smooth, |inp| {
            let f = rasterize_fwd(inp);
            rasterize_bwd(inp, &f.final_t, &f.last_contributor, &v_ch, &v_a)
        });
        let h_step = 1e-3f32;
        let mut failures = Vec::new();
        for gi in 0..3 {
            // (name, field, analytic, step): σ moves by ½dx²·h for a conic step, with dx up to
            // ~20 px, so conic steps are small to stay within the smooth ramp's curvature.
            let params: [(&str, Field, f32, f32); 6] = [
                ("mean.x", |s| &mut s.mean2d[0], g.splats[gi].mean2d[0], h_step),
                ("mean.y", |s| &mut s.mean2d[1], g.splats[gi].mean2d[1], h_step),
                ("conic.a", |s| &mut s.conic[0], g.splats[gi].conic[0], 5e-5),
                ("conic.b", |s| &mut s.conic[1], g.splats[gi].conic[1], 5e-5),
                ("conic.c", |s| &mut s.conic[2], g.splats[gi].conic[2], 5e-5),
                ("opacity", |s| &mut s.opacity, g.splats[gi].opacity, h_step),
            ];
            for (name, field, analytic, step) in params {
                let (mut p, mut m) = (splats.clone(), splats.clone());
                *field(&mut p[gi]) += step;
                *field(&mut m[gi]) -= step;
                let fd = (loss(&p, &channels) - loss(&m, &channels)) / (2.0 * step as f64);
                if (fd - analytic as f64).abs() > 2e-2 + 2e-2 * fd.abs() {
                    failures.push(format!("{name} of {gi}: fd {fd} vs {analytic}"));
                }
            }
            for k in 0..3 {
                let (mut p, mut m) = (channels.clone(), channels.clone());
                p[gi * 3 + k] += h_step;
                m[gi * 3 + k] -= h_step;
                let fd = (loss(&splats, &p) - loss(&splats, &m)) / (2.0 * h_step as f64);
                let analytic = g.channels[gi * 3 + k];
                if (fd - analytic as f64).abs() > 1e-2 + 1e-2 * fd.abs() {
                    failures.push(format!("channel {k} of {gi}: fd {fd} vs {analytic}"));
                }
            }
        }
        assert!(failures.is_empty(), "{failures:#?}");
    }
}
