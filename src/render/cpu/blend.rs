//! The per-(Gaussian, pixel) alpha of 3DGS and its vector-Jacobian product, shared by the
//! forward ([`super::forward`]) and backward ([`super::backward`]) rasterizers (and mirrored
//! by the GPU shader), so that both passes make exactly the same skip decisions.
//!
//! `α = min(alpha_max, o · exp(-σ))` with `σ = ½ dᵀ Σ⁻¹ d`, `d = mean2d − pixel centre`;
//! pixels where `σ ∉ [0, ln(255·o)]` or `o·exp(-σ) < ALPHA_THRESHOLD` are skipped.
//! [`Cutoff::Smooth`] replaces that step by a C¹ ramp (test-only, for finite differences).
//!
//! Evaluation order (the GPU shader must mirror it to give the same bits):
//! `σ = 0.5·(a·dx·dx + c·dy·dy) + b·dx·dy` (left to right, no fused multiply-add), the
//! exponential is [`exp_neg`] (a Cephes-style polynomial, not the platform's `expf`),
//! `raw = o·vis`. The evaluation is branch-free so that [`span_alpha`] evaluates a row span
//! of a tile in a loop the compiler vectorises; [`eval_alpha`] (one pixel) runs the same
//! arithmetic, so the forward pass (spans) and the backward pass make the same skip
//! decisions. The row spans themselves come from [`for_each_row`]; the forward pass skips
//! spans and rows whose pixels have all terminated.

use super::project::Splat2d;
use crate::render::Cutoff;
use crate::render::constants::{ALPHA_THRESHOLD, TILE_SIZE};

/// One evaluated (Gaussian, pixel) pair, kept for the VJP.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlphaEval {
    /// The blending alpha (after clamp and cutoff).
    pub alpha: f32,
    /// `o · exp(-σ)` before the clamp.
    pub raw: f32,
    /// `exp(-σ)`.
    pub vis: f32,
    /// `mean2d.x − pixel.x`.
    pub dx: f32,
    /// `mean2d.y − pixel.y`.
    pub dy: f32,
}

/// Lanes of [`span_alpha`]: the longest row span inside a tile.
pub const SPAN: usize = TILE_SIZE as usize;

/// `exp(x)` for `x <= 0` (larger inputs are clamped to 0, inputs below -87 to -87, NaN
/// gives `exp(-87)`): Cephes' `expf` without branches. `x = n·ln 2 + r` with n rounded to
/// nearest by adding 1.5·2²³, a degree-5 polynomial for `exp(r)` on |r| ≤ ln(2)/2, and
/// `2ⁿ` assembled from the exponent bits. Relative error below 3e-7.
#[inline(always)]
pub fn exp_neg(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0;
    let x = if x > -87.0 { x.min(0.0) } else { -87.0 };
    let t = x * std::f32::consts::LOG2_E + ROUND;
    let n = t - ROUND;
    let r = x - n * 0.693_359_4 - n * -2.121_944_4e-4;
    let p = ((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let e = r * r * p + r + 1.0;
    let k = t.to_bits().wrapping_sub(ROUND.to_bits()).wrapping_add(127) << 23;
    e * f32::from_bits(k)
}

/// The blending alpha and its intermediates at offset `(dx, dy)` from the mean, branch-free:
/// `(alpha, raw, vis)`, with `alpha == 0` when the pair does not contribute.
#[inline(always)]
fn alpha_parts(g: &Splat2d, dx: f32, dy: f32, alpha_max: f32, cutoff: Cutoff) -> (f32, f32, f32) {
    let [a, b, c] = g.conic;
    let sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
    let vis = exp_neg(-sigma);
    let raw = g.opacity * vis;
    // σ > ln(255·o) ⟺ o·exp(-σ) < 1/255; the `raw` test catches rounding at the edge.
    let inside = sigma >= 0.0 && sigma <= g.power && raw >= ALPHA_THRESHOLD;
    let alpha = match cutoff {
        Cutoff::Hard => raw.min(alpha_max),
        Cutoff::Smooth => (raw * smoothstep(ramp(raw))).min(alpha_max),
    };
    (if inside && alpha > 0.0 { alpha } else { 0.0 }, raw, vis)
}

/// Alpha of Gaussian `g` at the pixel centre `(px, py)` (pixel index + 0.5), or `None` when
/// it does not contribute. The same bits as [`span_alpha`] at that pixel.
#[inline]
pub fn eval_alpha(
    g: &Splat2d,
    px: f32,
    py: f32,
    alpha_max: f32,
    cutoff: Cutoff,
) -> Option<AlphaEval> {
    let dx = g.mean2d[0] - px;
    let dy = g.mean2d[1] - py;
    let (alpha, raw, vis) = alpha_parts(g, dx, dy, alpha_max, cutoff);
    (alpha > 0.0).then_some(AlphaEval { alpha, raw, vis, dx, dy })
}

/// Where [`span_alpha`] puts lane `i`'s alpha, `o · exp(-σ)` and `exp(-σ)`: an array of
/// alphas keeps the alphas only (the forward pass; the rest is never computed once
/// inlined), a [`SpanEval`] keeps all three (the backward pass).
pub trait SpanOut {
    /// Store lane `i < SPAN`.
    fn set(&mut self, i: usize, alpha: f32, raw: f32, vis: f32);
}

impl SpanOut for [f32; SPAN] {
    #[inline(always)]
    fn set(&mut self, i: usize, alpha: f32, _raw: f32, _vis: f32) {
        self[i] = alpha;
    }
}

/// Alphas of `g` at the pixel centres `(xa + i + 0.5, y + 0.5)` for the lanes `i < n`
/// (`n <= SPAN`), 0 where the pair does not contribute, stored in `out` (with the
/// intermediates it keeps); lanes `i >= n` hold unspecified values. Branch-free groups of
/// 4 lanes (vectorised by the compiler) up to `n`; lane `i` has exactly the bits of
/// [`eval_alpha`] at that pixel.
#[inline]
pub fn span_alpha(
    g: &Splat2d,
    xa: u32,
    n: usize,
    y: u32,
    alpha_max: f32,
    cutoff: Cutoff,
    out: &mut impl SpanOut,
) {
    let dy = g.mean2d[1] - (y as f32 + 0.5);
    let x0 = xa as f32;
    for q in 0..n.div_ceil(4).min(SPAN / 4) {
        let xq = x0 + (4 * q) as f32;
        for l in 0..4 {
            let dx = g.mean2d[0] - ((xq + l as f32) + 0.5);
            let (alpha, raw, vis) = alpha_parts(g, dx, dy, alpha_max, cutoff);
            out.set(4 * q + l, alpha, raw, vis);
        }
    }
}

/// Alpha and intermediates of one row span, lane `i` = pixel `xa + i` (see [`span_alpha`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct SpanEval {
    /// Blending alphas, 0 where the pair does not contribute.
    pub alpha: [f32; SPAN],
    /// `o · exp(-σ)` before the clamp.
    pub raw: [f32; SPAN],
    /// `exp(-σ)`.
    pub vis: [f32; SPAN],
}

impl SpanOut for SpanEval {
    #[inline(always)]
    fn set(&mut self, i: usize, alpha: f32, raw: f32, vis: f32) {
        self.alpha[i] = alpha;
        self.raw[i] = raw;
        self.vis[i] = vis;
    }
}

impl SpanEval {
    /// Lane `i` as an [`AlphaEval`] (`dx`, `dy` as [`eval_alpha`] computes them at the
    /// pixel centre `(px, py)`).
    #[inline]
    pub fn lane(&self, g: &Splat2d, i: usize, px: f32, py: f32) -> AlphaEval {
        AlphaEval {
            alpha: self.alpha[i],
            raw: self.raw[i],
            vis: self.vis[i],
            dx: g.mean2d[0] - px,
            dy: g.mean2d[1] - py,
        }
    }
}

/// Conservative pixel footprint of `g` inside the pixel rectangle `[x0, x1) x [y0, y1)`:
/// calls `row(y, xa, xb)` for every row whose pixel centres may satisfy `σ <= power`, with
/// the column range `[xa, xb)` that contains them (widened by a small margin so that
/// rounding never drops a pixel; [`eval_alpha`] makes the exact decision). Lets the
/// rasterizers visit about the ellipse's area instead of the whole tile.
#[inline]
pub fn for_each_row(
    g: &Splat2d,
    x0: u32,
    y0: u32,
    x1: u32,
    y1: u32,
    row: impl FnMut(u32, u32, u32),
) {
    for_each_live_row(g, (x0, y0, x1, y1), |_| true, row);
}

/// [`for_each_row`] over the rectangle `(x0, y0, x1, y1)` that skips, before any span
/// arithmetic, the rows `y` where `live(y)` is false (e.g. rows whose pixels have all
/// terminated).
#[inline]
pub fn for_each_live_row(
    g: &Splat2d,
    (x0, y0, x1, y1): (u32, u32, u32, u32),
    live: impl Fn(u32) -> bool,
    mut row: impl FnMut(u32, u32, u32),
) {
    let [mx, my] = g.mean2d;
    let [a, b, c] = g.conic;
    let p = g.power * (1.0 + 1e-3) + 1e-3;
    let ext_y = g.extent[1] + 1.0;
    let ya = ((my - ext_y - 0.5).floor().max(y0 as f32)) as u32;
    let yb = ((my + ext_y + 0.5).ceil().min(y1 as f32)).max(ya as f32) as u32;
    for y in ya..yb {
        if !live(y) {
            continue;
        }
        let dy = my - (y as f32 + 0.5);
        // σ(dx) = ½a dx² + b dy dx + ½c dy² ≤ p, dx = mx − px.
        let disc = b * b * dy * dy - a * (c * dy * dy - 2.0 * p);
        if disc < 0.0 {
            continue;
        }
        let root = disc.sqrt();
        let (dx_lo, dx_hi) = ((-b * dy - root) / a, (-b * dy + root) / a);
        // Pixel x is in when its centre x + 0.5 lies in [mx − dx_hi, mx − dx_lo]; the
        // widened `p` is the rounding margin. Clamp before the casts (no floor calls).
        let lo = (mx - dx_hi - 0.5).max(x0 as f32);
        let hi = (mx - dx_lo - 0.5).min(x1 as f32 - 1.0);
        if lo > hi {
            continue;
        }
        let t = lo as u32;
        let xa = if (t as f32) < lo { t + 1 } else { t };
        let xb = hi as u32 + 1;
        if xa < xb {
            row(y, xa, xb);
        }
    }
}

/// Gradient of the alpha w.r.t. the Gaussian's 2D parameters, given `v_alpha = dL/dα`.
/// Returns `(v_mean2d, v_conic, v_opacity)`; zero where α is clamped at `alpha_max`.
#[inline]
pub fn alpha_vjp(
    g: &Splat2d,
    e: &AlphaEval,
    v_alpha: f32,
    alpha_max: f32,
    cutoff: Cutoff,
) -> ([f32; 2], [f32; 3], f32) {
    let d_alpha_d_raw = match cutoff {
        Cutoff::Hard => {
            if e.raw < alpha_max {
                1.0
            } else {
                0.0
            }
        }
        Cutoff::Smooth => {
            let t = ramp(e.raw);
            if e.raw * smoothstep(t) < alpha_max {
                smoothstep(t) + e.raw * smoothstep_deriv(t) / ALPHA_THRESHOLD
            } else {
                0.0
            }
        }
    };
    let v_raw = v_alpha * d_alpha_d_raw;
    let v_opacity = e.vis * v_raw;
    let v_sigma = -e.raw * v_raw;
    let [a, b, c] = g.conic;
    let (dx, dy) = (e.dx, e.dy);
    let v_conic = [0.5 * dx * dx * v_sigma, dx * dy * v_sigma, 0.5 * dy * dy * v_sigma];
    let v_mean = [v_sigma * (a * dx + b * dy), v_sigma * (b * dx + c * dy)];
    (v_mean, v_conic, v_opacity)
}

fn ramp(raw: f32) -> f32 {
    ((raw - ALPHA_THRESHOLD) / ALPHA_THRESHOLD).clamp(0.0, 1.0)
}

fn smoothstep(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

fn smoothstep_deriv(t: f32) -> f32 {
    if t <= 0.0 || t >= 1.0 { 0.0 } else { 6.0 * t * (1.0 - t) }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splat(opacity: f32) -> Splat2d {
        Splat2d {
            mean2d: [10.0, 20.0],
            conic: [0.5, 0.1, 0.25],
            opacity,
            power: (255.0 * opacity).ln(),
            ..Splat2d::default()
        }
    }

    #[test]
    fn alpha_matches_formula_clamps_and_cuts() {
        let g = splat(0.8);
        let e = eval_alpha(&g, 11.0, 19.0, 0.99, Cutoff::Hard).unwrap();
        let sigma: f32 = 0.5 * (0.5 * 1.0 + 0.25 * 1.0) + -0.1 * 1.0;
        assert!((e.alpha - 0.8 * (-sigma).exp()).abs() < 1e-6);
        let full = splat(1.0);
        assert_eq!(eval_alpha(&full, 10.0, 20.0, 0.99, Cutoff::Hard).unwrap().alpha, 0.99);
        assert_eq!(eval_alpha(&full, 10.0, 20.0, 0.999, Cutoff::Hard).unwrap().alpha, 0.999);
        assert!(eval_alpha(&g, 40.0, 20.0, 0.99, Cutoff::Hard).is_none());
    }

    #[test]
    fn exp_neg_is_accurate_and_clamped() {
        for i in 0..87_000 {
            let x = -(i as f32) * 1e-3;
            let want = (x as f64).exp();
            let got = exp_neg(x) as f64;
            assert!(((got - want) / want).abs() < 3e-7, "exp({x}) = {got}, want {want}");
        }
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(1.0), 1.0);
        assert_eq!(exp_neg(-1e30), exp_neg(-87.0));
        assert_eq!(exp_neg(f32::NAN), exp_neg(-87.0));
    }

    #[test]
    fn span_lanes_have_the_bits_of_single_pixel_evaluation() {
        let mut g = splat(0.9);
        g.conic = [0.3, -0.12, 0.2];
        for cutoff in [Cutoff::Hard, Cutoff::Smooth] {
            for y in 10..31 {
                for (xa, n) in [(0u32, 16usize), (3, 9), (17, 1), (5, 0)] {
                    let mut out = [f32::NAN; SPAN];
                    span_alpha(&g, xa, n, y, 0.99, cutoff, &mut out);
                    for (i, a) in out[..n].iter().enumerate() {
                        let px = (xa + i as u32) as f32 + 0.5;
                        let e = eval_alpha(&g, px, y as f32 + 0.5, 0.99, cutoff);
                        let want = e.map_or(0.0, |e| e.alpha);
                        assert_eq!(a.to_bits(), want.to_bits(), "lane {i} of ({xa}, {y})");
                    }
                }
            }
        }
    }

    #[test]
    fn smooth_cutoff_is_continuous_at_threshold_and_exact_above() {
        let g = splat(0.5);
        let mut prev = 0.0f32;
        // Walk outward along x; the smooth alpha must fall monotonically to 0 without a step.
        for i in 0..2000 {
            let x = 10.0 + i as f32 * 0.005;
            let a = eval_alpha(&g, x, 20.0, 0.99, Cutoff::Smooth).map_or(0.0, |e| e.alpha);
            // Steps of 0.005 px: at most 1e-2 in the steep core, and far below the hard
            // cutoff's jump of 1/255 near the threshold.
            let tol = if prev < 3.0 * ALPHA_THRESHOLD { 5e-4 } else { 1e-2 };
            if i > 0 {
                assert!((a - prev).abs() < tol, "jump at x = {x}: {prev} -> {a}");
            }
            prev = a;
            let hard = eval_alpha(&g, x, 20.0, 0.99, Cutoff::Hard).map_or(0.0, |e| e.alpha);
            if hard > 2.0 * ALPHA_THRESHOLD {
                assert_eq!(a, hard);
            }
        }
        assert_eq!(prev, 0.0);
    }

    #[test]
    fn row_spans_contain_every_contributing_pixel() {
        let mut g = splat(0.9);
        g.conic = [0.08, -0.05, 0.2];
        let det = g.conic[0] * g.conic[2] - g.conic[1] * g.conic[1];
        // Bounding-box half-widths from the covariance (inverse of the conic).
        g.extent =
            [(2.0 * g.power * g.conic[2] / det).sqrt(), (2.0 * g.power * g.conic[0] / det).sqrt()];
        let mut visited = vec![false; 64 * 64];
        for_each_row(&g, 0, 0, 64, 64, |y, xa, xb| {
            for x in xa..xb {
                visited[(y * 64 + x) as usize] = true;
            }
        });
        let mut hits = 0;
        for y in 0..64u32 {
            for x in 0..64u32 {
                if eval_alpha(&g, x as f32 + 0.5, y as f32 + 0.5, 0.99, Cutoff::Hard).is_some() {
                    assert!(visited[(y * 64 + x) as usize], "pixel ({x}, {y}) missed");
                    hits += 1;
                }
            }
        }
        let n_visited = visited.iter().filter(|v| **v).count();
        assert!(hits > 50 && n_visited < hits * 2, "{n_visited} visited for {hits} hits");
    }

    #[test]
    fn vjp_matches_finite_differences() {
        for cutoff in [Cutoff::Hard, Cutoff::Smooth] {
            let g = splat(0.6);
            let (px, py) = (12.3, 18.9);
            let e = eval_alpha(&g, px, py, 0.99, cutoff).unwrap();
            let (vm, vc, vo) = alpha_vjp(&g, &e, 1.0, 0.99, cutoff);
            let f = |g: &Splat2d| eval_alpha(g, px, py, 0.99, cutoff).unwrap().alpha as f64;
            let h = 1e-3;
            let fd = |m: &dyn Fn(&mut Splat2d, f32)| {
                let (mut a, mut b) = (g, g);
                m(&mut a, h);
                m(&mut b, -h);
                (f(&a) - f(&b)) / (2.0 * h as f64)
            };
            let checks = [
                (vm[0], fd(&|s, d| s.mean2d[0] += d)),
                (vm[1], fd(&|s, d| s.mean2d[1] += d)),
                (vc[0], fd(&|s, d| s.conic[0] += d)),
                (vc[1], fd(&|s, d| s.conic[1] += d)),
                (vc[2], fd(&|s, d| s.conic[2] += d)),
                (vo, fd(&|s, d| s.opacity += d)),
            ];
            for (i, (an, num)) in checks.iter().enumerate() {
                assert!((*an as f64 - num).abs() < 2e-3, "{cutoff:?} case {i}: {an} vs {num}");
            }
        }
    }
}
