//! The LPIPS v0.1 network (`lpips/lpips.py`, formats-and-protocols.md §4.1) on the CPU:
//! scaling layer, AlexNet `features` up to relu5, channel-normalised squared differences,
//! 1x1 linear layers and the bilinear (align_corners=False) upsampling of the spatial map.
//!
//! Feature maps are `[h, w, C]` row-major. Every convolution runs in the Winograd domain
//! ([`super::winograd`]), which needs about a quarter of the multiplications: conv2 (5x5)
//! by F(3x3, 5x5), conv3-5 (3x3) by F(4x4, 3x3), and conv1 (11x11, stride 4) as the
//! equivalent 3x3 stride-1 convolution over the space-to-depth input (48 channels, the
//! kernel zero-padded to 12x12) by F(4x4, 3x3). The reference path, im2col + matrix
//! product, remains for other kernels and for the tests: for a fixed-size chunk of output
//! positions (rayon over chunks, so results do not depend on the thread count) the patch
//! matrix `[P, k·k·Cin]` (order ky, kx, ci) is multiplied by the weights `[k·k·Cin, Cout]`
//! (HWIO) with `ndarray`'s blocked GEMM (matrixmultiply).
//!
//! Feature maps and the large convolution buffers come from a process-wide pool of
//! recycled buffers ([`scratch`]): fresh multi-megabyte allocations are new pages that the
//! kernel faults in and clears on every call.

use ndarray::{ArrayView2, ArrayViewMut2, linalg::general_mat_mul};
use rayon::prelude::*;

use super::scratch;
use super::weights::{AlexWeights, ConvWeights};
use super::winograd::{self, WinogradConv};

/// `shift` of LPIPS's scaling layer (inputs in [−1, 1]).
pub const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
/// `scale` of LPIPS's scaling layer.
pub const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Strides and paddings of AlexNet's five convolutions.
const STRIDE_PAD: [(usize, usize); 5] = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)];
/// Output positions per GEMM chunk.
const CHUNK: usize = 512;
/// Smallest image side the network accepts (one position left after the second pooling).
pub const MIN_SIDE: usize = 31;

/// A feature map `[h, w, c]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// Height.
    pub h: usize,
    /// Width.
    pub w: usize,
    /// Channels.
    pub c: usize,
    /// `[h, w, c]` values.
    pub data: Vec<f32>,
}

/// One convolution ready for im2col (weights `[k·k·Cin, Cout]`, HWIO) and, where the
/// kernel (stride 1) or its space-to-depth form (stride s) has Winograd transforms, in the
/// Winograd domain.
struct Conv {
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    hwio: Vec<f32>,
    bias: Vec<f32>,
    /// The Winograd form: of the convolution itself (stride 1) or, for stride `s`, of the
    /// equivalent stride-1 convolution with kernel side `⌈k/s⌉` over the space-to-depth
    /// input `[⌈H/s⌉, ⌈W/s⌉, s·s·Cin]` (channel `(dy·s + dx)·Cin + ci`).
    winograd: Option<WinogradConv>,
}

impl Conv {
    fn new(w: &ConvWeights, stride: usize, pad: usize) -> Conv {
        let (cin, cout, k) = (w.cin, w.cout, w.k);
        let mut hwio = vec![0.0; w.weight.len()];
        for co in 0..cout {
            for ci in 0..cin {
                for ky in 0..k {
                    for kx in 0..k {
                        hwio[((ky * k + kx) * cin + ci) * cout + co] =
                            w.weight[((co * cin + ci) * k + ky) * k + kx];
                    }
                }
            }
        }
        let winograd = if stride == 1 {
            winograd::tile_for_kernel(k).map(|m| WinogradConv::new(&w.weight, cin, cout, k, pad, m))
        } else {
            // Kernel [Cout, s·s·Cin, k', k'] of the space-to-depth form: tap (a, b) of
            // channel (dy, dx, ci) is tap (a·s + dy, b·s + dx) of the original (0 beyond k).
            let (s, ks) = (stride, k.div_ceil(stride));
            winograd::tile_for_kernel(ks).map(|m| {
                let cs = s * s * cin;
                let mut ws = vec![0.0f32; cout * cs * ks * ks];
                for co in 0..cout {
                    for ci in 0..cin {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (a, dy, b, dx) = (ky / s, ky % s, kx / s, kx % s);
                                let c2 = (dy * s + dx) * cin + ci;
                                ws[((co * cs + c2) * ks + a) * ks + b] =
                                    w.weight[((co * cin + ci) * k + ky) * k + kx];
                            }
                        }
                    }
                }
                WinogradConv::new(&ws, cs, cout, ks, 0, m)
            })
        };
        Conv { cin, cout, k, stride, pad, hwio, bias: w.bias.clone(), winograd }
    }

    /// `relu(conv(x) + bias)`, by Winograd where it applies.
    fn forward_relu(&self, x: &Features) -> Features {
        assert_eq!(x.c, self.cin, "input channels");
        let Some(wg) = &self.winograd else { return self.forward_relu_im2col(x) };
        if self.stride == 1 {
            let (h, w, data) = wg.forward_relu(&x.data, x.h, x.w, &self.bias);
            return Features { h, w, c: self.cout, data };
        }
        // Space-to-depth of the zero-padded input, just large enough for the oh x ow
        // outputs of the stride-1 kernel of side ⌈k/s⌉.
        let (k, s, p, cin) = (self.k, self.stride, self.pad, self.cin);
        let oh = (x.h + 2 * p - k) / s + 1;
        let ow = (x.w + 2 * p - k) / s + 1;
        let ks = k.div_ceil(s);
        let (hs, ws, cs) = (oh + ks - 1, ow + ks - 1, s * s * cin);
        let mut d = scratch::take(hs * ws * cs);
        d.par_chunks_mut(ws * cs).enumerate().for_each(|(ys, row)| {
            for (xs, px) in row.chunks_exact_mut(cs).enumerate() {
                for (dy, dst) in px.chunks_exact_mut(s * cin).enumerate() {
                    let iy = (ys * s + dy) as isize - p as isize;
                    let ix = (xs * s) as isize - p as isize;
                    let dx0 = (-ix).clamp(0, s as isize) as usize;
                    let dx1 = (x.w as isize - ix).clamp(dx0 as isize, s as isize) as usize;
                    if iy < 0 || iy >= x.h as isize || dx0 == dx1 {
                        dst.fill(0.0);
                        continue;
                    }
                    let src = ((iy as usize * x.w) as isize + ix + dx0 as isize) as usize * cin;
                    dst[..dx0 * cin].fill(0.0);
                    dst[dx0 * cin..dx1 * cin]
                        .copy_from_slice(&x.data[src..src + (dx1 - dx0) * cin]);
                    dst[dx1 * cin..].fill(0.0);
                }
            }
        });
        let (h, w, data) = wg.forward_relu(&d, hs, ws, &self.bias);
        scratch::give(d);
        debug_assert_eq!((h, w), (oh, ow));
        Features { h, w, c: self.cout, data }
    }

    /// `relu(conv(x) + bias)` by im2col and GEMM.
    fn forward_relu_im2col(&self, x: &Features) -> Features {
        assert_eq!(x.c, self.cin, "input channels");
        let (k, s, p) = (self.k, self.stride, self.pad);
        let oh = (x.h + 2 * p - k) / s + 1;
        let ow = (x.w + 2 * p - k) / s + 1;
        let kk = k * k * self.cin;
        let cout = self.cout;
        let weights =
            ArrayView2::from_shape((kk, cout), &self.hwio).expect("weights are [k·k·Cin, Cout]");
        let mut out = scratch::take(oh * ow * cout);
        out.par_chunks_mut(CHUNK * cout).enumerate().for_each(|(chunk, out)| {
            let p0 = chunk * CHUNK;
            let np = out.len() / cout;
            let mut col = scratch::take(np * kk);
            let cin = self.cin;
            for (r, patch) in col.chunks_exact_mut(kk).enumerate() {
                let (oy, ox) = ((p0 + r) / ow, (p0 + r) % ow);
                // Input columns ox·s − p .. +k, clipped to the image: kx in kx0..kx1.
                let ix = (ox * s) as isize - p as isize;
                let kx0 = (-ix).clamp(0, k as isize) as usize;
                let kx1 = (x.w as isize - ix).clamp(kx0 as isize, k as isize) as usize;
                for (ky, dst) in patch.chunks_exact_mut(k * cin).enumerate() {
                    let iy = (oy * s + ky) as isize - p as isize;
                    if iy < 0 || iy >= x.h as isize || kx0 == kx1 {
                        dst.fill(0.0);
                        continue;
                    }
                    let src = (iy as usize * x.w) as isize + ix;
                    let src = (src + kx0 as isize) as usize * cin;
                    dst[..kx0 * cin].fill(0.0);
                    dst[kx0 * cin..kx1 * cin]
                        .copy_from_slice(&x.data[src..src + (kx1 - kx0) * cin]);
                    dst[kx1 * cin..].fill(0.0);
                }
            }
            for row in out.chunks_exact_mut(cout) {
                row.copy_from_slice(&self.bias);
            }
            let a = ArrayView2::from_shape((np, kk), &col).expect("patches are [P, k·k·Cin]");
            let mut c =
                ArrayViewMut2::from_shape((np, cout), &mut *out).expect("output is [P, Cout]");
            general_mat_mul(1.0, &a, &weights, 1.0, &mut c);
            for v in out.iter_mut() {
                *v = v.max(0.0);
            }
            scratch::give(col);
        });
        Features { h: oh, w: ow, c: cout, data: out }
    }
}

/// 3x3 max pooling with stride 2, no padding (floor mode).
fn max_pool(x: &Features) -> Features {
    let oh = (x.h - 3) / 2 + 1;
    let ow = (x.w - 3) / 2 + 1;
    let mut out = scratch::take(oh * ow * x.c);
    out.fill(f32::NEG_INFINITY);
    for oy in 0..oh {
        for ox in 0..ow {
            let dst = &mut out[(oy * ow + ox) * x.c..(oy * ow + ox + 1) * x.c];
            for ky in 0..3 {
                for kx in 0..3 {
                    let src = ((oy * 2 + ky) * x.w + ox * 2 + kx) * x.c;
                    for (d, v) in dst.iter_mut().zip(&x.data[src..src + x.c]) {
                        *d = d.max(*v);
                    }
                }
            }
        }
    }
    Features { h: oh, w: ow, c: x.c, data: out }
}

/// The LPIPS v0.1 AlexNet network, ready to run.
pub struct Network {
    convs: Vec<Conv>,
    lins: Vec<Vec<f32>>,
}

impl Network {
    /// Build the network from loaded weights.
    pub fn new(w: &AlexWeights) -> Network {
        let convs = w.convs.iter().zip(STRIDE_PAD).map(|(c, (s, p))| Conv::new(c, s, p)).collect();
        Network { convs, lins: w.lins.clone() }
    }

    /// The five relu taps of AlexNet for an image `[H, W, 3]` with values in [0, 1]
    /// (mapped to [−1, 1], then through the scaling layer). `H, W ≥ MIN_SIDE`.
    pub fn taps(&self, rgb: &[f32], w: usize, h: usize) -> Vec<Features> {
        assert!(w >= MIN_SIDE && h >= MIN_SIDE, "image {w}x{h} below {MIN_SIDE}");
        let mut data = scratch::take(rgb.len());
        for (d, p) in data.chunks_exact_mut(3).zip(rgb.chunks_exact(3)) {
            for c in 0..3 {
                d[c] = ((2.0 * p[c] - 1.0) - SHIFT[c]) / SCALE[c];
            }
        }
        let mut x = Features { h, w, c: 3, data };
        let mut taps: Vec<Features> = Vec::with_capacity(5);
        for (i, conv) in self.convs.iter().enumerate() {
            let input = match i {
                0 => &x,
                1 | 2 => {
                    let pooled = max_pool(&taps[i - 1]);
                    scratch::give(std::mem::replace(&mut x, pooled).data);
                    &x
                }
                _ => &taps[i - 1],
            };
            taps.push(conv.forward_relu(input));
        }
        scratch::give(x.data);
        taps
    }

    /// The spatial LPIPS map `[H, W]` between two images `[H, W, 3]` in [0, 1]: the sum
    /// over the five taps of the linear layer on `(n0 − n1)²` (n = f/(‖f‖ + 1e-10) over
    /// channels), each upsampled to `H×W` bilinearly.
    pub fn spatial_map(&self, a: &[f32], b: &[f32], w: usize, h: usize) -> Vec<f32> {
        let (ta, tb) = rayon::join(|| self.taps(a, w, h), || self.taps(b, w, h));
        let mut map = vec![0.0f32; w * h];
        for ((fa, fb), lin) in ta.iter().zip(&tb).zip(&self.lins) {
            let layer: Vec<f32> = fa
                .data
                .chunks_exact(fa.c)
                .zip(fb.data.chunks_exact(fb.c))
                .map(|(pa, pb)| {
                    let na = pa.iter().map(|v| v * v).sum::<f32>().sqrt() + 1e-10;
                    let nb = pb.iter().map(|v| v * v).sum::<f32>().sqrt() + 1e-10;
                    pa.iter()
                        .zip(pb)
                        .zip(lin)
                        .map(|((x, y), l)| l * (x / na - y / nb).powi(2))
                        .sum()
                })
                .collect();
            for (m, v) in map.iter_mut().zip(upsample_bilinear(&layer, fa.w, fa.h, w, h)) {
                *m += v;
            }
        }
        for f in ta.into_iter().chain(tb) {
            scratch::give(f.data);
        }
        map
    }
}

/// PyTorch `F.interpolate(mode="bilinear", align_corners=False)` of a single-channel map
/// `[h, w]` to `[out_h, out_w]`: `src = (dst + 0.5)·in/out − 0.5`, clamped at 0,
/// `i0 = floor(src)`, `i1 = min(i0 + 1, in − 1)`.
pub fn upsample_bilinear(src: &[f32], w: usize, h: usize, out_w: usize, out_h: usize) -> Vec<f32> {
    let axis = |n_in: usize, n_out: usize| -> Vec<(usize, usize, f32)> {
        let scale = n_in as f32 / n_out as f32;
        (0..n_out)
            .map(|d| {
                let s = ((d as f32 + 0.5) * scale - 0.5).max(0.0);
                let i0 = (s as usize).min(n_in - 1);
                let i1 = (i0 + 1).min(n_in - 1);
                (i0, i1, s - i0 as f32)
            })
            .collect()
    };
    let (xs, ys) = (axis(w, out_w), axis(h, out_h));
    let mut out = Vec::with_capacity(out_w * out_h);
    for &(y0, y1, ly) in &ys {
        for &(x0, x1, lx) in &xs {
            let top = (1.0 - lx) * src[y0 * w + x0] + lx * src[y0 * w + x1];
            let bottom = (1.0 - lx) * src[y1 * w + x0] + lx * src[y1 * w + x1];
            out.push((1.0 - ly) * top + ly * bottom);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilinear_upsample_matches_pytorch_align_corners_false() {
        // torch.nn.functional.interpolate(torch.tensor([[[[1., 2.], [3., 4.]]]]),
        //   size=(4, 4), mode="bilinear", align_corners=False)
        let want = [
            1.0, 1.25, 1.75, 2.0, //
            1.5, 1.75, 2.25, 2.5, //
            2.5, 2.75, 3.25, 3.5, //
            3.0, 3.25, 3.75, 4.0,
        ];
        assert_eq!(upsample_bilinear(&[1.0, 2.0, 3.0, 4.0], 2, 2, 4, 4), want);
        // A 3 → 2 downscale: src = (d + 0.5)·1.5 − 0.5 = 0.25, 1.75.
        let got = upsample_bilinear(&[0.0, 4.0, 8.0], 3, 1, 2, 1);
        assert_eq!(got, [1.0, 7.0]);
    }

    #[test]
    fn conv_matches_a_direct_convolution() {
        let (cin, cout, k) = (2, 3, 3);
        let weight: Vec<f32> =
            (0..cout * cin * k * k).map(|i| ((i * 7 % 11) as f32 - 5.0) / 10.0).collect();
        let bias = vec![0.1, -0.2, 0.05];
        let cw = ConvWeights { cin, cout, k, weight: weight.clone(), bias: bias.clone() };
        let conv = Conv::new(&cw, 2, 1);
        let (h, w) = (5, 6);
        let data: Vec<f32> = (0..h * w * cin).map(|i| ((i * 5 % 13) as f32 - 6.0) / 6.0).collect();
        let x = Features { h, w, c: cin, data };
        let y = conv.forward_relu(&x);
        assert_eq!((y.h, y.w, y.c), (3, 3, 3));
        for oy in 0..y.h {
            for ox in 0..y.w {
                for co in 0..cout {
                    let mut acc = bias[co];
                    for ci in 0..cin {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) =
                                    ((oy * 2 + ky) as isize - 1, (ox * 2 + kx) as isize - 1);
                                if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w {
                                    acc += weight[((co * cin + ci) * k + ky) * k + kx]
                                        * x.data[(iy as usize * w + ix as usize) * cin + ci];
                                }
                            }
                        }
                    }
                    let got = y.data[(oy * y.w + ox) * cout + co];
                    assert!(
                        (got - acc.max(0.0)).abs() < 1e-5,
                        "({oy}, {ox}, {co}): {got} vs {acc}"
                    );
                }
            }
        }
    }

    /// The Winograd path of conv2-5 agrees with im2col at AlexNet's kernel sizes, channel
    /// counts of the same order and weight magnitudes like the trained ones.
    #[test]
    fn winograd_matches_im2col() {
        for (k, pad, cin, cout, side) in [(5, 2, 64, 48, 21), (3, 1, 96, 64, 15)] {
            let mut s = 0x2545_F491_4F6C_DD1Du64;
            let mut next = move || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            };
            let scale = 1.0 / ((k * k * cin) as f32).sqrt();
            let weight: Vec<f32> = (0..cout * cin * k * k).map(|_| next() * scale).collect();
            let bias: Vec<f32> = (0..cout).map(|_| 0.1 * next()).collect();
            let cw = ConvWeights { cin, cout, k, weight, bias };
            let conv = Conv::new(&cw, 1, pad);
            assert!(conv.winograd.is_some());
            let data = (0..side * side * cin).map(|_| next().max(0.0) * 4.0).collect();
            let x = Features { h: side, w: side, c: cin, data };
            let (fast, slow) = (conv.forward_relu(&x), conv.forward_relu_im2col(&x));
            assert_eq!((fast.h, fast.w, fast.c), (slow.h, slow.w, slow.c));
            let peak = slow.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err =
                fast.data.iter().zip(&slow.data).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            eprintln!("winograd k{k}: max error {err:.3e} of peak {peak:.3}");
            assert!(err <= 1e-5 * peak, "k{k}: max error {err} vs peak {peak}");
        }
    }

    /// conv1's space-to-depth Winograd form (11x11, stride 4, padding 2) agrees with
    /// im2col, with image sides that leave 0 to 3 rows past the last window.
    #[test]
    fn strided_winograd_matches_im2col() {
        let (cin, cout, k) = (3, 16, 11);
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 23) as f32 - 1.0
        };
        let weight: Vec<f32> = (0..cout * cin * k * k).map(|_| next() * 0.05).collect();
        let bias: Vec<f32> = (0..cout).map(|_| 0.1 * next()).collect();
        let conv = Conv::new(&ConvWeights { cin, cout, k, weight, bias }, 4, 2);
        assert!(conv.winograd.is_some());
        for (h, w) in [(31, 34), (40, 33)] {
            let data = (0..h * w * cin).map(|_| next() * 2.0).collect();
            let x = Features { h, w, c: cin, data };
            let (fast, slow) = (conv.forward_relu(&x), conv.forward_relu_im2col(&x));
            assert_eq!((fast.h, fast.w, fast.c), (slow.h, slow.w, slow.c));
            let peak = slow.data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let err =
                fast.data.iter().zip(&slow.data).fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            eprintln!("space-to-depth winograd {h}x{w}: max error {err:.3e} of peak {peak:.3}");
            assert!(err <= 1e-5 * peak, "{h}x{w}: max error {err} vs peak {peak}");
        }
    }

    /// The spatial map is bitwise the same on 1 and 3 threads (random AlexNet-shaped
    /// weights, so no installed weights are needed).
    #[test]
    fn spatial_map_does_not_depend_on_the_thread_count() {
        let mut s = 0x0123_4567_89AB_CDEFu64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let convs = super::super::weights::CONV_SHAPES
            .iter()
            .map(|&(cin, cout, k)| {
                let scale = 2.0 / ((k * k * cin) as f32).sqrt();
                let weight = (0..cout * cin * k * k).map(|_| (next() - 0.5) * scale).collect();
                ConvWeights { cin, cout, k, weight, bias: (0..cout).map(|_| 0.0).collect() }
            })
            .collect::<Vec<_>>();
        let lins = convs.iter().map(|c| (0..c.cout).map(|_| next() * 0.1).collect()).collect();
        let net = Network::new(&AlexWeights { convs, lins });
        let (w, h) = (45, 38);
        let a: Vec<f32> = (0..w * h * 3).map(|_| next()).collect();
        let b: Vec<f32> = (0..w * h * 3).map(|_| next()).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| net.spatial_map(&a, &b, w, h))
        };
        let one = run(1);
        assert!(one.iter().any(|v| *v > 0.0));
        assert_eq!(one, run(3));
    }

    #[test]
    fn max_pool_takes_window_maxima() {
        let x =
            Features { h: 5, w: 5, c: 1, data: (0..25).map(|i| ((i * 7) % 25) as f32).collect() };
        let y = max_pool(&x);
        assert_eq!((y.h, y.w), (2, 2));
        // Window rows 0..3, cols 0..3 of values (7i mod 25).
        let want: f32 = (0..3)
            .flat_map(|r| (0..3).map(move |c| ((r * 5 + c) * 7 % 25) as f32))
            .fold(0.0, f32::max);
        assert_eq!(y.data[0], want);
    }
}
