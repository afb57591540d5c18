//! Winograd minimal filtering F(m×m, r×r) for the stride-1 convolutions of the LPIPS
//! network (Lavin & Gray 2016): `Y = Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d B)] A` per tile of `m×m`
//! outputs, where `d` is the `n×n` input patch (`n = m + r − 1`) and `g` the `r×r` kernel.
//! The channel sum of `⊙` becomes `n²` independent matrix products `[tiles, Cin]·[Cin,
//! Cout]`, which cost `n²/(m²r²)` of the direct convolution's multiplications (1/4 for
//! F(4×4, 3×3), 49/225 for F(3×3, 5×5)).
//!
//! The transforms are derived (Cook–Toom) from `n − 1` finite interpolation points plus
//! the point at infinity, in f64: with `P(x) = Πₗ(x − pₗ)` and `Nⱼ(x) = P(x)/(x − pⱼ)`,
//! - `Aᵀ[i][j] = pⱼⁱ` (`m×n`; the last column picks the highest power, `i = m − 1`),
//! - `G[j][k] = pⱼᵏ / Nⱼ(pⱼ)` (`n×r`; the last row picks `k = r − 1`),
//! - `Bᵀ[j][t]` = the coefficient of `xᵗ` in `Nⱼ` (`n×n`; the last row is that of `P`).
//!
//! Feature maps are `[h, w, C]` row-major, like [`super::network`]. Stages: input
//! transform `[tiles, n², Cin]` (rayon over tiles), `n²` GEMMs into `[n², tiles, Cout]`
//! (rayon over the `n²` products, each done whole by one thread) and output transform
//! with bias and ReLU (rayon over tile rows): every value is computed by the same
//! operations in the same order whatever the thread count.

use ndarray::{ArrayView2, ArrayViewMut2, ShapeBuilder, linalg::general_mat_mul};
use rayon::prelude::*;

use super::scratch;

/// Interpolation points of F(4×4, 3×3) and F(2×2, 5×5) (`n = 6`: five finite points);
/// ±1/2 rather than ±2 halves the f32 error of F(4×4, 3×3) on AlexNet-like layers.
const POINTS_6: [f64; 5] = [0.0, 1.0, -1.0, 0.5, -0.5];
/// Interpolation points of F(3×3, 5×5) (`n = 7`: six finite points; {0, ±1, ±2, 1/2} is
/// slightly more accurate here than {0, ±1, ±1/2, 2}).
const POINTS_7: [f64; 6] = [0.0, 1.0, -1.0, 2.0, -2.0, 0.5];

/// The tile size `m` used for a stride-1 kernel of side `k`, if Winograd applies.
pub fn tile_for_kernel(k: usize) -> Option<usize> {
    match k {
        3 => Some(4),
        5 => Some(3),
        _ => None,
    }
}

/// The finite interpolation points for `n = m + r − 1`.
fn points(n: usize) -> &'static [f64] {
    match n {
        6 => &POINTS_6,
        7 => &POINTS_7,
        _ => panic!("no Winograd interpolation points for n = {n}"),
    }
}

/// The Cook–Toom matrices `(Aᵀ [m, n], G [n, r], Bᵀ [n, n])` of F(m, r), row-major f64.
pub fn matrices(m: usize, r: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let n = m + r - 1;
    let p = points(n);
    assert_eq!(p.len(), n - 1, "F({m}, {r}) needs {} finite points", n - 1);
    let mut at = vec![0.0; m * n];
    for i in 0..m {
        for (j, pj) in p.iter().enumerate() {
            at[i * n + j] = pj.powi(i as i32);
        }
    }
    at[(m - 1) * n + n - 1] = 1.0;
    // Coefficients (lowest power first) of the product of (x − pₗ) over `roots`.
    let poly = |roots: &mut dyn Iterator<Item = f64>| -> Vec<f64> {
        let mut c = vec![1.0];
        for root in roots {
            let mut next = vec![0.0; c.len() + 1];
            for (t, v) in c.iter().enumerate() {
                next[t + 1] += v;
                next[t] -= root * v;
            }
            c = next;
        }
        c
    };
    let mut g = vec![0.0; n * r];
    let mut bt = vec![0.0; n * n];
    for (j, pj) in p.iter().enumerate() {
        let nj = poly(&mut p.iter().enumerate().filter(|(l, _)| *l != j).map(|(_, v)| *v));
        bt[j * n..j * n + n - 1].copy_from_slice(&nj);
        let f: f64 = p.iter().enumerate().filter(|(l, _)| *l != j).map(|(_, pl)| pj - pl).product();
        for k in 0..r {
            g[j * r + k] = pj.powi(k as i32) / f;
        }
    }
    g[(n - 1) * r + r - 1] = 1.0;
    bt[(n - 1) * n..].copy_from_slice(&poly(&mut p.iter().copied()));
    (at, g, bt)
}

/// A stride-1 convolution `k×k`, padding `pad`, in the Winograd domain.
pub struct WinogradConv {
    m: usize,
    n: usize,
    k: usize,
    pad: usize,
    cin: usize,
    cout: usize,
    /// `[m, n]` output transform.
    at: Vec<f32>,
    /// `[n, n]` input transform.
    bt: Vec<f32>,
    /// `[n², Cin, Cout]` transformed kernels `G g Gᵀ`.
    u: Vec<f32>,
}

impl WinogradConv {
    /// Transform the kernels `weight` `[Cout, Cin, k, k]` (OIHW) for tiles of `m×m`.
    pub fn new(
        weight: &[f32],
        cin: usize,
        cout: usize,
        k: usize,
        pad: usize,
        m: usize,
    ) -> WinogradConv {
        assert_eq!(weight.len(), cout * cin * k * k, "weights are [Cout, Cin, k, k]");
        let n = m + k - 1;
        let (at, g, bt) = matrices(m, k);
        let mut u = vec![0.0f32; n * n * cin * cout];
        let mut tmp = vec![0.0f64; n * k];
        for co in 0..cout {
            for ci in 0..cin {
                let w = &weight[(co * cin + ci) * k * k..(co * cin + ci + 1) * k * k];
                // tmp = G g  [n, k]; u = tmp Gᵀ  [n, n].
                for i in 0..n {
                    for x in 0..k {
                        tmp[i * k + x] = (0..k).map(|y| g[i * k + y] * w[y * k + x] as f64).sum();
                    }
                }
                for i in 0..n {
                    for j in 0..n {
                        let v: f64 = (0..k).map(|x| tmp[i * k + x] * g[j * k + x]).sum();
                        u[((i * n + j) * cin + ci) * cout + co] = v as f32;
                    }
                }
            }
        }
        let f32s = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect();
        WinogradConv { m, n, k, pad, cin, cout, at: f32s(at), bt: f32s(bt), u }
    }

    /// `relu(conv(x) + bias)` of `x` `[h, w, Cin]`; returns `(oh, ow, [oh, ow, Cout])`.
    pub fn forward_relu(
        &self,
        x: &[f32],
        h: usize,
        w: usize,
        bias: &[f32],
    ) -> (usize, usize, Vec<f32>) {
        let (m, n, cin, cout) = (self.m, self.n, self.cin, self.cout);
        assert_eq!(x.len(), h * w * cin, "input is [h, w, Cin]");
        let oh = h + 2 * self.pad + 1 - self.k;
        let ow = w + 2 * self.pad + 1 - self.k;
        let (th, tw) = (oh.div_ceil(m), ow.div_ceil(m));
        let tiles = th * tw;
        let nn = n * n;
        // Input transform: V [tiles, n², Cin].
        let mut v = scratch::take(tiles * nn * cin);
        v.par_chunks_mut(nn * cin).enumerate().for_each_init(
            || (vec![0.0f32; nn * cin], vec![0.0f32; nn * cin]),
            |(d, tmp), (t, out)| {
                let (y0, x0) = (
                    (t / tw * m) as isize - self.pad as isize,
                    (t % tw * m) as isize - self.pad as isize,
                );
                for a in 0..n {
                    for b in 0..n {
                        let dst = &mut d[(a * n + b) * cin..(a * n + b + 1) * cin];
                        let (iy, ix) = (y0 + a as isize, x0 + b as isize);
                        if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                            dst.fill(0.0);
                        } else {
                            let src = (iy as usize * w + ix as usize) * cin;
                            dst.copy_from_slice(&x[src..src + cin]);
                        }
                    }
                }
                // tmp[i][b] = Σ_a Bᵀ[i][a] d[a][b]; out[i][j] = Σ_b Bᵀ[j][b] tmp[i][b].
                transform(&self.bt, n, n, d, tmp, cin, Side::Left);
                transform(&self.bt, n, n, tmp, out, cin, Side::Right);
            },
        );
        // n² products: M [n², tiles, Cout].
        let mut prod = scratch::take(nn * tiles * cout);
        prod.par_chunks_mut(tiles * cout).enumerate().for_each(|(xi, c)| {
            let a = ArrayView2::from_shape((tiles, cin).strides((nn * cin, 1)), &v[xi * cin..])
                .expect("V is [tiles, n², Cin]");
            let b = ArrayView2::from_shape(
                (cin, cout),
                &self.u[xi * cin * cout..(xi + 1) * cin * cout],
            )
            .expect("U is [n², Cin, Cout]");
            let mut c =
                ArrayViewMut2::from_shape((tiles, cout), c).expect("M is [n², tiles, Cout]");
            general_mat_mul(1.0, &a, &b, 0.0, &mut c);
        });
        // Output transform, bias and ReLU, by rows of tiles.
        let mut out = scratch::take(oh * ow * cout);
        out.par_chunks_mut(m * ow * cout).enumerate().for_each_init(
            || (vec![0.0f32; nn * cout], vec![0.0f32; m * n * cout], vec![0.0f32; m * m * cout]),
            |(mt, tmp, y), (ty, rows)| {
                for tx in 0..tw {
                    let t = ty * tw + tx;
                    for xi in 0..nn {
                        let src = (xi * tiles + t) * cout;
                        mt[xi * cout..(xi + 1) * cout].copy_from_slice(&prod[src..src + cout]);
                    }
                    transform(&self.at, m, n, mt, tmp, cout, Side::Left);
                    transform(&self.at, m, n, tmp, y, cout, Side::Right);
                    for a in 0..m.min(oh - ty * m) {
                        for b in 0..m.min(ow - tx * m) {
                            let dst = (a * ow + tx * m + b) * cout;
                            let src = &y[(a * m + b) * cout..(a * m + b + 1) * cout];
                            for ((o, s), bias) in
                                rows[dst..dst + cout].iter_mut().zip(src).zip(bias)
                            {
                                *o = (s + bias).max(0.0);
                            }
                        }
                    }
                }
            },
        );
        scratch::give(v);
        scratch::give(prod);
        (oh, ow, out)
    }
}

/// Which side of a 2-D block a transform matrix multiplies.
#[derive(Clone, Copy)]
enum Side {
    /// `out[i][b] = Σ_a T[i][a] src[a][b]`: `src [cols, cols']` → `out [rows, cols']`.
    Left,
    /// `out[a][i] = Σ_b T[i][b] src[a][b]`: `src [rows', cols]` → `out [rows', rows]`.
    Right,
}

/// Apply the `[rows, cols]` matrix `t` to a block of channel vectors (`c` values per
/// entry), on the left (`src` is `[cols, q, c]`) or on the right (`src` is `[q, cols, c]`),
/// where `q = src.len() / (cols·c)`. Zero coefficients are skipped.
fn transform(
    t: &[f32],
    rows: usize,
    cols: usize,
    src: &[f32],
    out: &mut [f32],
    c: usize,
    side: Side,
) {
    let q = src.len() / (cols * c);
    let out = &mut out[..rows * q * c];
    out.fill(0.0);
    let axpy = |o: &mut [f32], s: &[f32], coef: f32| {
        for (o, s) in o.iter_mut().zip(s) {
            *o += coef * s;
        }
    };
    match side {
        // Whole rows `[q, c]` at once.
        Side::Left => {
            for (i, o) in out.chunks_exact_mut(q * c).enumerate() {
                for (a, s) in src.chunks_exact(q * c).enumerate() {
                    let coef = t[i * cols + a];
                    if coef != 0.0 {
                        axpy(o, s, coef);
                    }
                }
            }
        }
        Side::Right => {
            for (o, s) in out.chunks_exact_mut(rows * c).zip(src.chunks_exact(cols * c)) {
                for (i, o) in o.chunks_exact_mut(c).enumerate() {
                    for (a, s) in s.chunks_exact(c).enumerate() {
                        let coef = t[i * cols + a];
                        if coef != 0.0 {
                            axpy(o, s, coef);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic values in [−1, 1) (splitmix64).
    fn values(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = crate::util::rng::Rng::from_state(seed);
        (0..len).map(|_| 2.0 * rng.uniform_f32() - 1.0).collect()
    }

    #[test]
    fn one_dimensional_transforms_compute_a_correlation() {
        for (m, r) in [(4, 3), (2, 5), (3, 5)] {
            let n = m + r - 1;
            let (at, g, bt) = matrices(m, r);
            let d: Vec<f64> = values(n, 1).iter().map(|v| *v as f64).collect();
            let k: Vec<f64> = values(r, 2).iter().map(|v| *v as f64).collect();
            let gk: Vec<f64> = (0..n).map(|j| (0..r).map(|t| g[j * r + t] * k[t]).sum()).collect();
            let bd: Vec<f64> = (0..n).map(|j| (0..n).map(|t| bt[j * n + t] * d[t]).sum()).collect();
            for i in 0..m {
                let got: f64 = (0..n).map(|j| at[i * n + j] * gk[j] * bd[j]).sum();
                let want: f64 = (0..r).map(|t| k[t] * d[i + t]).sum();
                assert!((got - want).abs() < 1e-12, "F({m}, {r}) y{i}: {got} vs {want}");
            }
        }
    }

    #[test]
    fn matches_a_direct_convolution() {
        for (k, pad, h, w) in [(3, 1, 9, 11), (5, 2, 10, 7)] {
            let (cin, cout) = (5, 6);
            let weight = values(cout * cin * k * k, 3);
            let bias = values(cout, 4);
            let x = values(h * w * cin, 5);
            let conv = WinogradConv::new(&weight, cin, cout, k, pad, tile_for_kernel(k).unwrap());
            let (oh, ow, y) = conv.forward_relu(&x, h, w, &bias);
            assert_eq!((oh, ow), (h + 2 * pad + 1 - k, w + 2 * pad + 1 - k));
            for oy in 0..oh {
                for ox in 0..ow {
                    for co in 0..cout {
                        let mut acc = bias[co] as f64;
                        for ci in 0..cin {
                            for ky in 0..k {
                                for kx in 0..k {
                                    let (iy, ix) = (
                                        (oy + ky) as isize - pad as isize,
                                        (ox + kx) as isize - pad as isize,
                                    );
                                    if iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w
                                    {
                                        acc += weight[((co * cin + ci) * k + ky) * k + kx] as f64
                                            * x[(iy as usize * w + ix as usize) * cin + ci] as f64;
                                    }
                                }
                            }
                        }
                        let got = y[(oy * ow + ox) * cout + co] as f64;
                        assert!(
                            (got - acc.max(0.0)).abs() < 1e-4,
                            "k{k} ({oy}, {ox}, {co}): {got} vs {acc}"
                        );
                    }
                }
            }
        }
    }
}
