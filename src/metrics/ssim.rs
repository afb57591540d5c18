//! SSIM with DyCheck's masked variant mSSIM (`dycheck/core/metrics/image.py::compute_ssim`),
//! reproduced exactly:
//!
//! - window: the 11-tap Gaussian `f_i ∝ exp(−0.5·((i − 5)/1.5)²)`, normalised; `k1 = 0.01`,
//!   `k2 = 0.03`, data range 1;
//! - separable **valid** convolution, horizontal pass then vertical pass, so the SSIM map is
//!   `[(H − 10), (W − 10), 3]`;
//! - partial convolution per pass: `blur(z, m) = where(m' ≠ 0, conv(z·m, f)·11 / m', 0)` with
//!   `m' = conv(m, ones)`; the vertical pass uses the binary `m' ≠ 0` of the horizontal pass
//!   as its mask;
//! - `σ00 = blur(a²) − μ0²` (likewise σ11, σ01), clipped: `σ00, σ11 ≥ 0`,
//!   `σ01 = sign(σ01)·min(√(σ00·σ11), |σ01|)`;
//! - the score is the mean of the map; where no pixel of a window is valid, μ and σ are 0
//!   and the map is exactly 1.
//!
//! Without a mask (all ones) every weight `11 / m'` is 1 and this is the standard SSIM of
//! Wang et al. with a valid-mode Gaussian window (as `dm_pix.ssim` computes it).
//! Arithmetic is f64; the three channels are computed in parallel (rayon) and summed in
//! channel order. Each channel streams through the image once: the horizontal pass of the
//! five signals (a, b, a², b², ab) fills a ring of 11 rows from which the vertical pass and
//! the map are computed, so memory stays `O(W)` and nothing is allocated per row.

use rayon::prelude::*;

use super::{Error, Result, check_pair};
use crate::formats::png::Image;

/// Taps of the Gaussian window.
pub const WINDOW: usize = 11;
/// Standard deviation of the Gaussian window, pixels.
pub const SIGMA: f64 = 1.5;
/// SSIM constant k1 (c1 = k1², data range 1).
pub const K1: f64 = 0.01;
/// SSIM constant k2 (c2 = k2²).
pub const K2: f64 = 0.03;

/// The normalised 11-tap Gaussian window.
pub fn window() -> [f64; WINDOW] {
    let half = (WINDOW / 2) as f64;
    let mut f = [0.0; WINDOW];
    for (i, v) in f.iter_mut().enumerate() {
        let t = (i as f64 - half) / SIGMA;
        *v = (-0.5 * t * t).exp();
    }
    let s: f64 = f.iter().sum();
    f.map(|v| v / s)
}

/// SSIM of `a` against `b` (`[H, W, 3]`, values in [0, 1]); with `mask` `[H, W]` it is
/// DyCheck's mSSIM. Images need at least 11x11 pixels.
pub fn ssim(a: &Image, b: &Image, mask: Option<&[f32]>) -> Result<f64> {
    check_pair("ssim", a, b, mask)?;
    let (w, h) = (a.width, a.height);
    if w < WINDOW || h < WINDOW {
        return Err(Error::TooSmall { what: "ssim", w, h, min: WINDOW });
    }
    let blur = Blur::new(w, h, mask);
    // Channels in parallel, summed in channel order (deterministic).
    let sums: Vec<f64> = (0..3).into_par_iter().map(|c| blur.channel_sum(a, b, c)).collect();
    let total: f64 = sums.iter().sum();
    Ok(total / (3 * (w - WINDOW + 1) * (h - WINDOW + 1)) as f64)
}

/// Outputs computed together by [`filter`] (in registers).
const BLOCK: usize = 8;

/// `out[x] = Σ_k f[k]·src[k][x]` for every `x` of `out`, summing the taps in order from 0
/// (one weight per source row, the window's 11 or, at a border, fewer); blocks of
/// [`BLOCK`] outputs are accumulated in registers. Also the training SSIM's blur
/// ([`super::ssim_grad`]).
pub(super) fn filter(f: &[f64], src: &[&[f64]], out: &mut [f64]) {
    debug_assert_eq!(f.len(), src.len(), "one weight per source row");
    let mut blocks = out.chunks_exact_mut(BLOCK);
    let mut x = 0;
    for o in &mut blocks {
        let mut acc = [0.0f64; BLOCK];
        for (f, s) in f.iter().zip(src) {
            for (a, v) in acc.iter_mut().zip(&s[x..x + BLOCK]) {
                *a += f * v;
            }
        }
        o.copy_from_slice(&acc);
        x += BLOCK;
    }
    for (i, o) in blocks.into_remainder().iter_mut().enumerate() {
        *o = f.iter().zip(src).fold(0.0, |a, (f, s)| a + f * s[x + i]);
    }
}

/// The SSIM map value of one pixel from its five blurred statistics
/// `[μ0, μ1, E(a²), E(b²), E(ab)]`, with DyCheck's clipping of the (co)variances.
fn ssim_value(s: [f64; 5]) -> f64 {
    let (c1, c2) = (K1 * K1, K2 * K2);
    let [m0, m1, e00, e11, e01] = s;
    let s00 = (e00 - m0 * m0).max(0.0);
    let s11 = (e11 - m1 * m1).max(0.0);
    let s01 = e01 - m0 * m1;
    // sign(σ01)·min(√(σ00σ11), |σ01|), branch-free (0 stays 0).
    let s01 = (s00 * s11).sqrt().min(s01.abs()).copysign(s01);
    let numer = (2.0 * m0 * m1 + c1) * (2.0 * s01 + c2);
    let denom = (m0 * m0 + m1 * m1 + c1) * (s00 + s11 + c2);
    numer / denom
}

/// The two-pass partial convolution of one image size and mask, with the mask sums of
/// both passes precomputed (`None` without a mask: every factor is then exactly 1 and the
/// multiplications are skipped, which changes no bit of the result).
struct Blur {
    w: usize,
    h: usize,
    f: [f64; WINDOW],
    masks: Option<Masks>,
}

/// The mask and the per-pass factors of a masked [`Blur`].
struct Masks {
    /// `[H, W]` pixel mask of the first pass.
    mask: Vec<f64>,
    /// `[H, W − 10]` first-pass factor `11 / m'` (0 where `m' = 0`).
    scale1: Vec<f64>,
    /// `[H − 10, W − 10]` second-pass factor `11 / m''` (0 where `m'' = 0`).
    scale2: Vec<f64>,
}

/// The five signals blurred for SSIM: `a`, `b`, `a²`, `b²`, `a·b`.
const SIGNALS: usize = 5;

impl Blur {
    fn new(w: usize, h: usize, mask: Option<&[f32]>) -> Blur {
        let masks = mask.map(|m| {
            let mask: Vec<f64> = m.iter().map(|v| *v as f64).collect();
            let (w1, h1) = (w - WINDOW + 1, h - WINDOW + 1);
            let n = WINDOW as f64;
            let factor = |s: f64| if s != 0.0 { n / s } else { 0.0 };
            let mut scale1 = vec![0.0; h * w1];
            for y in 0..h {
                for x in 0..w1 {
                    let s: f64 = mask[y * w + x..y * w + x + WINDOW].iter().sum();
                    scale1[y * w1 + x] = factor(s);
                }
            }
            let mut scale2 = vec![0.0; h1 * w1];
            for y in 0..h1 {
                for x in 0..w1 {
                    let s: f64 =
                        (0..WINDOW).map(|k| (scale1[(y + k) * w1 + x] != 0.0) as u8 as f64).sum();
                    scale2[y * w1 + x] = factor(s);
                }
            }
            Masks { mask, scale1, scale2 }
        });
        Blur { w, h, f: window(), masks }
    }

    /// The sum of the SSIM map of channel `c` of `a` against `b`, streamed row by row: the
    /// horizontal pass of the five signals fills a ring of 11 rows `[11, 5, W − 10]` from
    /// which each output row's vertical pass is taken. Every output sums its taps in order
    /// k = 0..10 and the map is summed in row-major order.
    fn channel_sum(&self, a: &Image, b: &Image, c: usize) -> f64 {
        let (w, h) = (self.w, self.h);
        let w1 = w - WINDOW + 1;
        let mut input = vec![0.0f64; SIGNALS * w];
        let mut ring = vec![0.0f64; WINDOW * SIGNALS * w1];
        let mut out = vec![0.0f64; SIGNALS * w1];
        let mut map = vec![0.0f64; w1];
        let mut total = 0.0f64;
        for y in 0..h {
            // The five input rows `[5, W]`, masked.
            let (ra, rb) =
                (&a.data[y * w * 3..(y + 1) * w * 3], &b.data[y * w * 3..(y + 1) * w * 3]);
            let (sx, rest) = input.split_at_mut(w);
            let (sy, rest) = rest.split_at_mut(w);
            let (sxx, rest) = rest.split_at_mut(w);
            let (syy, sxy) = rest.split_at_mut(w);
            for x in 0..w {
                let (p, q) = (ra[3 * x + c] as f64, rb[3 * x + c] as f64);
                (sx[x], sy[x], sxx[x], syy[x], sxy[x]) = (p, q, p * p, q * q, p * q);
            }
            if let Some(m) = &self.masks {
                let mrow = &m.mask[y * w..(y + 1) * w];
                for row in input.chunks_exact_mut(w) {
                    for (v, m) in row.iter_mut().zip(mrow) {
                        *v *= m;
                    }
                }
            }
            // Horizontal pass into the ring slot of row y.
            let slot = &mut ring[(y % WINDOW) * SIGNALS * w1..(y % WINDOW + 1) * SIGNALS * w1];
            for (acc, row) in slot.chunks_exact_mut(w1).zip(input.chunks_exact(w)) {
                filter(&self.f, &std::array::from_fn::<_, WINDOW, _>(|k| &row[k..k + w1]), acc);
                if let Some(m) = &self.masks {
                    for (a, s) in acc.iter_mut().zip(&m.scale1[y * w1..(y + 1) * w1]) {
                        *a *= s;
                    }
                }
            }
            if y + 1 < WINDOW {
                continue;
            }
            // Vertical pass of output row oy = y − 10 over ring rows oy..=y.
            let oy = y + 1 - WINDOW;
            for (s, acc) in out.chunks_exact_mut(w1).enumerate() {
                let src: [&[f64]; WINDOW] = std::array::from_fn(|k| {
                    let r = (oy + k) % WINDOW;
                    &ring[(r * SIGNALS + s) * w1..(r * SIGNALS + s + 1) * w1]
                });
                filter(&self.f, &src, acc);
                if let Some(m) = &self.masks {
                    for (a, s) in acc.iter_mut().zip(&m.scale2[oy * w1..(oy + 1) * w1]) {
                        *a *= s;
                    }
                }
            }
            for x in 0..w1 {
                map[x] = ssim_value([
                    out[x],
                    out[w1 + x],
                    out[2 * w1 + x],
                    out[3 * w1 + x],
                    out[4 * w1 + x],
                ]);
            }
            for v in &map {
                total += v;
            }
        }
        total
    }
}

/// SSIM map `[H, W, 3]` of two `[H, W, 3]` images: 11×11 Gaussian window, σ = 1.5, zero
/// ('same') padding, C1 = 0.01², C2 = 0.03². Rayon over channels and image rows; every
/// output value is computed by one fixed sequence of operations (thread-count independent).
pub fn ssim_map(a: &[f32], b: &[f32], w: usize, h: usize) -> Vec<f32> {
    use rayon::prelude::*;
    if w == 0 || h == 0 {
        return Vec::new();
    }
    let g: Vec<f32> = {
        let k: Vec<f32> =
            (0..11).map(|i| (-((i as f32 - 5.0).powi(2)) / (2.0 * 1.5 * 1.5)).exp()).collect();
        let s: f32 = k.iter().sum();
        k.iter().map(|v| v / s).collect()
    };
    let blur = |x: &[f32]| -> Vec<f32> {
        let mut tmp = vec![0.0; w * h];
        tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (xx, o) in row.iter_mut().enumerate() {
                *o = (0..11)
                    .filter_map(|k| {
                        (xx + k).checked_sub(5).filter(|&c| c < w).map(|c| g[k] * x[y * w + c])
                    })
                    .sum();
            }
        });
        let mut out = vec![0.0; w * h];
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (xx, o) in row.iter_mut().enumerate() {
                *o = (0..11)
                    .filter_map(|k| {
                        (y + k).checked_sub(5).filter(|&r| r < h).map(|r| g[k] * tmp[r * w + xx])
                    })
                    .sum();
            }
        });
        out
    };
    let (c1, c2) = (0.01f32 * 0.01, 0.03f32 * 0.03);
    let channels: Vec<Vec<f32>> = (0..3)
        .into_par_iter()
        .map(|c| {
            let x: Vec<f32> = (0..w * h).map(|i| a[i * 3 + c]).collect();
            let y: Vec<f32> = (0..w * h).map(|i| b[i * 3 + c]).collect();
            let xx: Vec<f32> = x.iter().map(|v| v * v).collect();
            let yy: Vec<f32> = y.iter().map(|v| v * v).collect();
            let xy: Vec<f32> = x.iter().zip(&y).map(|(p, q)| p * q).collect();
            let (mx, my, sxx, syy, sxy) = (blur(&x), blur(&y), blur(&xx), blur(&yy), blur(&xy));
            (0..w * h)
                .map(|i| {
                    let (vx, vy, cv) =
                        (sxx[i] - mx[i] * mx[i], syy[i] - my[i] * my[i], sxy[i] - mx[i] * my[i]);
                    ((2.0 * mx[i] * my[i] + c1) * (2.0 * cv + c2))
                        / ((mx[i] * mx[i] + my[i] * my[i] + c1) * (vx + vy + c2))
                })
                .collect()
        })
        .collect();
    let mut out = vec![0.0; w * h * 3];
    for (c, m) in channels.iter().enumerate() {
        for (i, v) in m.iter().enumerate() {
            out[i * 3 + c] = *v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random image (splitmix64).
    fn noise(w: usize, h: usize, seed: u64) -> Image {
        let mut rng = crate::util::rng::Rng::from_state(seed);
        let data = (0..w * h * 3).map(|_| rng.uniform_f32()).collect();
        Image { width: w, height: h, channels: 3, data }
    }

    /// Direct 2-D windowed SSIM (valid mode, no mask), written independently.
    fn naive_ssim(a: &Image, b: &Image) -> f64 {
        let f = window();
        let (w, h) = (a.width, a.height);
        let mut total = 0.0;
        let mut count = 0;
        for c in 0..3 {
            for y in 0..=h - WINDOW {
                for x in 0..=w - WINDOW {
                    let (mut m0, mut m1, mut e00, mut e11, mut e01) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for i in 0..WINDOW {
                        for j in 0..WINDOW {
                            let wgt = f[i] * f[j];
                            let p = a.at(x + j, y + i, c) as f64;
                            let q = b.at(x + j, y + i, c) as f64;
                            m0 += wgt * p;
                            m1 += wgt * q;
                            e00 += wgt * p * p;
                            e11 += wgt * q * q;
                            e01 += wgt * p * q;
                        }
                    }
                    let (s00, s11, s01) = (e00 - m0 * m0, e11 - m1 * m1, e01 - m0 * m1);
                    let (c1, c2) = (K1 * K1, K2 * K2);
                    total += (2.0 * m0 * m1 + c1) * (2.0 * s01 + c2)
                        / ((m0 * m0 + m1 * m1 + c1) * (s00 + s11 + c2));
                    count += 1;
                }
            }
        }
        total / count as f64
    }

    /// DyCheck's masked SSIM written directly from its definition on whole arrays:
    /// `blur(z, m)` per pass as `where(m' ≠ 0, conv(z·m, f)·11 / m', 0)`.
    fn naive_masked_ssim(a: &Image, b: &Image, mask: &[f32]) -> f64 {
        let f = window();
        let (w, h) = (a.width, a.height);
        let (w1, h1) = (w - WINDOW + 1, h - WINDOW + 1);
        // One pass along x (`dx = 1`) or y over `[rows, cols]` arrays.
        let pass = |z: &[f64], m: &[f64], cols: usize, horizontal: bool| -> (Vec<f64>, Vec<f64>) {
            let rows = z.len() / cols;
            let (orows, ocols) = if horizontal { (rows, cols - 10) } else { (rows - 10, cols) };
            let (mut out, mut valid) = (vec![0.0; orows * ocols], vec![0.0; orows * ocols]);
            for r in 0..orows {
                for q in 0..ocols {
                    let at =
                        |k: usize| if horizontal { r * cols + q + k } else { (r + k) * cols + q };
                    let conv: f64 = (0..WINDOW).map(|k| f[k] * z[at(k)] * m[at(k)]).sum();
                    let msum: f64 = (0..WINDOW).map(|k| m[at(k)]).sum();
                    if msum != 0.0 {
                        out[r * ocols + q] = conv * WINDOW as f64 / msum;
                        valid[r * ocols + q] = 1.0;
                    }
                }
            }
            (out, valid)
        };
        let m: Vec<f64> = mask.iter().map(|v| *v as f64).collect();
        let blur = |z: Vec<f64>| -> Vec<f64> {
            let (p1, v1) = pass(&z, &m, w, true);
            pass(&p1, &v1, w1, false).0
        };
        let mut total = 0.0;
        for c in 0..3 {
            let x: Vec<f64> = (0..w * h).map(|i| a.data[3 * i + c] as f64).collect();
            let y: Vec<f64> = (0..w * h).map(|i| b.data[3 * i + c] as f64).collect();
            let prod = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(p, q)| p * q).collect();
            let stats = [
                blur(x.clone()),
                blur(y.clone()),
                blur(prod(&x, &x)),
                blur(prod(&y, &y)),
                blur(prod(&x, &y)),
            ];
            for i in 0..w1 * h1 {
                total += ssim_value(stats.clone().map(|s| s[i]));
            }
        }
        total / (3 * w1 * h1) as f64
    }

    #[test]
    fn masked_matches_a_naive_direct_implementation() {
        let (w, h) = (23, 17);
        let a = noise(w, h, 9);
        let mut b = noise(w, h, 10);
        for (q, p) in b.data.iter_mut().zip(&a.data) {
            *q = 0.7 * *p + 0.3 * *q;
        }
        // A soft mask with an empty region wider than the window.
        let mask: Vec<f32> = (0..w * h)
            .map(|i| match (i % w, i / w) {
                (x, _) if x < 12 => 0.0,
                (x, y) => ((x * 3 + y * 5) % 7) as f32 / 6.0,
            })
            .collect();
        let got = ssim(&a, &b, Some(&mask)).unwrap();
        let want = naive_masked_ssim(&a, &b, &mask);
        assert!((got - want).abs() < 1e-9, "{got} vs {want}");
        assert!(got > 0.1 && got < 0.999, "{got}");
    }

    #[test]
    fn window_is_normalised_and_symmetric() {
        let f = window();
        assert!((f.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert_eq!(f[0], f[10]);
        assert!((f[5] - 0.266_011_2).abs() < 1e-6, "centre tap {}", f[5]);
    }

    #[test]
    fn identical_images_give_one() {
        let a = noise(16, 13, 1);
        assert!((ssim(&a, &a, None).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn matches_a_naive_direct_implementation() {
        let a = noise(19, 14, 2);
        let mut b = noise(19, 14, 3);
        // Correlate b with a so that the covariance term matters.
        for (q, p) in b.data.iter_mut().zip(&a.data) {
            *q = 0.6 * *p + 0.4 * *q;
        }
        let got = ssim(&a, &b, None).unwrap();
        let want = naive_ssim(&a, &b);
        assert!((got - want).abs() < 1e-9, "{got} vs {want}");
        assert!(got > 0.1 && got < 0.99, "{got}");
    }

    #[test]
    fn full_mask_equals_unmasked_and_zero_mask_gives_one() {
        let a = noise(15, 12, 4);
        let b = noise(15, 12, 5);
        let ones = vec![1.0; 15 * 12];
        let (m, u) = (ssim(&a, &b, Some(&ones)).unwrap(), ssim(&a, &b, None).unwrap());
        assert!((m - u).abs() < 1e-12, "{m} vs {u}");
        let zeros = vec![0.0; 15 * 12];
        assert_eq!(ssim(&a, &b, Some(&zeros)).unwrap(), 1.0);
    }

    #[test]
    fn masked_pixels_do_not_matter() {
        // Changing b where the mask is 0 leaves mSSIM unchanged.
        let (w, h) = (14, 14);
        let a = noise(w, h, 6);
        let b = noise(w, h, 7);
        let mask: Vec<f32> = (0..w * h).map(|i| if i % w < 7 { 1.0 } else { 0.0 }).collect();
        let mut b2 = b.clone();
        for i in 0..w * h {
            if mask[i] == 0.0 {
                b2.data[3 * i] = 1.0 - b2.data[3 * i];
            }
        }
        let s1 = ssim(&a, &b, Some(&mask)).unwrap();
        let s2 = ssim(&a, &b2, Some(&mask)).unwrap();
        assert_eq!(s1, s2);
        assert!(s1 < 1.0);
    }

    #[test]
    fn too_small_is_an_error() {
        let a = noise(10, 20, 8);
        let e = ssim(&a, &a, None).unwrap_err().to_string();
        assert_eq!(e, "ssim: image 10x20 is smaller than the metric's minimum 11x11");
    }
}
