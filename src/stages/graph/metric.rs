//! The anisotropic uncertainty of the paper's Eq. 6 and the norms of Eqs. 7-8 built on it.

use glam::{DMat3, Mat3, Vec3};

/// World-to-camera rotation R_cw of the camera that renders each training frame `[T]`
/// (the model's own camera when it carries cameras, [`crate::model::Model::training_camera`]).
pub fn train_rotations(scene: &crate::scene::Scene, model: &crate::model::Model) -> Vec<DMat3> {
    scene.train_by_frame().iter().map(|c| model.training_camera(c).rotation()).collect()
}

/// The anisotropic uncertainty of Eq. 6: U_{i,t} = R_wc diag(r_x u, r_y u, r_z u) R_wcᵀ,
/// with R_wc = R_cwᵀ the camera-to-world rotation of frame t.
pub fn uncertainty_matrix(u: f64, r: [f64; 3], r_cw: DMat3) -> DMat3 {
    let r_wc = r_cw.transpose();
    r_wc * DMat3::from_diagonal(glam::DVec3::new(r[0] * u, r[1] * u, r[2] * u)) * r_wc.transpose()
}

/// How the norm ‖δ‖_M of Eqs. 7-8, M = U_{t,i} + U_{t,j}, reads its matrix.
///
/// The paper writes its anchor losses as ‖·‖_{U⁻¹} (Sec. 4.3, L^key and L^non-key), so in
/// its notation ‖x‖_M = √(xᵀ M x) and Eqs. 7-8, written ‖·‖_{(U_i + U_j)}, use the
/// uncertainty itself as the weight: `weight`, the paper profile's default. That reading
/// also fits the text: "the Mahalanobis metric up-weights directions of high uncertainty,
/// so edges are formed between nodes that are both spatially close and reliable", and
/// r_z = 0.01 (Eq. 6) discounts the unreliable depth axis. The textbook Mahalanobis
/// distance with M as a covariance, δᵀ M⁻¹ δ (`inverse`), does the opposite: it weights
/// depth errors ×100, and a key unseen at frame t (u = φ) contributes ≈ 0 there, so keys
/// that are rarely seen win Eq. 8's argmin.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum MetricForm {
    /// ‖δ‖² = δᵀ (U_i + U_j) δ = (u_i + u_j)·‖B_t δ‖², B_t = diag(r)^{1/2} R_cw (paper notation).
    Weight,
    /// ‖δ‖² = δᵀ (U_i + U_j)⁻¹ δ = ‖A_t δ‖² / (u_i + u_j), A_t = diag(r)^{-1/2} R_cw.
    Inverse,
}

impl MetricForm {
    /// The linear map of frame t that turns the metric into a scaled Euclidean one:
    /// [`weight_transform`] or [`metric_transform`].
    pub fn transform(self, r: [f64; 3], r_cw: DMat3) -> Mat3 {
        match self {
            MetricForm::Weight => weight_transform(r, r_cw),
            MetricForm::Inverse => metric_transform(r, r_cw),
        }
    }

    /// `x` scaled by the uncertainty factor `s` (of u_i + u_j, or of its square root):
    /// `x·s` for `weight`, `x/s` for `inverse`. Monotone non-decreasing in x ≥ 0, and in
    /// s > 0 for `weight` (non-increasing for `inverse`), also for the rounded floats.
    #[inline]
    pub fn scale(self, x: f32, s: f32) -> f32 {
        match self {
            MetricForm::Weight => x * s,
            MetricForm::Inverse => x / s,
        }
    }

    /// Of the smallest and largest u of a set of keys, the one that gives the smallest
    /// [`scale`](Self::scale) (a lower bound of every member's factor).
    #[inline]
    pub fn bound_u(self, u_min: f32, u_max: f32) -> f32 {
        match self {
            MetricForm::Weight => u_min,
            MetricForm::Inverse => u_max,
        }
    }
}

/// The linear map A_t = diag(r)^{-1/2} R_cw of the `inverse` form ([`MetricForm`]). Both
/// Gaussians are seen by the same camera at frame t, so
/// U_i + U_j = R_wc diag(r (u_i + u_j)) R_wcᵀ and `δᵀ (U_i + U_j)⁻¹ δ = ‖A_t δ‖² / (u_i + u_j)`.
pub fn metric_transform(r: [f64; 3], r_cw: DMat3) -> Mat3 {
    let s = glam::DVec3::new(1.0 / r[0].sqrt(), 1.0 / r[1].sqrt(), 1.0 / r[2].sqrt());
    (DMat3::from_diagonal(s) * r_cw).as_mat3()
}

/// The linear map B_t = diag(r)^{1/2} R_cw of the `weight` form ([`MetricForm`]):
/// `δᵀ (U_i + U_j) δ = (u_i + u_j)·‖B_t δ‖²` (same camera for both Gaussians at frame t).
pub fn weight_transform(r: [f64; 3], r_cw: DMat3) -> Mat3 {
    let s = glam::DVec3::new(r[0].sqrt(), r[1].sqrt(), r[2].sqrt());
    (DMat3::from_diagonal(s) * r_cw).as_mat3()
}

/// `A p` as an array.
pub fn apply(a: &Mat3, p: [f32; 3]) -> [f32; 3] {
    (*a * Vec3::from_array(p)).to_array()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metric_transform_matches_the_mahalanobis_distance_of_eq6() {
        let r_cw = DMat3::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.7);
        let r = [1.0, 1.0, 0.01];
        let (ui, uj) = (0.3, 1.7);
        let sum = uncertainty_matrix(ui, r, r_cw) + uncertainty_matrix(uj, r, r_cw);
        let d = glam::DVec3::new(0.2, -0.5, 0.9);
        let exact = d.dot(sum.inverse() * d);
        let a = metric_transform(r, r_cw);
        let q = a * d.as_vec3();
        let fast = q.length_squared() as f64 / (ui + uj);
        assert!((exact - fast).abs() < 1e-4 * exact, "{exact} vs {fast}");
    }

    #[test]
    fn weight_transform_matches_the_weighted_norm_of_eq6() {
        let r = [1.0, 1.0, 0.01];
        for (k, (ui, uj)) in [(0.3, 1.7), (1e-3, 2.0), (1e8, 0.05)].into_iter().enumerate() {
            let r_cw = DMat3::from_euler(glam::EulerRot::XYZ, 0.3 * k as f64, -1.1, 0.7);
            let sum = uncertainty_matrix(ui, r, r_cw) + uncertainty_matrix(uj, r, r_cw);
            let d = glam::DVec3::new(0.2, -0.5, 0.9);
            let exact = d.dot(sum * d);
            let q = MetricForm::Weight.transform(r, r_cw) * d.as_vec3();
            let fast = MetricForm::Weight.scale(q.length_squared(), (ui + uj) as f32) as f64;
            assert!((exact - fast).abs() < 1e-4 * exact, "{exact} vs {fast}");
            // The inverse form's twin, for the same δ and matrices.
            let exact_inv = d.dot(sum.inverse() * d);
            let q = MetricForm::Inverse.transform(r, r_cw) * d.as_vec3();
            let fast_inv = MetricForm::Inverse.scale(q.length_squared(), (ui + uj) as f32) as f64;
            assert!((exact_inv - fast_inv).abs() < 1e-4 * exact_inv, "{exact_inv} vs {fast_inv}");
        }
    }
}
