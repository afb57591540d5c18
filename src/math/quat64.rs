//! Double-precision quaternions (w, x, y, z, Hamilton product) and rotation matrices: the
//! vector-Jacobian product (VJP) of each operation the optimiser's losses use (checked by
//! finite differences, which needs f64; the renderer's f32 helpers are in [`super::quat`]),
//! and the two upstream matrix-to-quaternion conventions the importers reproduce: roma's
//! ([`mat_to_quat_roma`]: Markley's method, the largest-magnitude component made positive;
//! Shape of Motion) and pytorch3d ≥ 0.7.6's ([`from_rotmat`]: the largest candidate, then
//! standardised to w ≥ 0; MoSca).
//!
//! A VJP takes the cotangent `g` of the output and returns the cotangents of the inputs.

/// A quaternion (w, x, y, z).
pub type Q = [f64; 4];
/// A 3-vector.
pub type V3 = [f64; 3];
/// A 3x3 matrix, row-major: `m[row][col]`.
pub type M3 = [[f64; 3]; 3];

/// The arithmetic of the generic quaternion functions: `f64`, or lanes of it
/// ([`super::lanes::Lanes`]).
pub trait Real:
    Copy
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Neg<Output = Self>
{
}

impl<T> Real for T where
    T: Copy
        + std::ops::Add<Output = T>
        + std::ops::Sub<Output = T>
        + std::ops::Mul<Output = T>
        + std::ops::Neg<Output = T>
{
}

/// Hamilton product `a ⊗ b`.
#[inline(always)]
pub fn mul<T: Real>(a: [T; 4], b: [T; 4]) -> [T; 4] {
    let [aw, ax, ay, az] = a;
    let [bw, bx, by, bz] = b;
    [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + bw * ax + ay * bz - az * by,
        aw * by + bw * ay + az * bx - ax * bz,
        aw * bz + bw * az + ax * by - ay * bx,
    ]
}

/// VJP of [`mul`]: `(g_a, g_b) = (g ⊗ b*, a* ⊗ g)` (left and right multiplication by a
/// quaternion are linear maps whose transposes multiply by its conjugate).
#[inline(always)]
pub fn mul_vjp<T: Real>(a: [T; 4], b: [T; 4], g: [T; 4]) -> ([T; 4], [T; 4]) {
    (mul(g, conj(b)), mul(conj(a), g))
}

/// Conjugate `(w, −x, −y, −z)`.
#[inline(always)]
pub fn conj<T: Real>(q: [T; 4]) -> [T; 4] {
    [q[0], -q[1], -q[2], -q[3]]
}

/// Euclidean norm of the four components.
#[inline]
pub fn norm(q: Q) -> f64 {
    dot4(q, q).sqrt()
}

/// Dot product of four components.
#[inline(always)]
pub fn dot4<T: Real>(a: [T; 4], b: [T; 4]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
}

/// `q / ‖q‖` and `‖q‖`; a zero quaternion gives the identity (and norm 0).
#[inline]
pub fn normalize(q: Q) -> (Q, f64) {
    let n = norm(q);
    if n > 0.0 { (q.map(|v| v / n), n) } else { ([1.0, 0.0, 0.0, 0.0], 0.0) }
}

/// VJP of [`normalize`] at `unit = q/‖q‖`: `(g − unit·⟨unit, g⟩) / ‖q‖` (0 for a zero q).
#[inline]
pub fn normalize_vjp(unit: Q, n: f64, g: Q) -> Q {
    if n == 0.0 {
        return [0.0; 4];
    }
    let d = dot4(unit, g);
    [0, 1, 2, 3].map(|k| (g[k] - unit[k] * d) / n)
}

/// Rotation matrix of a unit quaternion.
#[inline]
pub fn to_rotmat(q: Q) -> M3 {
    let [w, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// VJP of [`to_rotmat`] (the formula's polynomial, unit q assumed): `dL/dq` from `dL/dR`.
#[inline]
pub fn to_rotmat_vjp(q: Q, g: &M3) -> Q {
    super::quat::rotmat_vjp!(q, |i: usize, j: usize| g[i][j])
}

/// Quaternion of a rotation matrix, as pytorch3d's `matrix_to_quaternion` (v0.7.6+): the
/// best-conditioned of four candidates (first on ties), standardised to w ≥ 0.
pub fn from_rotmat(m: &M3) -> Q {
    let (m00, m01, m02) = (m[0][0], m[0][1], m[0][2]);
    let (m10, m11, m12) = (m[1][0], m[1][1], m[1][2]);
    let (m20, m21, m22) = (m[2][0], m[2][1], m[2][2]);
    let sqrt_pos = |x: f64| if x > 0.0 { x.sqrt() } else { 0.0 };
    let q_abs = [
        sqrt_pos(1.0 + m00 + m11 + m22),
        sqrt_pos(1.0 + m00 - m11 - m22),
        sqrt_pos(1.0 - m00 + m11 - m22),
        sqrt_pos(1.0 - m00 - m11 + m22),
    ];
    let cand = [
        [q_abs[0] * q_abs[0], m21 - m12, m02 - m20, m10 - m01],
        [m21 - m12, q_abs[1] * q_abs[1], m10 + m01, m02 + m20],
        [m02 - m20, m10 + m01, q_abs[2] * q_abs[2], m12 + m21],
        [m10 - m01, m20 + m02, m21 + m12, q_abs[3] * q_abs[3]],
    ];
    let mut best = 0;
    for k in 1..4 {
        if q_abs[k] > q_abs[best] {
            best = k;
        }
    }
    let d = 2.0 * q_abs[best].max(0.1);
    standardize(cand[best].map(|v| v / d))
}

/// `q` or `−q`, whichever has w ≥ 0 (pytorch3d's `standardize_quaternion`).
#[inline]
pub fn standardize(q: Q) -> Q {
    if q[0] < 0.0 { q.map(|v| -v) } else { q }
}

/// `F.normalize(q)`: `q / max(‖q‖, 1e-12)`.
pub fn normalize4(q: [f64; 4]) -> [f64; 4] {
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
    q.map(|x| x / n)
}

/// pytorch3d `quaternion_to_matrix` (self-normalising through `2 / ‖q‖²`).
pub fn quat_to_mat(q: [f64; 4]) -> M3 {
    let [r, i, j, k] = q;
    let two_s = 2.0 / (r * r + i * i + j * j + k * k);
    [
        [1.0 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r)],
        [two_s * (i * j + k * r), 1.0 - two_s * (i * i + k * k), two_s * (j * k - i * r)],
        [two_s * (i * k - j * r), two_s * (j * k + i * r), 1.0 - two_s * (i * i + j * j)],
    ]
}

/// roma 1.8 `rotmat_to_unitquat` (Markley; scipy's `from_matrix`), returned as `w, x, y, z`.
pub fn mat_to_quat_roma(m: M3) -> [f64; 4] {
    let diag = [m[0][0], m[1][1], m[2][2]];
    let trace = diag[0] + diag[1] + diag[2];
    let decision = [diag[0], diag[1], diag[2], trace];
    // torch.argmax returns the first maximum.
    let mut choice = 0;
    for c in 1..4 {
        if decision[c] > decision[choice] {
            choice = c;
        }
    }
    let mut xyzw = [0.0; 4];
    if choice != 3 {
        let i = choice;
        let j = (i + 1) % 3;
        let k = (j + 1) % 3;
        xyzw[i] = 1.0 - trace + 2.0 * m[i][i];
        xyzw[j] = m[j][i] + m[i][j];
        xyzw[k] = m[k][i] + m[i][k];
        xyzw[3] = m[k][j] - m[j][k];
    } else {
        xyzw = [m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1.0 + trace];
    }
    let n = xyzw.iter().map(|x| x * x).sum::<f64>().sqrt();
    [xyzw[3] / n, xyzw[0] / n, xyzw[1] / n, xyzw[2] / n]
}

/// `a · b`.
pub fn matmul(a: M3, b: M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// `a · bᵀ`.
pub fn matmul_bt(a: M3, b: M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[j][k]).sum()))
}

/// `m v`.
#[inline]
pub fn mat_vec(m: &M3, v: V3) -> V3 {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

/// `mᵀ v`.
#[inline]
pub fn mat_t_vec(m: &M3, v: V3) -> V3 {
    [0, 1, 2].map(|c| m[0][c] * v[0] + m[1][c] * v[1] + m[2][c] * v[2])
}

/// `a bᵀ` added to `m` (the cotangent of `M` in `y = M b` given `g_y = a`).
#[inline]
pub fn add_outer(m: &mut M3, a: V3, b: V3) {
    for r in 0..3 {
        for c in 0..3 {
            m[r][c] += a[r] * b[c];
        }
    }
}

/// `v ↦ q v q*` for a unit quaternion, via its matrix.
#[inline]
pub fn rotate(q: Q, v: V3) -> V3 {
    mat_vec(&to_rotmat(q), v)
}

/// Vector part of a quaternion.
#[inline]
pub fn vec3(q: Q) -> V3 {
    [q[1], q[2], q[3]]
}

/// The pure quaternion `(0, v)`.
#[inline]
pub fn pure(v: V3) -> Q {
    [0.0, v[0], v[1], v[2]]
}

/// f32 to f64 quaternion.
#[inline]
pub fn q64(q: [f32; 4]) -> Q {
    q.map(f64::from)
}

/// f32 to f64 vector.
#[inline]
pub fn v64(v: [f32; 3]) -> V3 {
    v.map(f64::from)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn conventions_agree_up_to_sign_and_round_trip() {
        for q in [
            [0.3, -0.5, 0.7, 0.1],
            [-0.9, 0.1, 0.2, 0.3],
            [0.0, 1.0, 0.0, 0.0],
            [0.01, 0.2, -0.9, 0.3],
        ] {
            let q = normalize4(q);
            let m = quat_to_mat(q);
            let a = mat_to_quat_roma(m);
            let b = from_rotmat(&m);
            let s = if q[0] * a[0] + q[1] * a[1] + q[2] * a[2] + q[3] * a[3] < 0.0 {
                -1.0
            } else {
                1.0
            };
            assert!(close(&a, &q.map(|x| s * x), 1e-12), "{a:?} {q:?}");
            assert!(b[0] >= 0.0);
            let s = if q[0] < 0.0 { -1.0 } else { 1.0 };
            assert!(close(&b, &q.map(|x| s * x), 1e-12), "{b:?} {q:?}");
            // roma makes the largest-magnitude component positive.
            let big = (0..4).max_by(|&i, &j| a[i].abs().total_cmp(&a[j].abs())).unwrap_or(0);
            assert!(a[big] > 0.0);
        }
        let i = mul([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(i, [0.0, 0.0, 0.0, 1.0]);
    }

    /// A small deterministic generator for tests (splitmix64), uniform in [-1, 1).
    pub(crate) struct TestRng(pub u64);
    impl TestRng {
        pub(crate) fn next(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
        pub(crate) fn q(&mut self) -> Q {
            [self.next(), self.next(), self.next(), self.next()]
        }
        pub(crate) fn v(&mut self) -> V3 {
            [self.next(), self.next(), self.next()]
        }
    }

    fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol * (1.0 + y.abs()))
    }

    #[test]
    fn product_conjugate_and_matrix_agree() {
        let mut rng = TestRng(3);
        for _ in 0..20 {
            let (a, _) = normalize(rng.q());
            let (b, _) = normalize(rng.q());
            let v = rng.v();
            // (a ⊗ b) rotates as R(a) R(b); q ⊗ q* = 1; from_rotmat inverts to_rotmat.
            let ab = mul(a, b);
            let lhs = rotate(ab, v);
            let rhs = rotate(a, rotate(b, v));
            assert!(close(&lhs, &rhs, 1e-12));
            let v2 = vec3(mul(mul(a, pure(v)), conj(a)));
            assert!(close(&v2, &rotate(a, v), 1e-12));
            assert!(close(&mul(a, conj(a)), &[1.0, 0.0, 0.0, 0.0], 1e-12));
            assert!(close(&from_rotmat(&to_rotmat(a)), &standardize(a), 1e-12));
        }
    }

    #[test]
    fn vjps_match_finite_differences() {
        let mut rng = TestRng(11);
        let h = 1e-6;
        let mut worst = 0.0f64;
        for _ in 0..10 {
            let (a, b, gq) = (rng.q(), rng.q(), rng.q());
            let gm: M3 = [rng.v(), rng.v(), rng.v()];
            // mul
            let (ga, gb) = mul_vjp(a, b, gq);
            for k in 0..4 {
                let f = |d: f64, which: usize| {
                    let (mut x, mut y) = (a, b);
                    if which == 0 {
                        x[k] += d
                    } else {
                        y[k] += d
                    }
                    dot4(mul(x, y), gq)
                };
                worst = worst.max((ga[k] - (f(h, 0) - f(-h, 0)) / (2.0 * h)).abs());
                worst = worst.max((gb[k] - (f(h, 1) - f(-h, 1)) / (2.0 * h)).abs());
            }
            // normalize ∘ to_rotmat
            let (u, n) = normalize(a);
            let g = normalize_vjp(u, n, to_rotmat_vjp(u, &gm));
            for k in 0..4 {
                let f = |d: f64| {
                    let mut x = a;
                    x[k] += d;
                    let r = to_rotmat(normalize(x).0);
                    (0..3).map(|i| (0..3).map(|j| r[i][j] * gm[i][j]).sum::<f64>()).sum::<f64>()
                };
                worst = worst.max((g[k] - (f(h) - f(-h)) / (2.0 * h)).abs());
            }
        }
        assert!(worst < 1e-7, "max |analytic − FD| = {worst}");
    }
}
