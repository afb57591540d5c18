//! Rotation matrices and quaternions (`w, x, y, z`, Hamilton product) in f64, with the two
//! upstream matrix-to-quaternion conventions the importers must reproduce: roma's
//! (Markley's method, the largest-magnitude component made positive; Shape of Motion) and
//! pytorch3d ≥ 0.7.6's (largest candidate, then standardised to w ≥ 0; MoSca).

/// Row-major 3x3 matrix `m[i][j]`.
pub type Mat3 = [[f64; 3]; 3];

/// Hamilton product `p ⊗ q` of `w, x, y, z` quaternions.
pub fn qmul(p: [f64; 4], q: [f64; 4]) -> [f64; 4] {
    let [pw, px, py, pz] = p;
    let [qw, qx, qy, qz] = q;
    [
        pw * qw - (px * qx + py * qy + pz * qz),
        pw * qx + qw * px + (py * qz - pz * qy),
        pw * qy + qw * py + (pz * qx - px * qz),
        pw * qz + qw * pz + (px * qy - py * qx),
    ]
}

/// `F.normalize(q)`: `q / max(‖q‖, 1e-12)`.
pub fn normalize4(q: [f64; 4]) -> [f64; 4] {
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
    q.map(|x| x / n)
}

/// pytorch3d `quaternion_to_matrix` (self-normalising through `2 / ‖q‖²`).
pub fn quat_to_mat(q: [f64; 4]) -> Mat3 {
    let [r, i, j, k] = q;
    let two_s = 2.0 / (r * r + i * i + j * j + k * k);
    [
        [1.0 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r)],
        [two_s * (i * j + k * r), 1.0 - two_s * (i * i + k * k), two_s * (j * k - i * r)],
        [two_s * (i * k - j * r), two_s * (j * k + i * r), 1.0 - two_s * (i * i + j * j)],
    ]
}

/// roma 1.8 `rotmat_to_unitquat` (Markley; scipy's `from_matrix`), returned as `w, x, y, z`.
pub fn mat_to_quat_roma(m: Mat3) -> [f64; 4] {
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

/// pytorch3d v0.7.7 `matrix_to_quaternion`: the best-conditioned of four candidates,
/// standardised to w ≥ 0 (`w, x, y, z`, unit up to rounding).
pub fn mat_to_quat_pytorch3d(m: Mat3) -> [f64; 4] {
    let [[m00, m01, m02], [m10, m11, m12], [m20, m21, m22]] = m;
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
    for c in 1..4 {
        if q_abs[c] > q_abs[best] {
            best = c;
        }
    }
    let d = 2.0 * q_abs[best].max(0.1);
    let q = cand[best].map(|x| x / d);
    if q[0] < 0.0 { q.map(|x| -x) } else { q }
}

/// `a · b`.
pub fn matmul(a: Mat3, b: Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// `a · bᵀ`.
pub fn matmul_bt(a: Mat3, b: Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[j][k]).sum()))
}

/// `m · v`.
pub fn matvec(m: Mat3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| m[i][k] * v[k]).sum())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < tol)
    }

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
            let b = mat_to_quat_pytorch3d(m);
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
        let i = qmul([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]);
        assert_eq!(i, [0.0, 0.0, 0.0, 1.0]);
    }
}
