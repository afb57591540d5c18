//! Edge construction (paper Sec. 4.2, "Edge construction"; official-release.md Sec. 4).
//!
//! *Key → key.* Paper (UA-kNN, Eq. 7): for key i at its most reliable frame
//! t̂ = argmin_t u_{i,t}, the k keys j reliable at t̂ ("only among other low-uncertainty
//! key nodes") of lowest ‖p_i − p_j‖_{(U_{t̂,i} + U_{t̂,j})}, U from Eq. 6. The norm's form is
//! `--metric-form` ([`MetricForm`], whose doc gives the reasoning): `weight` (paper
//! profile), the paper's own notation ‖x‖_M = √(xᵀMx), i.e. (u_i + u_j)·‖B_t̂ δ‖² with
//! B_t = diag(r)^{1/2} R_cw since both Gaussians share frame t̂'s camera; or `inverse`,
//! δᵀ(U_i + U_j)⁻¹δ = ‖A_t̂ δ‖² / (u_i + u_j) with A_t = diag(r)^{-1/2} R_cw. Release: 120-NN by the largest distance over the
//! frames where both keys are confident (`minmax-distance`), or at t̂ among confident keys
//! (`max-contrib`), or by the time-averaged distance (`max-native`). Ablation (b): plain
//! Euclidean kNN at t̂ among all keys (`euclidean`).
//!
//! *Non-key → key.* Paper (Eq. 8): i is attached to
//! j = argmin_l Σ_t ‖p_{i,t} − p_{l,t}‖_{(U_{t,i} + U_{t,l})} (same form), summed over all
//! T frames as written: with `weight`, a frame where the key is unreliable (u = φ) adds a
//! large term, which is the paper's intent (attach to "the most reliable key node that
//! stays close to it over time"), so no restriction to reliable frames is needed; with
//! `inverse` such a frame adds ≈ 0. Then i is connected to E_j ∪ {j}.
//! Release: the 5 keys of lowest max_{t: key confident} ‖p_u(t) − p_k(t)‖.
//!
//! *Left-out non-keys.* Gaussians whose `key_nodes` role is `unlinked` or `culled` (the
//! release's non-key cap and minimum contribution, profile rows 33-35) get no edges.
//!
//! *Weights*, normalised over the edges leaving each Gaussian: key edges `uniform` (the
//! release's initial learned weights, 1/k) or `rigidity` (our choice for the paper's
//! unspecified w_ij: exp(−β·cv²) with cv the coefficient of variation of the pair's
//! distance over time, so pairs moving rigidly together weigh most); non-key edges
//! exp(−λ d²) at the non-key's t̂, clamped to [1e-10, 1e10] (release `cal_weight_edges2`
//! with θ = 1).
//!
//! All searches are exact (see [`super::graph::search`]); nothing of size T × N_nonkey ×
//! N_key is materialised. Memory: the tracks (`N·T·17` bytes, see [`super::graph`]), two
//! copies of the keys' `[K, T]` data, T kiddo trees of ≤ K points, the Eq. 8 key tree
//! (< K/2 nodes of 28·T bytes, and the keys again at 16·T bytes each), and the edges.

use std::path::PathBuf;

use glam::{DMat3, Mat3};
use rayon::prelude::*;

use super::graph::metric::{MetricForm, apply};
use super::graph::search::{self, KeyFrames};
use super::graph::tracks::Tracks;
use super::params::Profile;
use crate::context::Context;
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::key_nodes::{KeyNodes, Role};

/// Most keys in a leaf of the Eq. 8 key tree (4 and 8 time the same; 8 halves its memory).
const KEY_TREE_LEAF: usize = 8;

/// How key → key neighbours are chosen (profile row 26; ablation (b)).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum KeyEdgeMode {
    /// UA-kNN, Eq. 7 (paper).
    UaKnn,
    /// Euclidean kNN at t̂ among all keys (ablation (b), "w/o UA-kNN").
    Euclidean,
    /// Largest distance over co-confident frames (release, iPhone).
    MinmaxDistance,
    /// Euclidean kNN at t̂ among keys confident there (release, DAVIS).
    MaxContrib,
    /// Time-averaged distance (release option).
    MaxNative,
}

/// Weights of key → key edges (profile row 27).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum KeyEdgeWeights {
    /// exp(−β·cv²) of the pair distance's coefficient of variation over time.
    Rigidity,
    /// 1/k (the release's initial learned weights).
    Uniform,
}

/// How non-key Gaussians are attached to keys (profile row 30).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum NonkeyAssignMode {
    /// Eq. 8, then E_i = E_j ∪ {j} (paper).
    ArgminSumMahalanobis,
    /// The `nonkey-k` keys of lowest max distance over key-confident frames (release).
    KnnMaxDist,
}

/// Parameters of `usplat4d edges`; unset values take the profile's defaults.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct EdgeParams {
    /// Model directory (gaussians.parquet + trajectories.parquet).
    #[arg(long, value_name = "MODEL_DIR")]
    pub model: PathBuf,
    /// Directory holding uncertainty.parquet.
    #[arg(long, value_name = "DIR")]
    pub uncertainty: PathBuf,
    /// Directory holding key_nodes.parquet.
    #[arg(long, value_name = "DIR")]
    pub keynodes: PathBuf,
    /// Output directory (edges.parquet).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Scene directory: the training cameras' rotations for the anisotropic metric (Eq. 6);
    /// required by the paper's Mahalanobis modes unless r is isotropic.
    #[arg(long, value_name = "SCENE_DIR")]
    #[serde(default)]
    pub scene: Option<PathBuf>,
    /// Which defaults the unset parameters take.
    #[arg(long, value_enum, default_value_t = Profile::Paper, help_heading = "Method")]
    #[serde(default)]
    pub profile: Profile,
    /// Key → key mode [paper ua-knn, release minmax-distance].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub key_edge_mode: Option<KeyEdgeMode>,
    /// Neighbours per key [paper 8, release 120].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub key_knn_k: Option<usize>,
    /// Key edge weights [paper rigidity, release uniform].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub key_edge_weights: Option<KeyEdgeWeights>,
    /// β of the rigidity weights exp(−β·cv²) [50].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub rigidity_sharpness: Option<f64>,
    /// Non-key assignment [paper argmin-sum-mahalanobis, release knn-max-dist].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub nonkey_assign_mode: Option<NonkeyAssignMode>,
    /// Keys per non-key in `knn-max-dist` [5].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub nonkey_k: Option<usize>,
    /// λ of the non-key weights exp(−λ d²) [100].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub nonkey_weight_sharpness: Option<f64>,
    /// Form of the norm ‖δ‖_{(U_i + U_j)} of Eqs. 7-8: `weight` = √(δᵀ(U_i+U_j)δ), the
    /// paper's notation; `inverse` = √(δᵀ(U_i+U_j)⁻¹δ) [paper weight, release inverse
    /// (unused by its edges)].
    #[arg(long, value_enum, help_heading = "Method")]
    #[serde(default)]
    pub metric_form: Option<MetricForm>,
    /// Anisotropy r_x,r_y,r_z of Eq. 6 [paper 1,1,0.01; release 1,1,0.1 (unused by its
    /// edges)].
    #[arg(long, value_delimiter = ',', help_heading = "Method")]
    #[serde(default)]
    pub r_xyz: Option<Vec<f64>>,
    /// Confidence mask of the release modes: normalised contribution > c, i.e. u < 1/c [2].
    #[arg(long, help_heading = "Method")]
    #[serde(default)]
    pub contrib_threshold: Option<f32>,
}

/// Concrete settings of edge construction (recorded in the table's provenance).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct EdgeSettings {
    /// The profile the defaults came from.
    pub profile: Profile,
    /// Key → key mode.
    pub key_edge_mode: KeyEdgeMode,
    /// Neighbours per key.
    pub key_knn_k: usize,
    /// Key edge weights.
    pub key_edge_weights: KeyEdgeWeights,
    /// β of the rigidity weights.
    pub rigidity_sharpness: f64,
    /// Non-key assignment.
    pub nonkey_assign_mode: NonkeyAssignMode,
    /// Keys per non-key (`knn-max-dist`).
    pub nonkey_k: usize,
    /// λ of the non-key weights.
    pub nonkey_weight_sharpness: f64,
    /// Form of the norm of Eqs. 7-8.
    pub metric_form: MetricForm,
    /// Anisotropy of Eq. 6.
    pub r_xyz: [f64; 3],
    /// Release confidence mask threshold on the normalised contribution.
    pub contrib_threshold: f32,
}

impl EdgeSettings {
    /// The defaults of `profile` (official-release.md Sec. 11, rows 15, 25-34).
    pub fn defaults(profile: Profile) -> Self {
        let paper = profile == Profile::Paper;
        EdgeSettings {
            profile,
            key_edge_mode: if paper { KeyEdgeMode::UaKnn } else { KeyEdgeMode::MinmaxDistance },
            key_knn_k: if paper { 8 } else { 120 },
            key_edge_weights: if paper {
                KeyEdgeWeights::Rigidity
            } else {
                KeyEdgeWeights::Uniform
            },
            rigidity_sharpness: 50.0,
            nonkey_assign_mode: if paper {
                NonkeyAssignMode::ArgminSumMahalanobis
            } else {
                NonkeyAssignMode::KnnMaxDist
            },
            nonkey_k: 5,
            nonkey_weight_sharpness: 100.0,
            metric_form: if paper { MetricForm::Weight } else { MetricForm::Inverse },
            r_xyz: if paper { [1.0, 1.0, 0.01] } else { [1.0, 1.0, 0.1] },
            contrib_threshold: 2.0,
        }
    }

    /// Whether the settings use the anisotropic metric (and so need camera rotations).
    pub fn needs_rotations(&self) -> bool {
        let aniso = self.r_xyz[0] != self.r_xyz[1] || self.r_xyz[1] != self.r_xyz[2];
        aniso
            && (self.key_edge_mode == KeyEdgeMode::UaKnn
                || self.nonkey_assign_mode == NonkeyAssignMode::ArgminSumMahalanobis)
    }
}

impl EdgeParams {
    /// The profile's defaults with the overrides applied.
    pub fn resolve(&self) -> anyhow::Result<EdgeSettings> {
        let d = EdgeSettings::defaults(self.profile);
        let r_xyz = match &self.r_xyz {
            None => d.r_xyz,
            Some(v) if v.len() == 3 && v.iter().all(|x| x.is_finite() && *x > 0.0) => {
                [v[0], v[1], v[2]]
            }
            Some(v) => anyhow::bail!("r-xyz: expected three positive numbers, got {v:?}"),
        };
        let s = EdgeSettings {
            profile: self.profile,
            key_edge_mode: self.key_edge_mode.unwrap_or(d.key_edge_mode),
            key_knn_k: self.key_knn_k.unwrap_or(d.key_knn_k),
            key_edge_weights: self.key_edge_weights.unwrap_or(d.key_edge_weights),
            rigidity_sharpness: self.rigidity_sharpness.unwrap_or(d.rigidity_sharpness),
            nonkey_assign_mode: self.nonkey_assign_mode.unwrap_or(d.nonkey_assign_mode),
            nonkey_k: self.nonkey_k.unwrap_or(d.nonkey_k),
            nonkey_weight_sharpness: self
                .nonkey_weight_sharpness
                .unwrap_or(d.nonkey_weight_sharpness),
            metric_form: self.metric_form.unwrap_or(d.metric_form),
            r_xyz,
            contrib_threshold: self.contrib_threshold.unwrap_or(d.contrib_threshold),
        };
        if s.key_knn_k == 0 || s.nonkey_k == 0 {
            anyhow::bail!("key-knn-k and nonkey-k must be at least 1");
        }
        if s.contrib_threshold.is_nan() || s.contrib_threshold <= 0.0 {
            anyhow::bail!("contrib-threshold must be positive, got {}", s.contrib_threshold);
        }
        Ok(s)
    }
}

/// Errors of edge construction (inputs that disagree).
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum EdgeError {
    /// The key-node table does not list the tracks' Gaussians in order.
    #[error(
        "key_nodes: row {row} is Gaussian {found}, the uncertainty table has {expected} (run keynodes again)"
    )]
    KeyOrder {
        /// Row.
        row: usize,
        /// Id in the key-node table.
        found: u32,
        /// Id in the tracks.
        expected: u32,
    },
    /// The key-node table has a different number of rows.
    #[error("key_nodes has {found} rows, the uncertainty table {expected} Gaussians")]
    KeyCount {
        /// Rows of the key table.
        found: usize,
        /// Gaussians of the tracks.
        expected: usize,
    },
    /// Camera rotations are needed but missing or of the wrong count.
    #[error(
        "the anisotropic metric needs one training-camera rotation per frame ({expected}), got {found} (pass --scene)"
    )]
    Rotations {
        /// Rotations given.
        found: usize,
        /// Frames T.
        expected: usize,
    },
    /// A frame index of the key table is out of range.
    #[error("key_nodes: row {row} has t_hat {t_hat}, but there are {frames} frames")]
    Frame {
        /// Row.
        row: usize,
        /// The frame.
        t_hat: u32,
        /// T.
        frames: usize,
    },
}

/// Build the graph's edges from the tracks, the key nodes and (for the anisotropic metric)
/// the training cameras' rotations R_cw `[T]`. Deterministic whatever the thread count.
pub fn build(
    tracks: &Tracks,
    keys: &KeyNodes,
    rotations: &[DMat3],
    s: &EdgeSettings,
) -> Result<Edges, EdgeError> {
    let (n, nt) = (tracks.len(), tracks.num_frames);
    if keys.id.len() != n {
        return Err(EdgeError::KeyCount { found: keys.id.len(), expected: n });
    }
    if let Some(row) = (0..n).find(|&i| keys.id[i] != tracks.ids[i]) {
        return Err(EdgeError::KeyOrder { row, found: keys.id[row], expected: tracks.ids[row] });
    }
    if let Some(row) = (0..n).find(|&i| keys.t_hat[i] as usize >= nt.max(1)) {
        return Err(EdgeError::Frame { row, t_hat: keys.t_hat[row], frames: nt });
    }
    let mats: Vec<Mat3> = if s.needs_rotations() {
        if rotations.len() != nt {
            return Err(EdgeError::Rotations { found: rotations.len(), expected: nt });
        }
        rotations.iter().map(|r| s.metric_form.transform(s.r_xyz, *r)).collect()
    } else {
        let iso = s.metric_form.transform(s.r_xyz, DMat3::IDENTITY);
        vec![iso; nt]
    };
    let key_rows = keys.rows(Role::Key);
    // unlinked and culled non-keys get no edges
    let nonkey_rows = keys.rows(Role::Nonkey);
    let u_mask = 1.0 / s.contrib_threshold;
    let world = key_frames(
        tracks,
        &key_rows,
        |_, p| p,
        |tr, i, t| tr.u(i, t) < u_mask && tr.reliable(i, t),
    );
    let metric =
        key_frames(tracks, &key_rows, |t, p| apply(&mats[t], p), |tr, i, t| tr.reliable(i, t));

    let k = s.key_knn_k;
    let neighbours: Vec<Vec<(f32, u32)>> = match s.key_edge_mode {
        KeyEdgeMode::UaKnn | KeyEdgeMode::Euclidean | KeyEdgeMode::MaxContrib => {
            let (kf, form) = match s.key_edge_mode {
                KeyEdgeMode::UaKnn => (metric.clone(), Some(s.metric_form)),
                KeyEdgeMode::Euclidean => (
                    KeyFrames { eligible: vec![true; world.eligible.len()], ..world.clone() },
                    None,
                ),
                _ => (world.clone(), None),
            };
            let trees = search::frame_trees(&kf);
            (0..key_rows.len())
                .into_par_iter()
                .map(|a| {
                    let t = keys.t_hat[key_rows[a]] as usize;
                    let q = kf.q[a * nt + t];
                    let u = kf.u[a * nt + t];
                    search::knn_at_frame(&kf, &trees[t], q, u, t, Some(a as u32), k, form)
                })
                .collect()
        }
        KeyEdgeMode::MinmaxDistance => {
            (0..key_rows.len()).into_par_iter().map(|a| search::knn_minmax(&world, a, k)).collect()
        }
        KeyEdgeMode::MaxNative => {
            let all = KeyFrames { eligible: vec![true; world.eligible.len()], ..world.clone() };
            (0..key_rows.len()).into_par_iter().map(|a| search::knn_mean(&all, a, k)).collect()
        }
    };
    let positions = KeyFrames { eligible: vec![true; world.eligible.len()], ..world.clone() };
    let key_weights: Vec<Vec<f64>> = neighbours
        .par_iter()
        .enumerate()
        .map(|(a, nb)| match s.key_edge_weights {
            KeyEdgeWeights::Uniform => vec![1.0; nb.len()],
            KeyEdgeWeights::Rigidity => nb
                .iter()
                .map(|&(_, b)| {
                    (-s.rigidity_sharpness * distance_cv2(&positions, a, b as usize)).exp()
                })
                .collect(),
        })
        .collect();

    let nonkey_edges: Vec<Vec<(u32, f64)>> = match s.nonkey_assign_mode {
        NonkeyAssignMode::ArgminSumMahalanobis => {
            let trees = search::frame_trees(&metric);
            let tree = search::key_tree(&metric, KEY_TREE_LEAF, s.metric_form);
            nonkey_rows
                .par_iter()
                .map(|&i| {
                    let q: Vec<[f32; 3]> =
                        (0..nt).map(|t| apply(&mats[t], tracks.pos(i, t))).collect();
                    let u: Vec<f32> = (0..nt).map(|t| tracks.u(i, t)).collect();
                    let th = keys.t_hat[i] as usize;
                    let cand = trees[th].nearest(q[th], 2).0;
                    match search::argmin_sum(&metric, &tree, &q, &u, &cand) {
                        Some((_, j)) => {
                            let mut dst = vec![j];
                            dst.extend(neighbours[j as usize].iter().map(|c| c.1));
                            nonkey_weights(
                                tracks,
                                &positions,
                                i,
                                th,
                                &dst,
                                s.nonkey_weight_sharpness,
                            )
                        }
                        None => Vec::new(),
                    }
                })
                .collect()
        }
        NonkeyAssignMode::KnnMaxDist => {
            let tau: Vec<u32> = (0..key_rows.len())
                .map(|a| {
                    let th = keys.t_hat[key_rows[a]] as usize;
                    if world.eligible[a * nt + th] {
                        th as u32
                    } else {
                        (0..nt).find(|&t| world.eligible[a * nt + t]).map_or(u32::MAX, |t| t as u32)
                    }
                })
                .collect();
            let trees = search::frame_trees(&world);
            nonkey_rows
                .par_iter()
                .map(|&i| {
                    let p: Vec<[f32; 3]> = (0..nt).map(|t| tracks.pos(i, t)).collect();
                    let th = keys.t_hat[i] as usize;
                    let cand = trees[th].nearest(p[th], s.nonkey_k).0;
                    let dst: Vec<u32> = search::knn_max(&world, &tau, &p, s.nonkey_k, &cand)
                        .into_iter()
                        .map(|c| c.1)
                        .collect();
                    nonkey_weights(tracks, &positions, i, th, &dst, s.nonkey_weight_sharpness)
                })
                .collect()
        }
    };

    let mut edges = Edges::default();
    for (a, nb) in neighbours.iter().enumerate() {
        let total: f64 = key_weights[a].iter().sum();
        for (c, w) in nb.iter().zip(&key_weights[a]) {
            let w = if total > 0.0 { w / total } else { 1.0 / nb.len() as f64 };
            edges.push(
                tracks.ids[key_rows[a]],
                tracks.ids[key_rows[c.1 as usize]],
                EdgeKind::KeyKey,
                w as f32,
            );
        }
    }
    for (b, list) in nonkey_edges.iter().enumerate() {
        for &(dst, w) in list {
            edges.push(
                tracks.ids[nonkey_rows[b]],
                tracks.ids[key_rows[dst as usize]],
                EdgeKind::NonkeyKey,
                w as f32,
            );
        }
    }
    Ok(edges)
}

/// One key's `[T]` positions, u and eligibility.
type KeyColumns = (Vec<[f32; 3]>, Vec<f32>, Vec<bool>);

/// The keys' `[K, T]` data: positions mapped by `map(t, p)`, u, and `eligible(tracks, i, t)`.
fn key_frames(
    tracks: &Tracks,
    key_rows: &[usize],
    map: impl Fn(usize, [f32; 3]) -> [f32; 3] + Sync,
    eligible: impl Fn(&Tracks, usize, usize) -> bool + Sync,
) -> KeyFrames {
    let nt = tracks.num_frames;
    let per_key: Vec<KeyColumns> = key_rows
        .par_iter()
        .map(|&i| {
            (
                (0..nt).map(|t| map(t, tracks.pos(i, t))).collect(),
                (0..nt).map(|t| tracks.u(i, t)).collect(),
                (0..nt).map(|t| eligible(tracks, i, t)).collect(),
            )
        })
        .collect();
    let mut kf = KeyFrames { num_keys: key_rows.len(), num_frames: nt, ..Default::default() };
    for (q, u, e) in per_key {
        kf.q.extend(q);
        kf.u.extend(u);
        kf.eligible.extend(e);
    }
    kf
}

/// Squared coefficient of variation over time of the distance between keys `a` and `b`.
fn distance_cv2(kf: &KeyFrames, a: usize, b: usize) -> f64 {
    let nt = kf.num_frames;
    let d: Vec<f64> = (0..nt)
        .map(|t| (search::dist2(kf.q[a * nt + t], kf.q[b * nt + t]) as f64).sqrt())
        .collect();
    let mean = d.iter().sum::<f64>() / nt.max(1) as f64;
    let var = d.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / nt.max(1) as f64;
    if mean > 0.0 { var / (mean * mean) } else { 0.0 }
}

/// Normalised non-key weights exp(−λ d²), d the distance at the non-key's frame `t`,
/// clamped to [1e-10, 1e10] before normalising (release `cal_weight_edges2`, θ = 1).
fn nonkey_weights(
    tracks: &Tracks,
    keys: &KeyFrames,
    i: usize,
    t: usize,
    dst: &[u32],
    lambda: f64,
) -> Vec<(u32, f64)> {
    let p = tracks.pos(i, t);
    let w: Vec<f64> = dst
        .iter()
        .map(|&j| {
            (-lambda * search::dist2(p, keys.q[j as usize * keys.num_frames + t]) as f64)
                .exp()
                .clamp(1e-10, 1e10)
        })
        .collect();
    let total: f64 = w.iter().sum();
    dst.iter().zip(w).map(|(&j, w)| (j, w / total)).collect()
}

/// `usplat4d edges`: read the model, uncertainty and key nodes (and the scene's cameras
/// for the anisotropic metric), build, write `OUT/edges.parquet`.
pub fn run(p: &EdgeParams, ctx: &Context) -> anyhow::Result<()> {
    use crate::tables::Table;
    let _span = tracing::info_span!("edges").entered();
    let settings = p.resolve()?;
    let model = crate::model::Model::load(&p.model)?;
    let unc = p.uncertainty.join(crate::tables::uncertainty::UncertaintyTable::file_name());
    let tracks = super::graph::tracks::load_tracks(&model, &unc, ctx)?;
    let key_path = p.keynodes.join(crate::tables::key_nodes::KeyNodesTable::file_name());
    let keys = crate::tables::key_nodes::read(&key_path)?;
    let rotations = match (&p.scene, settings.needs_rotations()) {
        (Some(dir), true) => {
            super::graph::metric::train_rotations(&crate::scene::Scene::load(dir)?)
        }
        (None, true) => anyhow::bail!(
            "edges: the {:?} profile's anisotropic metric (r-xyz {:?}) needs the training cameras: pass --scene",
            settings.profile,
            settings.r_xyz
        ),
        _ => Vec::new(),
    };
    let edges = build(&tracks, &keys, &rotations, &settings)
        .map_err(|e| anyhow::anyhow!("{}: {e}", key_path.display()))?;
    ctx.info(format!(
        "edges: {} edges ({} keys, {} Gaussians)",
        edges.len(),
        keys.num_keys(),
        tracks.len()
    ));
    let prov = crate::tables::Provenance::new(
        "edges",
        &serde_json::json!({ "params": p, "resolved": settings }),
    );
    crate::tables::edges::write(
        &p.out.join(crate::tables::edges::EdgesTable::file_name()),
        &edges,
        &prov,
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::graph::search::{argmin_sum_brute, knn_max_brute};
    use crate::stages::graph::tracks::synthetic_tracks;
    use crate::stages::keynodes::{KeynodeSettings, select};

    fn setup(profile: Profile) -> (Tracks, Vec<DMat3>, KeyNodes) {
        let (tracks, rotations, _) = synthetic_tracks(1500, 16, 3, 9);
        let mut ks = KeynodeSettings::defaults(profile);
        ks.voxel_size =
            crate::stages::keynodes::VoxelSize::Fixed(crate::stages::params::Amount::Value(0.4));
        ks.candidates_per_frame = crate::stages::params::Amount::Value(300.0);
        ks.spt_u_max = f32::INFINITY;
        let keys = select(&tracks, &ks);
        assert!(keys.num_keys() > 20, "{} keys", keys.num_keys());
        (tracks, rotations, keys)
    }

    #[test]
    fn output_does_not_depend_on_the_thread_count() {
        for profile in [Profile::Paper, Profile::Release] {
            let (tracks, rotations, keys) = setup(profile);
            let s = EdgeSettings { contrib_threshold: 1.0, ..EdgeSettings::defaults(profile) };
            let run = |n: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap();
                let e = pool.install(|| build(&tracks, &keys, &rotations, &s)).unwrap();
                let dir = tempfile::tempdir().unwrap();
                let path = dir.path().join("edges.parquet");
                crate::tables::edges::write(
                    &path,
                    &e,
                    &crate::tables::Provenance::new("edges", &s),
                )
                .unwrap();
                std::fs::read(path).unwrap()
            };
            assert_eq!(run(1), run(2), "{profile:?}");
        }
    }

    #[test]
    fn paper_nonkeys_attach_to_the_brute_force_argmin_and_its_neighbours() {
        let (tracks, rotations, keys) = setup(Profile::Paper);
        for form in [MetricForm::Weight, MetricForm::Inverse] {
            let s = EdgeSettings { metric_form: form, ..EdgeSettings::defaults(Profile::Paper) };
            let e = build(&tracks, &keys, &rotations, &s).unwrap();
            let nt = tracks.num_frames;
            let key_rows = keys.rows(Role::Key);
            let mats: Vec<Mat3> = rotations.iter().map(|r| form.transform(s.r_xyz, *r)).collect();
            let kf = key_frames(
                &tracks,
                &key_rows,
                |t, p| apply(&mats[t], p),
                |tr, i, t| tr.reliable(i, t),
            );
            for nonkey in keys.rows(Role::Nonkey).into_iter().step_by(97).take(8) {
                let q: Vec<[f32; 3]> =
                    (0..nt).map(|t| apply(&mats[t], tracks.pos(nonkey, t))).collect();
                let u: Vec<f32> = (0..nt).map(|t| tracks.u(nonkey, t)).collect();
                let j = argmin_sum_brute(&kf, &q, &u, form).unwrap().1 as usize;
                let j = tracks.ids[key_rows[j]];
                let out: Vec<u32> = (0..e.len())
                    .filter(|&k| e.src[k] == tracks.ids[nonkey])
                    .map(|k| e.dst[k])
                    .collect();
                let nbrs: Vec<u32> = (0..e.len())
                    .filter(|&k| e.src[k] == j && e.kind[k] == EdgeKind::KeyKey)
                    .map(|k| e.dst[k])
                    .collect();
                assert_eq!(out[0], j, "{form:?}");
                assert_eq!(out[1..], nbrs[..], "{form:?}");
                assert_eq!(nbrs.len(), s.key_knn_k);
                let total: f32 = (0..e.len())
                    .filter(|&k| e.src[k] == tracks.ids[nonkey])
                    .map(|k| e.weight[k])
                    .sum();
                assert!((total - 1.0).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn release_nonkeys_take_the_five_lowest_max_distances() {
        let (tracks, rotations, keys) = setup(Profile::Release);
        let s = EdgeSettings { contrib_threshold: 1.0, ..EdgeSettings::defaults(Profile::Release) };
        let e = build(&tracks, &keys, &rotations, &s).unwrap();
        let nt = tracks.num_frames;
        let key_rows = keys.rows(Role::Key);
        let kf = key_frames(
            &tracks,
            &key_rows,
            |_, p| p,
            |tr, i, t| tr.reliable(i, t) && tr.u(i, t) < 1.0,
        );
        for nonkey in keys.rows(Role::Nonkey).into_iter().take(20) {
            let p: Vec<[f32; 3]> = (0..nt).map(|t| tracks.pos(nonkey, t)).collect();
            let want: Vec<u32> = knn_max_brute(&kf, &p, 5)
                .iter()
                .map(|c| tracks.ids[key_rows[c.1 as usize]])
                .collect();
            let got: Vec<u32> = (0..e.len())
                .filter(|&k| e.src[k] == tracks.ids[nonkey])
                .map(|k| e.dst[k])
                .collect();
            assert_eq!(got, want);
        }
        let per_key =
            (0..e.len()).filter(|&k| e.kind[k] == EdgeKind::KeyKey && e.src[k] == e.src[0]).count();
        assert_eq!(per_key, s.key_knn_k.min(keys.num_keys() - 1));
    }

    #[test]
    fn profiles_and_overrides() {
        let p = EdgeSettings::defaults(Profile::Paper);
        let r = EdgeSettings::defaults(Profile::Release);
        assert_eq!((p.key_knn_k, r.key_knn_k), (8, 120));
        assert_eq!(
            (p.key_edge_mode, r.key_edge_mode),
            (KeyEdgeMode::UaKnn, KeyEdgeMode::MinmaxDistance)
        );
        assert!(p.needs_rotations() && !r.needs_rotations());
        assert_eq!((p.metric_form, r.metric_form), (MetricForm::Weight, MetricForm::Inverse));
        let yaml = "model: m\nuncertainty: u\nkeynodes: k\nout: o\nkey-edge-mode: euclidean\nr-xyz: [1, 1, 0.5]\nmetric-form: inverse\n";
        let o: EdgeParams = serde_saphyr::from_str(yaml).unwrap();
        let s = o.resolve().unwrap();
        assert_eq!((s.key_edge_mode, s.r_xyz), (KeyEdgeMode::Euclidean, [1.0, 1.0, 0.5]));
        assert_eq!(s.metric_form, MetricForm::Inverse);
        let bad: EdgeParams = serde_saphyr::from_str(
            "model: m\nuncertainty: u\nkeynodes: k\nout: o\nr-xyz: [1, 0]\n",
        )
        .unwrap();
        assert_eq!(
            bad.resolve().unwrap_err().to_string(),
            "r-xyz: expected three positive numbers, got [1.0, 0.0]"
        );
        assert!(
            serde_saphyr::from_str::<EdgeParams>(
                "model: m\nuncertainty: u\nkeynodes: k\nout: o\nk: 3\n"
            )
            .is_err()
        );
    }
}
