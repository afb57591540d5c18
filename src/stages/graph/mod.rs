//! Shared machinery of the graph stages (`keynodes`, `edges`, `segment`, `bench graph`):
//! the paper/release [`Profile`], a seeded hash for reproducible random picks, the
//! in-memory [`Tracks`] (positions and uncertainties of the graph's Gaussians over all
//! frames) and the anisotropic uncertainty of the paper's Eq. 6.
//!
//! Memory: [`Tracks`] holds `N·T·(12 + 4 + 1)` bytes (positions, u, reliable flag); for
//! N = 200,000 Gaussians and T = 475 frames that is 1.6 GB, the largest array of the
//! graph stages (the edge search adds O(K·T) for K key nodes and O(N·k) edges).

pub mod search;
pub mod spectral;

use std::path::Path;

use glam::{DMat3, Mat3, Vec3};

use crate::model::Model;
use crate::tables::uncertainty::UncertaintyReader;

/// Which defaults a stage's unset parameters take (official-release.md, Sec. 11).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Deserialize,
    serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Profile {
    /// Follow arXiv 2510.12768 where it is specific.
    #[default]
    Paper,
    /// Reproduce the official MoSca-based code release.
    Release,
}

/// A count, or a fraction of a total written with `%` (`"1000"`, `"2%"`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(try_from = "String", into = "String")]
pub enum Amount {
    /// An absolute value (a count, or a length in world units).
    Value(f64),
    /// A fraction of the relevant total (stored as 0.02 for `2%`).
    Fraction(f64),
}

impl Amount {
    /// The amount given `total` (the count or length that a fraction refers to).
    pub fn of(self, total: f64) -> f64 {
        match self {
            Amount::Value(v) => v,
            Amount::Fraction(f) => f * total,
        }
    }
}

impl std::str::FromStr for Amount {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("'{s}' is not a non-negative number or percentage (e.g. 1000, 0.2, 2%)");
        let (num, pct) = match s.trim().strip_suffix('%') {
            Some(n) => (n, true),
            None => (s.trim(), false),
        };
        let v: f64 = num.trim().parse().map_err(|_| bad())?;
        if !(v.is_finite() && v >= 0.0) {
            return Err(bad());
        }
        Ok(if pct { Amount::Fraction(v / 100.0) } else { Amount::Value(v) })
    }
}

impl std::fmt::Display for Amount {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Amount::Value(v) => write!(f, "{v}"),
            Amount::Fraction(v) => write!(f, "{}%", v * 100.0),
        }
    }
}

impl TryFrom<String> for Amount {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<Amount> for String {
    fn from(a: Amount) -> String {
        a.to_string()
    }
}

/// splitmix64 finaliser: a well-mixed 64-bit hash of `x`.
pub fn mix(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// A reproducible random key of `(seed, stream, item)`: picking the item with the smallest
/// key is a uniform random pick that does not depend on iteration order or thread count.
pub fn rank_key(seed: u64, stream: u64, item: u64) -> u64 {
    mix(mix(mix(seed) ^ stream) ^ item)
}

/// A small seeded generator (splitmix64 stream) for k-means++ and synthetic data.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    /// A generator for `seed`.
    pub fn new(seed: u64) -> Self {
        Rng(mix(seed))
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix(self.0)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let a = self.uniform().max(1e-300);
        let b = self.uniform();
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

/// Positions and uncertainties of the graph's Gaussians over all frames, Gaussian-major.
#[derive(Debug, Clone, Default)]
pub struct Tracks {
    /// `gaussian_id` of each graph node `[N]` (the uncertainty table's order).
    pub ids: Vec<u32>,
    /// Number of frames T.
    pub num_frames: usize,
    /// World positions `[N, T]`: `positions[i * T + t]`.
    pub positions: Vec<[f32; 3]>,
    /// Scalar uncertainty u_{i,t} `[N, T]` (φ when unreliable).
    pub u: Vec<f32>,
    /// Whether u_{i,t} is a measured value (converged and seen, Eq. 5's 𝟙_{i,t} = 1) `[N, T]`.
    pub reliable: Vec<bool>,
}

impl Tracks {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Position of Gaussian `i` at frame `t`.
    pub fn pos(&self, i: usize, t: usize) -> [f32; 3] {
        self.positions[i * self.num_frames + t]
    }

    /// u of Gaussian `i` at frame `t`.
    pub fn u(&self, i: usize, t: usize) -> f32 {
        self.u[i * self.num_frames + t]
    }

    /// Whether Gaussian `i` is reliable (converged and seen) at frame `t`.
    pub fn reliable(&self, i: usize, t: usize) -> bool {
        self.reliable[i * self.num_frames + t]
    }

    /// Check that the arrays agree with N and T.
    pub fn check(&self) -> Result<(), String> {
        let nt = self.len() * self.num_frames;
        if self.positions.len() != nt || self.u.len() != nt || self.reliable.len() != nt {
            return Err(format!(
                "tracks of {} Gaussians x {} frames hold {} positions, {} u, {} flags",
                self.len(),
                self.num_frames,
                self.positions.len(),
                self.u.len(),
                self.reliable.len()
            ));
        }
        Ok(())
    }
}

/// Load the tracks of the Gaussians of `uncertainty_file` from `model`, frame by frame.
pub fn load_tracks(
    model: &Model,
    uncertainty_file: &Path,
    ctx: &crate::context::Context,
) -> anyhow::Result<Tracks> {
    let unc = UncertaintyReader::open(uncertainty_file)?;
    let nt = unc.num_frames();
    if nt != model.num_frames() {
        anyhow::bail!(
            "{}: {nt} frames, but the model {} has {}",
            uncertainty_file.display(),
            model.dir.display(),
            model.num_frames()
        );
    }
    if unc.ids().len() != model.gaussians.len() {
        anyhow::bail!(
            "{}: {} rows per frame, expected one per Gaussian of the model {} ({})",
            uncertainty_file.display(),
            unc.ids().len(),
            model.dir.display(),
            model.gaussians.len()
        );
    }
    let index: std::collections::HashMap<u32, usize> =
        model.gaussians.id.iter().enumerate().map(|(i, id)| (*id, i)).collect();
    let rows: Vec<usize> = unc
        .ids()
        .iter()
        .enumerate()
        .map(|(row, id)| {
            index.get(id).copied().ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: column 'gaussian_id', row {row}: Gaussian {id} is not in the model {}",
                    uncertainty_file.display(),
                    model.dir.display()
                )
            })
        })
        .collect::<anyhow::Result<_>>()?;
    let n = rows.len();
    let mut tracks = Tracks {
        ids: unc.ids().to_vec(),
        num_frames: nt,
        positions: vec![[0.0; 3]; n * nt],
        u: vec![0.0; n * nt],
        reliable: vec![false; n * nt],
    };
    let bar = ctx.progress(nt as u64, "load tracks");
    for t in 0..nt {
        let state = model.frame(t)?;
        let f = unc.frame(t)?;
        for (i, &row) in rows.iter().enumerate() {
            tracks.positions[i * nt + t] = state.position[row];
            tracks.u[i * nt + t] = f.u[i];
            tracks.reliable[i * nt + t] = f.converged[i] && f.n_pixels[i] > 0;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(tracks)
}

/// World-to-camera rotation R_cw of the training camera of each frame `[T]`.
pub fn train_rotations(scene: &crate::scene::Scene) -> Vec<DMat3> {
    scene.train_by_frame().iter().map(|c| c.rotation()).collect()
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

    /// An uncertainty table of another model's size is blamed itself, not the key nodes
    /// that a later check would find disagreeing with it.
    #[test]
    fn an_uncertainty_table_of_another_size_names_itself() {
        use crate::tables::uncertainty::{UncertaintyFrame, UncertaintyWriter};
        let dir = tempfile::tempdir().unwrap();
        let (_, model_dir) = crate::render::synthetic::write_demo_scene(dir.path(), 2).unwrap();
        let model = Model::load(&model_dir).unwrap();
        let ids = &model.gaussians.id[..10];
        let path = dir.path().join("uncertainty.parquet");
        let mut w = UncertaintyWriter::create(&path, ids, &Default::default()).unwrap();
        for t in 0..2 {
            w.write(&UncertaintyFrame {
                frame: t,
                sum_w2: vec![1.0; 10],
                sum_w: vec![1.0; 10],
                n_pixels: vec![1; 10],
                converged: vec![true; 10],
                u: vec![1.0; 10],
            })
            .unwrap();
        }
        w.finish().unwrap();
        let err = load_tracks(&model, &path, &crate::context::Context::quiet()).unwrap_err();
        assert_eq!(
            err.to_string(),
            format!(
                "{}: 10 rows per frame, expected one per Gaussian of the model {} (576)",
                path.display(),
                model_dir.display()
            )
        );
    }

    #[test]
    fn amount_parses_counts_and_percentages() {
        assert_eq!("1000".parse::<Amount>().unwrap(), Amount::Value(1000.0));
        assert_eq!("2%".parse::<Amount>().unwrap(), Amount::Fraction(0.02));
        assert_eq!("2%".parse::<Amount>().unwrap().of(50_000.0).round(), 1000.0);
        assert!("-1".parse::<Amount>().is_err());
        assert!("x%".parse::<Amount>().is_err());
        let s: String = Amount::Fraction(0.02).into();
        assert_eq!(s.parse::<Amount>().unwrap(), Amount::Fraction(0.02));
    }

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
