//! Spherical-harmonics colour (3DGS convention) and its VJP.
//!
//! `colour = dc + Σ_{k≥1} Y_k(dir) · rest[k-1]`, then clamped at 0 as 3DGS does
//! (`max(colour, 0)`; the gradient is zero where the clamp is active). `dc` is already the
//! degree-0 RGB (`0.5 + C0·f_dc` of 3DGS), so degree 0 is `dc` itself. `dir` is the unit vector
//! from the camera centre to the Gaussian, in world coordinates ([`super::ShFrame::World`]) or
//! rotated into the Gaussian's local frame (`Rᵀ dir`, [`super::ShFrame::Local`], MoSca).
//! The basis and constants are those of 3DGS `forward.cu::computeColorFromSH` (real SH, with
//! its sign convention); `rest` is `[N, K, 3]`, coefficient k ↔ basis function k+1.

use std::ops::{Add, Mul, Sub};

/// `Y_0 = 1/(2√π)`: a 3DGS degree-0 coefficient `f_dc` is the RGB `dc = 0.5 + C0·f_dc`.
pub const C0: f64 = 0.282_094_791_773_878_14;
const C1: f32 = 0.488_602_5;
const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
const C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_33,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// Number of basis functions of degree ≤ `degree`, i.e. (degree+1)².
pub fn num_basis(degree: u8) -> usize {
    (degree as usize + 1).pow(2)
}

/// A value with its gradient w.r.t. the 3 direction components (forward-mode AD).
#[derive(Debug, Clone, Copy, Default)]
struct Dual3 {
    v: f32,
    d: [f32; 3],
}

impl Add for Dual3 {
    type Output = Dual3;
    fn add(self, o: Dual3) -> Dual3 {
        Dual3 { v: self.v + o.v, d: std::array::from_fn(|i| self.d[i] + o.d[i]) }
    }
}

impl Sub for Dual3 {
    type Output = Dual3;
    fn sub(self, o: Dual3) -> Dual3 {
        Dual3 { v: self.v - o.v, d: std::array::from_fn(|i| self.d[i] - o.d[i]) }
    }
}

// The product rule adds two terms.
#[allow(clippy::suspicious_arithmetic_impl)]
impl Mul for Dual3 {
    type Output = Dual3;
    fn mul(self, o: Dual3) -> Dual3 {
        Dual3 { v: self.v * o.v, d: std::array::from_fn(|i| self.d[i] * o.v + self.v * o.d[i]) }
    }
}

impl Mul<Dual3> for f32 {
    type Output = Dual3;
    fn mul(self, o: Dual3) -> Dual3 {
        Dual3 { v: self * o.v, d: o.d.map(|d| self * d) }
    }
}

/// Real SH basis `Y_0..Y_15` at the unit direction `(x, y, z)`, generic so that the same
/// code gives values (f32) and direction gradients (Dual3). Entries above `degree` are 0, and
/// so is `Y_0` (the degree-0 term is carried by `dc`).
fn basis<T>(degree: u8, x: T, y: T, z: T) -> [T; 16]
where
    T: Copy + Default + Add<Output = T> + Sub<Output = T> + Mul<Output = T>,
    f32: Mul<T, Output = T>,
{
    let mut b = [T::default(); 16];
    if degree >= 1 {
        b[1] = -C1 * y;
        b[2] = C1 * z;
        b[3] = -C1 * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = C2[0] * (x * y);
        b[5] = C2[1] * (y * z);
        b[6] = C2[2] * (2.0 * zz - xx - yy);
        b[7] = C2[3] * (x * z);
        b[8] = C2[4] * (xx - yy);
        if degree >= 3 {
            b[9] = C3[0] * y * (3.0 * xx - yy);
            b[10] = C3[1] * (x * y) * z;
            b[11] = C3[2] * y * (4.0 * zz - xx - yy);
            b[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = C3[4] * x * (4.0 * zz - xx - yy);
            b[14] = C3[5] * z * (xx - yy);
            b[15] = C3[6] * x * (xx - 3.0 * yy);
        }
    }
    b
}

/// The basis `Y_0..Y_15` at unit direction `dir` (entries above `degree`, and `Y_0`, are 0):
/// `eval_unclamped(degree, dc, rest, dir)[c] = dc[c] + Σ_k basis_values(..)[k] · rest[(k-1)·3 + c]`.
pub fn basis_values(degree: u8, dir: [f32; 3]) -> [f32; 16] {
    basis(degree, dir[0], dir[1], dir[2])
}

/// Colour before the clamp: `dc + Σ Y_k(dir) rest[k-1]`; `rest` is this Gaussian's `[K, 3]`.
pub fn eval_unclamped(degree: u8, dc: [f32; 3], rest: &[f32], dir: [f32; 3]) -> [f32; 3] {
    let y = basis(degree, dir[0], dir[1], dir[2]);
    let mut c = dc;
    for k in 1..num_basis(degree) {
        for ch in 0..3 {
            c[ch] += y[k] * rest[(k - 1) * 3 + ch];
        }
    }
    c
}

/// The clamped colour `max(eval_unclamped, 0)`.
pub fn eval(degree: u8, dc: [f32; 3], rest: &[f32], dir: [f32; 3]) -> [f32; 3] {
    eval_unclamped(degree, dc, rest, dir).map(|v| v.max(0.0))
}

/// VJP of [`eval`] given `v_color = dL/dcolour`: returns `(v_dc, v_dir)` and writes
/// `v_rest` (`[K, 3]`, overwritten).
pub fn eval_vjp(
    degree: u8,
    dc: [f32; 3],
    rest: &[f32],
    dir: [f32; 3],
    v_color: [f32; 3],
    v_rest: &mut [f32],
) -> ([f32; 3], [f32; 3]) {
    let raw = eval_unclamped(degree, dc, rest, dir);
    let v: [f32; 3] = std::array::from_fn(|c| if raw[c] < 0.0 { 0.0 } else { v_color[c] });
    let seed = |i: usize, val: f32| {
        let mut d = [0.0; 3];
        d[i] = 1.0;
        Dual3 { v: val, d }
    };
    let y = basis(degree, seed(0, dir[0]), seed(1, dir[1]), seed(2, dir[2]));
    let mut v_dir = [0.0f32; 3];
    for k in 1..num_basis(degree) {
        let mut v_y = 0.0;
        for ch in 0..3 {
            v_rest[(k - 1) * 3 + ch] = y[k].v * v[ch];
            v_y += rest[(k - 1) * 3 + ch] * v[ch];
        }
        for i in 0..3 {
            v_dir[i] += v_y * y[k].d[i];
        }
    }
    (v, v_dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn degree_zero_is_dc_and_clamp_is_applied() {
        assert_eq!(eval(0, [0.2, -0.1, 0.9], &[], [0.0, 0.0, 1.0]), [0.2, 0.0, 0.9]);
    }

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Fibonacci-sphere quadrature of ∫ Y_i Y_j dΩ ≈ δ_ij (Y_0 is carried by `dc`).
        let n = 20000;
        let mut gram = [[0.0f64; 16]; 16];
        for s in 0..n {
            let z = 1.0 - 2.0 * (s as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = s as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let y = basis(3, (r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            for i in 0..16 {
                for j in 0..16 {
                    gram[i][j] += (y[i] * y[j]) as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for i in 1..16 {
            for j in 1..16 {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((gram[i][j] - want).abs() < 2e-3, "<Y{i}, Y{j}> = {}", gram[i][j]);
            }
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let rest: Vec<f32> = (0..45).map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.03).collect();
        let dc = [0.5, 0.6, 0.4];
        let dir = [0.3f32, -0.5, 0.81];
        let v_color = [0.7, -0.3, 1.1];
        let mut v_rest = vec![0.0; 45];
        let (v_dc, v_dir) = eval_vjp(3, dc, &rest, dir, v_color, &mut v_rest);
        let loss = |dc: [f32; 3], rest: &[f32], dir: [f32; 3]| -> f64 {
            let c = eval(3, dc, rest, dir);
            (0..3).map(|i| (c[i] * v_color[i]) as f64).sum()
        };
        let h = 1e-3f32;
        for i in 0..3 {
            let (mut a, mut b) = (dir, dir);
            a[i] += h;
            b[i] -= h;
            let fd = (loss(dc, &rest, a) - loss(dc, &rest, b)) / (2.0 * h as f64);
            assert!((fd - v_dir[i] as f64).abs() < 2e-3, "dir {i}: {fd} vs {}", v_dir[i]);
        }
        for k in 0..45 {
            let (mut a, mut b) = (rest.clone(), rest.clone());
            a[k] += h;
            b[k] -= h;
            let fd = (loss(dc, &a, dir) - loss(dc, &b, dir)) / (2.0 * h as f64);
            assert!((fd - v_rest[k] as f64).abs() < 2e-3, "rest {k}: {fd} vs {}", v_rest[k]);
        }
        assert_eq!(v_dc, v_color);
    }
}
