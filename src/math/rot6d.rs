//! Continuous 6D rotations (Zhou et al. 2019) as Shape of Motion stores its motion bases:
//! the first two columns of a rotation matrix, orthonormalised by Gram-Schmidt on use
//! (`flow3d/transforms.py::cont_6d_to_rmat`), in f64.

/// `F.normalize`: `v / max(‖v‖, 1e-12)`.
fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

/// The rotation matrix (row-major `R[i][j]`) of 6D vector `a = [a1 | a2]`:
/// `x = normalize(a1)`, `y = normalize(a2 − (a2·x) x)`, `z = x × y`, `R = [x y z]` (columns).
pub fn to_rotmat(a: [f64; 6]) -> [[f64; 3]; 3] {
    let x = normalize([a[0], a[1], a[2]]);
    let y1 = [a[3], a[4], a[5]];
    let d = y1[0] * x[0] + y1[1] * x[1] + y1[2] * x[2];
    let y = normalize([y1[0] - d * x[0], y1[1] - d * x[1], y1[2] - d * x[2]]);
    let z = [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]];
    [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]]
}

/// The 6D vector of rotation matrix `r` (its first two columns): `[R00, R10, R20, R01, R11, R21]`.
pub fn from_rotmat(r: [[f64; 3]; 3]) -> [f64; 6] {
    [r[0][0], r[1][0], r[2][0], r[0][1], r[1][1], r[2][1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orthonormalises_and_round_trips() {
        let r = to_rotmat([2.0, 0.1, -0.3, 0.5, 1.5, 0.2]);
        for i in 0..3 {
            for j in 0..3 {
                let dot: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
                assert!((dot - f64::from(u8::from(i == j))).abs() < 1e-14);
            }
        }
        let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
            - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
        assert!((det - 1.0).abs() < 1e-14);
        let back = to_rotmat(from_rotmat(r));
        for (a, b) in back.iter().flatten().zip(r.iter().flatten()) {
            assert!((a - b).abs() < 1e-15, "{back:?} vs {r:?}");
        }
        assert_eq!(
            to_rotmat([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        );
    }
}
