//! Quaternions `w, x, y, z` (scalar first, as the tables store them) and the
//! vector-Jacobian products (VJPs) the renderer's backward pass and the optimiser chain.

use glam::{Mat3, Vec3};

/// Rotation matrix of a unit quaternion `w, x, y, z`.
pub fn to_rotmat(q: [f32; 4]) -> Mat3 {
    let [w, x, y, z] = q;
    Mat3::from_cols(
        Vec3::new(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        Vec3::new(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        Vec3::new(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    )
}

/// VJP of [`to_rotmat`]: `dL/dq` (unit q) from `dL/dR`.
pub fn to_rotmat_vjp(q: [f32; 4], v_r: Mat3) -> [f32; 4] {
    rotmat_vjp!(q, |i: usize, j: usize| v_r.col(j)[i])
}

/// The VJP of the rotation matrix of a unit quaternion `q = [w, x, y, z]` (the formula's
/// polynomial): `dL/dq` from `v(i, j) = dL/dR[i][j]`. Written once for the f32
/// [`to_rotmat_vjp`] and the f64 [`super::quat64::to_rotmat_vjp`], whose matrices differ.
macro_rules! rotmat_vjp {
    ($q:expr, $v:expr) => {{
        let [w, x, y, z] = $q;
        let v = $v;
        [
            2.0 * (x * (v(2, 1) - v(1, 2)) + y * (v(0, 2) - v(2, 0)) + z * (v(1, 0) - v(0, 1))),
            2.0 * (-2.0 * x * (v(1, 1) + v(2, 2))
                + y * (v(1, 0) + v(0, 1))
                + z * (v(2, 0) + v(0, 2))
                + w * (v(2, 1) - v(1, 2))),
            2.0 * (x * (v(1, 0) + v(0, 1)) - 2.0 * y * (v(0, 0) + v(2, 2))
                + z * (v(2, 1) + v(1, 2))
                + w * (v(0, 2) - v(2, 0))),
            2.0 * (x * (v(2, 0) + v(0, 2)) + y * (v(2, 1) + v(1, 2))
                - 2.0 * z * (v(0, 0) + v(1, 1))
                + w * (v(1, 0) - v(0, 1))),
        ]
    }};
}
pub(crate) use rotmat_vjp;

/// The normalised quaternion and its norm, or `None` when it is zero or not finite.
pub fn normalize(q: [f32; 4]) -> Option<([f32; 4], f32)> {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(n.is_finite() && n > 1e-12) {
        return None;
    }
    Some((q.map(|v| v / n), n))
}

/// VJP of [`normalize`]: `dL/dq` of the raw quaternion from `dL/dq̂`, given the unit
/// quaternion `unit` = q̂ and the norm ‖q‖: `(v − (v·q̂) q̂) / ‖q‖`.
pub fn normalize_vjp(unit: [f32; 4], norm: f32, v_unit: [f32; 4]) -> [f32; 4] {
    let dot: f32 = (0..4).map(|k| v_unit[k] * unit[k]).sum();
    std::array::from_fn(|k| (v_unit[k] - dot * unit[k]) / norm)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_matrix_is_orthonormal_and_matches_glam() {
        let q = normalize([0.3, -0.5, 0.2, 0.7]).unwrap().0;
        let r = to_rotmat(q);
        let g = Mat3::from_quat(glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]));
        assert!(r.abs_diff_eq(g, 1e-6));
        assert!((r * r.transpose()).abs_diff_eq(Mat3::IDENTITY, 1e-6));
    }

    #[test]
    fn vjps_match_finite_differences() {
        let q = [0.3f32, -0.5, 0.2, 0.7];
        let (unit, norm) = normalize(q).unwrap();
        // L(q) = Σ G ⊙ R(normalize(q)) for a fixed G.
        let g = Mat3::from_cols_array(&[0.3, -0.2, 0.5, 0.1, 0.7, -0.4, -0.6, 0.2, 0.9]);
        let loss = |q: [f32; 4]| -> f64 {
            let r = to_rotmat(normalize(q).unwrap().0);
            (0..3).map(|j| r.col(j).dot(g.col(j)) as f64).sum()
        };
        let v = normalize_vjp(unit, norm, to_rotmat_vjp(unit, g));
        for k in 0..4 {
            let h = 1e-3;
            let (mut a, mut b) = (q, q);
            a[k] += h;
            b[k] -= h;
            let fd = (loss(a) - loss(b)) / (2.0 * h as f64);
            assert!((fd - v[k] as f64).abs() < 2e-3, "component {k}: {fd} vs {}", v[k]);
        }
    }
}
