//! SSIM as a training loss, with its exact backward (the photometric term L_rgb of the base
//! models, paper Appendix A.3): the 11-tap Gaussian window of [`super::ssim`] (σ 1.5),
//! c1 = 0.01², c2 = 0.03², no clipping of the (co)variances, the mean over the map and the
//! channels. Training needs no mask here: MoSca masks by multiplying both images first, which
//! the caller does (and chains).
//!
//! Borders ([`SsimPadding`]): `Same` zero-pads the image by 5 pixels, so the map is H×W
//! (3DGS's and MoSca's `ssim`, the release's L_rgb); `Valid` keeps only windows inside the
//! image, an (H − 10)×(W − 10) map (Shape of Motion's `pytorch_msssim.SSIM`; equal to the
//! unmasked metric [`super::ssim::ssim`]).
//!
//! Backward. Per map pixel q the statistics are Gaussian blurs μx, μy, E[x²], E[y²], E[xy];
//! with σxx = E[x²] − μx² (likewise σyy, σxy) the map is
//! `s = (2μxμy + c1)(2σxy + c2) / ((μx² + μy² + c1)(σxx + σyy + c2))` and S = mean_q s. Then
//! `dS/dx_p = Σ_q g(p − q)·[A(q) + 2x_p·B(q) + y_p·C(q)] / |map|` with B = ∂s/∂σxx,
//! C = ∂s/∂σxy, A = ∂s/∂μx − 2μx·B − μy·C (zero off the map): three more blurs with the same
//! (symmetric) window. Each blur is separable, O(H·W·11); a channel costs 8 blurs and 14
//! `[H, W]` f64 planes, nothing quadratic, and the planes are kept per thread between calls.
//!
//! Threading: every pass runs rayon over rows; each value is computed by one task with its
//! taps summed in a fixed order and row sums are added in row order, so the results are
//! bit-identical whatever the thread count.

use rayon::prelude::*;

use super::ssim::{K1, K2, WINDOW, filter, window};
use super::{Error, Result};

/// Half the window width (5): the zero padding of [`SsimPadding::Same`].
const HALF: usize = WINDOW / 2;

/// Which windows make up the SSIM map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SsimPadding {
    /// One window per pixel, zero outside the image: an H×W map (3DGS, MoSca, the release).
    #[default]
    Same,
    /// Only windows inside the image: an (H − 10)×(W − 10) map (Shape of Motion).
    Valid,
}

/// Mean SSIM of `x` against the fixed reference `y`, both `[H, W, C]` interleaved with
/// values in [0, 1]. With `grad = Some((g, scale))` it adds `scale · dSSIM/dx` to `g`
/// (`[H, W, C]`). `Valid` needs at least 11×11 pixels.
pub fn ssim_with_grad(
    x: &[f32],
    y: &[f32],
    w: usize,
    h: usize,
    channels: usize,
    padding: SsimPadding,
    grad: Option<(&mut [f32], f64)>,
) -> Result<f64> {
    let n = w * h * channels;
    if x.len() != n || y.len() != n {
        return Err(Error::Size {
            what: "training ssim",
            a: format!("{} values", x.len()),
            b: format!("{} values ({w}x{h}x{channels} expected)", y.len()),
        });
    }
    let map = map_size(w, h, padding).ok_or(Error::TooSmall {
        what: "training ssim (valid)",
        w,
        h,
        min: WINDOW,
    })?;
    let f = window();
    let want = grad.is_some();
    let norm = 1.0 / (map * channels) as f64;
    let mut out = grad;
    if let Some((g, _)) = &out {
        assert_eq!(g.len(), n, "gradient buffer is [H, W, C]");
    }
    let mut planes = PLANES.take();
    let mut total = 0.0;
    for c in 0..channels {
        let fill = |plane: &mut Vec<f64>, img: &[f32]| {
            plane.resize(w * h, 0.0);
            plane.par_chunks_mut(w).zip(img.par_chunks(w * channels)).for_each(|(o, row)| {
                for (o, p) in o.iter_mut().zip(row.chunks_exact(channels)) {
                    *o = p[c] as f64;
                }
            });
        };
        fill(&mut planes.x, x);
        fill(&mut planes.y, y);
        total += channel(&mut planes, w, h, padding, &f, want);
        if let Some((out, scale)) = out.as_mut() {
            let k = *scale * norm;
            out.par_chunks_mut(w * channels).zip(planes.grad.par_chunks(w)).for_each(|(o, g)| {
                for (px, v) in o.chunks_exact_mut(channels).zip(g) {
                    px[c] += (k * v) as f32;
                }
            });
        }
    }
    PLANES.set(planes);
    Ok(total * norm)
}

/// Number of map pixels, or `None` when a `Valid` map would be empty.
fn map_size(w: usize, h: usize, padding: SsimPadding) -> Option<usize> {
    match padding {
        SsimPadding::Same => Some(w * h),
        SsimPadding::Valid if w >= WINDOW && h >= WINDOW => {
            Some((w - WINDOW + 1) * (h - WINDOW + 1))
        }
        SsimPadding::Valid => None,
    }
}

/// The map's column range in every map row, and whether image row `y` is a map row.
fn map_cols(w: usize, padding: SsimPadding) -> std::ops::Range<usize> {
    match padding {
        SsimPadding::Same => 0..w,
        SsimPadding::Valid => HALF..w - HALF,
    }
}

fn is_map_row(y: usize, h: usize, padding: SsimPadding) -> bool {
    padding == SsimPadding::Same || (HALF..h - HALF).contains(&y)
}

/// The `[H, W]` planes of [`channel`], kept per thread between calls of
/// [`ssim_with_grad`]: a training step takes the SSIM of several frames of one size, and
/// allocating these planes (about 14 per channel) afresh each time made glibc map and unmap
/// whole heaps, page faults that cost more system time than the blurs. A call that finds
/// them taken (rayon may start another on the same thread while one waits) allocates its
/// own.
#[derive(Debug, Default)]
struct Planes {
    /// The channel of the rendered image and of the reference.
    x: Vec<f64>,
    y: Vec<f64>,
    /// The horizontal pass of the five signals, `[H, 5, W]`.
    hor: Vec<f64>,
    /// A, B and C, `[H, 3, W]`, and their horizontal pass.
    coef: Vec<f64>,
    hor3: Vec<f64>,
    /// The gradient of the map's sum w.r.t. `x`.
    grad: Vec<f64>,
}

thread_local! {
    static PLANES: std::cell::Cell<Planes> = std::cell::Cell::new(Planes::default());
}

/// One channel, planes `p.x` and `p.y` (`[H, W]`): the sum of its SSIM map and, when
/// `want_grad`, the gradient of that sum w.r.t. `x` in `p.grad` (`[H, W]`).
///
/// Forward: a horizontal pass of the five signals into row-interleaved planes `[H, 5, W]`,
/// then per map row one vertical pass over the whole `[5, W]` block, the map values and
/// the coefficients A, B, C (`[H, 3, W]`, 0 off the map). Backward: the same two passes
/// over `[H, 3, W]`, the vertical one fused with `A + 2x·B + y·C`.
fn channel(
    p: &mut Planes,
    w: usize,
    h: usize,
    padding: SsimPadding,
    f: &[f64; WINDOW],
    want_grad: bool,
) -> f64 {
    const S: usize = 5;
    let Planes { x, y, hor, coef, hor3, grad } = p;
    let (x, y) = (&x[..], &y[..]);
    hor.resize(S * w * h, 0.0);
    hor.par_chunks_mut(S * w).enumerate().for_each_init(
        || vec![0.0; w + 2 * HALF],
        |padded, (yy, out)| {
            let (xr, yr) = (&x[yy * w..(yy + 1) * w], &y[yy * w..(yy + 1) * w]);
            let signals: [(&[f64], Option<&[f64]>); S] =
                [(xr, None), (yr, None), (xr, Some(xr)), (yr, Some(yr)), (xr, Some(yr))];
            for (o, (a, b)) in out.chunks_exact_mut(w).zip(signals) {
                let inner = &mut padded[HALF..HALF + w];
                match b {
                    None => inner.copy_from_slice(a),
                    Some(b) => inner.iter_mut().zip(a).zip(b).for_each(|((p, a), b)| *p = a * b),
                }
                blur_row(padded, o, f);
            }
        },
    );
    let hor = &hor[..];
    let cols = map_cols(w, padding);
    // Per row: the map's sum, and A, B, C into `coef` rows `[3, W]` (0 off the map).
    coef.resize(if want_grad { 3 * w * h } else { 0 }, 0.0);
    let per_row = |v: &mut Vec<f64>, (yy, out): (usize, &mut [f64])| -> f64 {
        out.fill(0.0);
        if !is_map_row(yy, h, padding) {
            return 0.0;
        }
        blur_column(hor, S * w, h, yy, f, v);
        let mut sum = 0.0;
        for xx in cols.clone() {
            let (s, abc) = ssim_terms(std::array::from_fn(|k| v[k * w + xx]));
            sum += s;
            if !out.is_empty() {
                for (k, c) in abc.into_iter().enumerate() {
                    out[k * w + xx] = c;
                }
            }
        }
        sum
    };
    let scratch = || vec![0.0; S * w];
    let row_sums: Vec<f64> = if want_grad {
        coef.par_chunks_mut(3 * w).enumerate().map_init(scratch, per_row).collect()
    } else {
        (0..h).into_par_iter().map_init(scratch, |v, yy| per_row(v, (yy, &mut []))).collect()
    };
    let total = row_sums.iter().sum();
    if !want_grad {
        return total;
    }
    hor3.resize(3 * w * h, 0.0);
    hor3.par_chunks_mut(3 * w).zip(coef.par_chunks(3 * w)).for_each_init(
        || vec![0.0; w + 2 * HALF],
        |padded, (o, c)| {
            for (o, c) in o.chunks_exact_mut(w).zip(c.chunks_exact(w)) {
                padded[HALF..HALF + w].copy_from_slice(c);
                blur_row(padded, o, f);
            }
        },
    );
    let hor3 = &hor3[..];
    grad.resize(w * h, 0.0);
    grad.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0.0; 3 * w],
        |v, (yy, g)| {
            blur_column(hor3, 3 * w, h, yy, f, v);
            let (xr, yr) = (&x[yy * w..(yy + 1) * w], &y[yy * w..(yy + 1) * w]);
            for i in 0..w {
                g[i] = v[i] + 2.0 * xr[i] * v[w + i] + yr[i] * v[2 * w + i];
            }
        },
    );
    total
}

/// The SSIM map value of one pixel from `[μx, μy, E(x²), E(y²), E(xy)]`, and its
/// coefficients `[A, B, C]` (module doc), written without dividing by the numerator
/// factors so that a zero numerator is harmless.
fn ssim_terms(s: [f64; 5]) -> (f64, [f64; 3]) {
    let (c1, c2) = (K1 * K1, K2 * K2);
    let [mx, my, exx, eyy, exy] = s;
    let sxx = exx - mx * mx;
    let syy = eyy - my * my;
    let sxy = exy - mx * my;
    let (n1, n2) = (2.0 * mx * my + c1, 2.0 * sxy + c2);
    let (d1, d2) = (mx * mx + my * my + c1, sxx + syy + c2);
    // One division: 1/d1 = d2·inv and 1/d2 = d1·inv.
    let inv = 1.0 / (d1 * d2);
    let v = n1 * n2 * inv;
    let b = -v * d1 * inv;
    let c = 2.0 * n1 * inv;
    let ds_dmx = 2.0 * (my * n2 - mx * v * d2) * inv;
    (v, [ds_dmx - 2.0 * mx * b - my * c, b, c])
}

/// Horizontal pass of one row held in `padded` between 5 zeros on either side:
/// `o[x] = Σ_k f[k]·s[x + k − 5]` with zeros outside, taps added in order k = 0..10 to 0. A
/// tap on a padding zero leaves the sum's bits unchanged (the sum starts at +0, so it is
/// never −0), so this equals the fold that leaves the taps outside the row out.
fn blur_row(padded: &[f64], o: &mut [f64], f: &[f64; WINDOW]) {
    let w = o.len();
    filter(f, &std::array::from_fn::<_, WINDOW, _>(|k| &padded[k..k + w]), o);
}

/// Vertical pass at row `yy` of planes stored as rows of `len` values (`[H, len]`) with
/// zeros outside: `out = Σ_k f[k]·rows[yy + k − 5]` over the taps k whose row is inside,
/// added in order to 0.
fn blur_column(rows: &[f64], len: usize, h: usize, yy: usize, f: &[f64; WINDOW], out: &mut [f64]) {
    // taps k with 0 ≤ yy + k − 5 < h
    let (lo, hi) = (HALF.saturating_sub(yy), (h + HALF - yy).min(WINDOW));
    let src: [&[f64]; WINDOW] = std::array::from_fn(|k| {
        let r = yy + lo + k;
        if lo + k < hi { &rows[(r - HALF) * len..(r - HALF + 1) * len] } else { &[] }
    });
    filter(&f[lo..hi], &src[..hi - lo], out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::png::Image;
    use crate::util::rng::grid_noise as noise;

    /// Direct 2-D windowed SSIM with zero padding (`Same`) or valid windows, independent of
    /// the separable code.
    fn naive(x: &[f32], y: &[f32], w: usize, h: usize, ch: usize, padding: SsimPadding) -> f64 {
        let f = window();
        let at = |img: &[f32], xx: isize, yy: isize, c: usize| -> f64 {
            if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                0.0
            } else {
                img[(yy as usize * w + xx as usize) * ch + c] as f64
            }
        };
        let (mut total, mut count) = (0.0, 0usize);
        for c in 0..ch {
            for yy in 0..h {
                for xx in 0..w {
                    let inside = (HALF..h - HALF).contains(&yy) && (HALF..w - HALF).contains(&xx);
                    if padding == SsimPadding::Valid && !inside {
                        continue;
                    }
                    let mut m = [0.0f64; 5];
                    for i in 0..WINDOW {
                        for j in 0..WINDOW {
                            let (px, py) =
                                (xx as isize + j as isize - 5, yy as isize + i as isize - 5);
                            let (p, q) = (at(x, px, py, c), at(y, px, py, c));
                            let g = f[i] * f[j];
                            for (acc, v) in m.iter_mut().zip([p, q, p * p, q * q, p * q]) {
                                *acc += g * v;
                            }
                        }
                    }
                    total += ssim_terms(m).0;
                    count += 1;
                }
            }
        }
        total / count as f64
    }

    #[test]
    fn forward_matches_a_direct_implementation_and_the_metric() {
        let (w, h) = (17, 13);
        let x = noise(w * h * 3, 1);
        let mut y = noise(w * h * 3, 2);
        for (q, p) in y.iter_mut().zip(&x) {
            *q = 0.6 * *p + 0.4 * *q;
        }
        for padding in [SsimPadding::Same, SsimPadding::Valid] {
            let got = ssim_with_grad(&x, &y, w, h, 3, padding, None).unwrap();
            let want = naive(&x, &y, w, h, 3, padding);
            assert!((got - want).abs() < 1e-12, "{padding:?}: {got} vs {want}");
        }
        let img = |d: &[f32]| Image { width: w, height: h, channels: 3, data: d.to_vec() };
        let metric = crate::metrics::ssim::ssim(&img(&x), &img(&y), None).unwrap();
        let valid = ssim_with_grad(&x, &y, w, h, 3, SsimPadding::Valid, None).unwrap();
        assert!((metric - valid).abs() < 1e-12, "{metric} vs {valid}");
    }

    /// Central differences in f64 on the planar core (the forward is f64 throughout).
    #[test]
    fn gradient_matches_finite_differences() {
        let (w, h) = (14, 12);
        let f = window();
        let mut failures = Vec::new();
        let mut max_err = 0.0f64;
        for (seed, padding) in [(3, SsimPadding::Same), (5, SsimPadding::Valid)] {
            let x: Vec<f64> = noise(w * h, seed).iter().map(|v| *v as f64).collect();
            let y: Vec<f64> = noise(w * h, seed + 1)
                .iter()
                .zip(&x)
                .map(|(q, p)| 0.5 * p + 0.5 * *q as f64)
                .collect();
            let sum = |x: &[f64], want: bool| {
                let mut p = Planes { x: x.to_vec(), y: y.clone(), ..Planes::default() };
                (channel(&mut p, w, h, padding, &f, want), p.grad)
            };
            let g = sum(&x, true).1;
            let eps = 1e-5;
            // Every pixel: corners, borders and the interior.
            for i in 0..w * h {
                let mut xp = x.clone();
                xp[i] += eps;
                let mut xm = x.clone();
                xm[i] -= eps;
                let fd = (sum(&xp, false).0 - sum(&xm, false).0) / (2.0 * eps);
                let err = (fd - g[i]).abs();
                max_err = max_err.max(err);
                if err > 1e-7 + 1e-5 * fd.abs() {
                    failures.push(format!("{padding:?} pixel {i}: analytic {} fd {fd}", g[i]));
                }
            }
        }
        eprintln!("ssim_grad FD: max abs error {max_err:.3e}");
        assert!(failures.is_empty(), "{}", failures.join("\n"));
    }

    /// The public f32 entry point: scaled accumulation into `[H, W, C]`, checked by
    /// central differences on 1/1024 steps (exact in f32 for inputs on the 1/4096 grid).
    #[test]
    fn interleaved_gradient_is_scaled_and_accumulated() {
        let (w, h, ch) = (12, 11, 3);
        let x = noise(w * h * ch, 7);
        let y = noise(w * h * ch, 8);
        let mut g = vec![1.0f32; w * h * ch];
        ssim_with_grad(&x, &y, w, h, ch, SsimPadding::Same, Some((&mut g, -2.0))).unwrap();
        let eps = 1.0 / 1024.0;
        let mut failures = Vec::new();
        for i in (0..w * h * ch).step_by(7) {
            let mut xp = x.clone();
            xp[i] += eps;
            let mut xm = x.clone();
            xm[i] -= eps;
            let s = |v: &[f32]| ssim_with_grad(v, &y, w, h, ch, SsimPadding::Same, None).unwrap();
            let fd = -2.0 * (s(&xp) - s(&xm)) / (2.0 * eps as f64);
            let got = g[i] as f64 - 1.0;
            if (fd - got).abs() > 1e-6 + 1e-3 * fd.abs() {
                failures.push(format!("value {i}: analytic {got} fd {fd}"));
            }
        }
        assert!(failures.is_empty(), "{}", failures.join("\n"));
    }

    /// The blurs give the bits of the plain folds that leave the taps outside the image out
    /// (signed values, zeros of both signs, widths below and above the register group).
    #[test]
    fn blurs_equal_the_folds_without_the_outside_taps() {
        let f = window();
        for (w, h, seed) in [(3, 2, 1), (8, 5, 2), (21, 13, 3), (37, 4, 4)] {
            let mut s: Vec<f64> = noise(w * h, seed).iter().map(|v| *v as f64 - 0.5).collect();
            s[0] = -0.0;
            s[w * h - 1] = 0.0;
            for yy in 0..h {
                let row = &s[yy * w..(yy + 1) * w];
                let mut padded = vec![0.0; w + 2 * HALF];
                padded[HALF..HALF + w].copy_from_slice(row);
                let mut got = vec![f64::NAN; w];
                blur_row(&padded, &mut got, &f);
                let want: Vec<f64> = (0..w)
                    .map(|x| {
                        let taps = (0..WINDOW).filter(|k| (HALF..w + HALF).contains(&(x + k)));
                        taps.fold(0.0, |a, k| a + f[k] * row[x + k - HALF])
                    })
                    .collect();
                assert_eq!(bits(&got), bits(&want), "row {yy} of {w}x{h}");
                let mut got = vec![f64::NAN; w];
                blur_column(&s, w, h, yy, &f, &mut got);
                let want: Vec<f64> = (0..w)
                    .map(|x| {
                        let taps = (0..WINDOW).filter(|k| (HALF..h + HALF).contains(&(yy + k)));
                        taps.fold(0.0, |a, k| a + f[k] * s[(yy + k - HALF) * w + x])
                    })
                    .collect();
                assert_eq!(bits(&got), bits(&want), "column pass at row {yy} of {w}x{h}");
            }
        }
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    #[test]
    fn identical_images_give_one_and_zero_gradient() {
        let (w, h) = (13, 12);
        let x = noise(w * h * 3, 9);
        let mut g = vec![0.0f32; w * h * 3];
        let s = ssim_with_grad(&x, &x, w, h, 3, SsimPadding::Same, Some((&mut g, 1.0))).unwrap();
        assert!((s - 1.0).abs() < 1e-12, "{s}");
        assert!(g.iter().all(|v| v.abs() < 1e-9), "SSIM is maximal at x = y");
    }

    #[test]
    fn deterministic_across_thread_counts() {
        let (w, h) = (40, 31);
        let x = noise(w * h * 3, 11);
        let y = noise(w * h * 3, 12);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let mut g = vec![0.0f32; w * h * 3];
                let s = ssim_with_grad(&x, &y, w, h, 3, SsimPadding::Same, Some((&mut g, 1.0)))
                    .unwrap();
                (s.to_bits(), g.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            })
        };
        assert_eq!(run(1), run(4));
    }

    /// The planes kept between calls carry nothing over: after larger images on the same
    /// thread, a call gives the bits of the same call on a fresh thread.
    #[test]
    fn kept_planes_carry_nothing_over() {
        let run = |w: usize, h: usize, seed: u64, padding: SsimPadding| {
            let (x, y) = (noise(w * h * 3, seed), noise(w * h * 3, seed + 1));
            let mut g = vec![0.0f32; w * h * 3];
            let s = ssim_with_grad(&x, &y, w, h, 3, padding, Some((&mut g, 1.0))).unwrap();
            (s.to_bits(), g.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
        };
        let fresh = std::thread::spawn(move || run(23, 17, 5, SsimPadding::Valid)).join().unwrap();
        let reused = std::thread::spawn(move || {
            run(40, 31, 1, SsimPadding::Same);
            run(29, 19, 3, SsimPadding::Valid);
            run(23, 17, 5, SsimPadding::Valid)
        });
        assert_eq!(reused.join().unwrap(), fresh);
    }

    #[test]
    fn bad_sizes_are_errors() {
        let x = noise(10 * 10 * 3, 1);
        let e = ssim_with_grad(&x, &x, 10, 10, 3, SsimPadding::Valid, None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "training ssim (valid): image 10x10 is smaller than the metric's minimum 11x11"
        );
        assert!(ssim_with_grad(&x, &x[1..], 10, 10, 3, SsimPadding::Same, None).is_err());
        assert!(ssim_with_grad(&x, &x, 10, 10, 3, SsimPadding::Same, None).is_ok());
    }
}
