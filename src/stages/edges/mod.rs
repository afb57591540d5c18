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
//! A key with fewer than k qualifying neighbours is filled by `key-knn-fill`: paper
//! `nearest` (the nearest other keys at t̂ in the same metric without the reliability
//! condition; release modes without t̂: time-averaged distance), so no key is left without
//! neighbours (min(k, K − 1) each); release `first-keys`, the release's own padding (its
//! never-co-confident pairs at +∞ come out of its top-k in key order), without the
//! self-loops its "drop self" step leaves on such rows.
//!
//! *Scale* (`scale-normalise`, paper profile): reliable u are divided by the keys' median
//! reliable u before Eqs. 7-8 (φ unchanged) and the non-key weight distances by the graph's
//! bounding-box diagonal, so scene scale and image resolution (u ∝ 1/pixels²) do not change
//! the graph; the release works in raw units, as its code does.
//!
//! *Non-key → key.* Paper (Eq. 8): i is attached to
//! j = argmin_l Σ_t ‖p_{i,t} − p_{l,t}‖_{(U_{t,i} + U_{t,l})} (same form), summed over all
//! T frames as written: with `weight`, a frame where the key is unreliable (u = φ) adds a
//! large term, which is the paper's intent (attach to "the most reliable key node that
//! stays close to it over time"), so no restriction to reliable frames is needed; with
//! `inverse` such a frame adds ≈ 0. Then i is connected to E_j ∪ {j}.
//! Release: the 5 keys of lowest max_{t: key confident} ‖p_u(t) − p_k(t)‖.
//!
//! *Graph scope.* Only the Gaussians in `graph-scope` (dynamic by default, issue 15 item 1)
//! are keys, non-keys or neighbours; the others get no edges.
//!
//! *Left-out non-keys.* Gaussians whose `key_nodes` role is `unlinked` or `culled` (the
//! release's non-key cap and minimum contribution, profile rows 33-35) get no edges.
//!
//! *Weights*, normalised over the edges leaving each Gaussian: key edges `uniform` (both
//! profiles: the release's initial learned weights, 1/k, which the optimiser learns; the
//! paper leaves w_ij unspecified) or `rigidity` (an option: exp(−β·cv²) with cv the
//! coefficient of variation of the pair's distance over time); non-key edges
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
use super::graph::search::{self, FrameQuery, KeyFrames};
use super::graph::tracks::{
    GRAPH_SCOPE, GraphInputs, GraphScope, ScopedTracks, Tracks, bbox_diagonal,
};
use super::params::check;
use crate::context::Context;
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::key_nodes::{KeyNodes, Role};

/// Most keys in a leaf of the Eq. 8 key tree (4 and 8 time the same; 8 halves its memory).
const KEY_TREE_LEAF: usize = 8;

/// How key → key neighbours are chosen (profile row 26; ablation (b)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
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
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeyEdgeWeights {
    /// exp(−β·cv²) of the pair distance's coefficient of variation over time.
    Rigidity,
    /// 1/k (the release's initial learned weights).
    Uniform,
}

/// What a key with fewer than k qualifying neighbours (no co-confident frame, too few keys
/// reliable at its t̂) is given to fill its k (issue 15 item 8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeyKnnFill {
    /// The nearest other keys at t̂ in the mode's own metric, the reliability condition
    /// dropped (release modes without a t̂: the time-averaged distance).
    Nearest,
    /// The release's padding: never-co-confident pairs sit at +∞, which its top-k returns
    /// in key order, so the first keys in key order; without the release's self-loops
    /// (a row of +∞ loses a real neighbour to its "drop self" step there).
    FirstKeys,
    /// No fill: such a key keeps fewer neighbours, possibly none.
    None,
}

/// How non-key Gaussians are attached to keys (profile row 30).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum NonkeyAssignMode {
    /// Eq. 8, then E_i = E_j ∪ {j} (paper).
    ArgminSumMahalanobis,
    /// The `nonkey-k` keys of lowest max distance over key-confident frames (release).
    KnnMaxDist,
}

crate::stage_params! {
    /// Parameters of `usplat4d edges`; unset values take the profile's defaults.
    pub struct EdgeParams;
    /// Concrete settings of edge construction (recorded in the table's provenance).
    pub struct EdgeSettings;
    inputs {
        /// The model and its uncertainty table.
        #[command(flatten)]
        #[serde(flatten)]
        graph: GraphInputs,
        /// Directory holding key_nodes.parquet.
        #[arg(long, value_name = "DIR")]
        keynodes: PathBuf,
        /// Output directory (edges.parquet).
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
        /// Scene directory: the training cameras' rotations for the anisotropic metric (Eq. 6);
        /// required by the paper's Mahalanobis modes unless r is isotropic.
        #[arg(long, value_name = "SCENE_DIR")]
        scene: Option<PathBuf>,
    }
    params {
        heading "Method" {
            graph_scope: GraphScope => GraphScope { shared GRAPH_SCOPE },
            /// Key → key mode (ua-knn, euclidean, minmax-distance, max-contrib, max-native).
            key_edge_mode: KeyEdgeMode => KeyEdgeMode [check::choice]
                { paper "ua-knn", release "minmax-distance", row "26" },
            /// Neighbours per key.
            key_knn_k: usize => usize [check::count] { paper "8", release "120", row "25" },
            /// Fill of keys with fewer than k qualifying neighbours (nearest, first-keys, none).
            key_knn_fill: KeyKnnFill => KeyKnnFill [check::choice]
                { paper "nearest", release "first-keys", row "25" },
            /// Key edge weights (rigidity, uniform).
            key_edge_weights: KeyEdgeWeights => KeyEdgeWeights [check::choice]
                { paper "uniform", release "uniform", row "27" },
            /// β of the rigidity weights exp(−β·cv²).
            rigidity_sharpness: f64 => f64 [check::parsed] { paper "50", release "50" },
            /// Non-key assignment (argmin-sum-mahalanobis, knn-max-dist).
            nonkey_assign_mode: NonkeyAssignMode => NonkeyAssignMode [check::choice]
                { paper "argmin-sum-mahalanobis", release "knn-max-dist", row "30" },
            /// Keys per non-key in `knn-max-dist`.
            nonkey_k: usize => usize [check::count] { paper "5", release "5", row "31" },
            /// λ of the non-key weights exp(−λ d²).
            nonkey_weight_sharpness: f64 => f64 [check::parsed]
                { paper "100", release "100", row "32" },
            /// Scale normalisation (paper App. "Adaptation": unify the spatial volume, normalise
            /// the thresholds): u of Eqs. 7-8 divided by the keys' median reliable u, and the
            /// distances of the non-key weights by the graph's bounding-box diagonal (over all
            /// frames), so that scene scale and image resolution do not change the graph.
            scale_normalise: bool => bool [check::parsed]
                { paper "true", release "false", row "32" },
            /// Form of the norm ‖δ‖_{(U_i + U_j)} of Eqs. 7-8: `weight` = √(δᵀ(U_i+U_j)δ), the
            /// paper's notation; `inverse` = √(δᵀ(U_i+U_j)⁻¹δ) (unused by the release's edges).
            metric_form: MetricForm => MetricForm [check::choice]
                { paper "weight", release "inverse", row "16" },
            /// Anisotropy r_x,r_y,r_z of Eq. 6 (unused by the release's edges).
            r_xyz: [f64; 3] => [f64; 3] [check::triple]
                { paper "1,1,0.01", release "1,1,0.1", row "15" },
            /// Confidence mask of the release modes: normalised contribution > c, i.e. u < 1/c.
            contrib_threshold: f32 => f32 [check::positive] { paper "2", release "2", row "14" },
        }
    }
    copied {}
}

impl EdgeSettings {
    /// Whether the settings use the anisotropic metric (and so need camera rotations).
    pub fn needs_rotations(&self) -> bool {
        let aniso = self.r_xyz[0] != self.r_xyz[1] || self.r_xyz[1] != self.r_xyz[2];
        aniso
            && (self.key_edge_mode == KeyEdgeMode::UaKnn
                || self.nonkey_assign_mode == NonkeyAssignMode::ArgminSumMahalanobis)
    }
}

/// Key of the edges table's metadata holding what the optimiser needs besides the edges
/// ([`graph_metadata`]), so that it does not depend on the provenance.
pub const GRAPH_KEY: &str = "usplat4d.graph";

/// The graph's settings the optimiser needs, as stored under [`GRAPH_KEY`]: r_xyz and the
/// metric form of Eq. 6-8, the non-key weight sharpness λ and the length its distances are
/// measured in (the graph's bounding-box diagonal with `scale-normalise`, else 1), the
/// key-edge start weights, the graph scope, and where the non-keys' DQB source poses come
/// from (their pose at t̂, `key_nodes.t_hat`, in the model).
pub fn graph_metadata(s: &EdgeSettings, tracks: &Tracks) -> serde_json::Value {
    let diag = bbox_diagonal(&tracks.positions);
    let unit = if s.scale_normalise && diag > 0.0 { diag } else { 1.0 };
    serde_json::json!({
        "r-xyz": s.r_xyz,
        "metric-form": s.metric_form,
        "nonkey-weight-sharpness": s.nonkey_weight_sharpness,
        "nonkey-distance-unit": unit,
        "key-edge-weights": s.key_edge_weights,
        "graph-scope": s.graph_scope,
        "source-poses": "model pose at key_nodes.t_hat",
    })
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
    build_with_report(tracks, keys, rotations, s).map(|r| r.0)
}

/// [`build`], with the number of keys that had fewer than min(k, K − 1) qualifying
/// neighbours, and of those with none (before `key-knn-fill`).
pub fn build_with_report(
    tracks: &Tracks,
    keys: &KeyNodes,
    rotations: &[DMat3],
    s: &EdgeSettings,
) -> Result<(Edges, [usize; 2]), EdgeError> {
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
    let mut metric =
        key_frames(tracks, &key_rows, |t, p| apply(&mats[t], p), |tr, i, t| tr.reliable(i, t));
    // scale normalisation: reliable u relative to the keys' median, distances of the non-key
    // weights relative to the graph's extent (u = φ stays φ)
    let (u_norm, lambda) = if s.scale_normalise {
        let mut reliable: Vec<f32> =
            metric.u.iter().zip(&metric.eligible).filter(|(_, e)| **e).map(|(u, _)| *u).collect();
        let median = crate::util::stats::quantile(&mut reliable, 0.5);
        let u_norm = if median > 0.0 && median.is_finite() { 1.0 / median } else { 1.0 };
        for (u, e) in metric.u.iter_mut().zip(&metric.eligible) {
            if *e {
                *u *= u_norm;
            }
        }
        let diag = bbox_diagonal(&tracks.positions);
        // graph_metadata records the same unit
        let scale = if diag > 0.0 { 1.0 / (diag * diag) } else { 1.0 };
        (u_norm, s.nonkey_weight_sharpness * scale)
    } else {
        (1.0, s.nonkey_weight_sharpness)
    };
    let query_u = |i: usize, t: usize| {
        if tracks.reliable(i, t) { tracks.u(i, t) * u_norm } else { tracks.u(i, t) }
    };

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
                    let query = FrameQuery { q, u, t, exclude: Some(a as u32), k, form };
                    search::knn_at_frame(&kf, &trees[t], &query)
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
    let all_metric = KeyFrames { eligible: vec![true; metric.eligible.len()], ..metric.clone() };
    let positions = KeyFrames { eligible: vec![true; world.eligible.len()], ..world.clone() };
    let want = k.min(key_rows.len().saturating_sub(1));
    let short = neighbours.iter().filter(|nb| nb.len() < want).count();
    let isolated = neighbours.iter().filter(|nb| nb.is_empty()).count();
    let neighbours: Vec<Vec<(f32, u32)>> = neighbours
        .into_par_iter()
        .enumerate()
        .map(|(a, mut nb)| {
            if nb.len() >= want || s.key_knn_fill == KeyKnnFill::None {
                return nb;
            }
            let t = keys.t_hat[key_rows[a]] as usize;
            let others: Vec<(f32, u32)> = match (s.key_knn_fill, s.key_edge_mode) {
                (KeyKnnFill::FirstKeys, _) | (KeyKnnFill::None, _) => (0..key_rows.len() as u32)
                    .filter(|&l| l != a as u32)
                    .map(|l| (f32::INFINITY, l))
                    .collect(),
                (KeyKnnFill::Nearest, KeyEdgeMode::UaKnn) => {
                    let (q, u) = (all_metric.q[a * nt + t], all_metric.u[a * nt + t]);
                    let form = Some(s.metric_form);
                    let query = FrameQuery { q, u, t, exclude: Some(a as u32), k: want, form };
                    search::knn_at_frame_brute(&all_metric, &query)
                }
                (KeyKnnFill::Nearest, KeyEdgeMode::Euclidean | KeyEdgeMode::MaxContrib) => {
                    let q = positions.q[a * nt + t];
                    let query =
                        FrameQuery { q, u: 0.0, t, exclude: Some(a as u32), k: want, form: None };
                    search::knn_at_frame_brute(&positions, &query)
                }
                (KeyKnnFill::Nearest, _) => search::knn_mean(&positions, a, want),
            };
            for c in others {
                if nb.len() >= want {
                    break;
                }
                if !nb.iter().any(|b| b.1 == c.1) {
                    nb.push(c);
                }
            }
            nb
        })
        .collect();
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
                    let u: Vec<f32> = (0..nt).map(|t| query_u(i, t)).collect();
                    let th = keys.t_hat[i] as usize;
                    let cand = trees[th].nearest(q[th], 2).0;
                    match search::argmin_sum(&metric, &tree, &q, &u, &cand) {
                        Some((_, j)) => {
                            let mut dst = vec![j];
                            dst.extend(neighbours[j as usize].iter().map(|c| c.1));
                            nonkey_weights(tracks, &positions, i, th, &dst, lambda)
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
                    nonkey_weights(tracks, &positions, i, th, &dst, lambda)
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
    Ok((edges, [short, isolated]))
}

/// The rows of the key-node table `keys` (one per Gaussian of the uncertainty table) of the
/// in-scope Gaussians of `scoped`, in order.
fn keys_in_scope(keys: &KeyNodes, scoped: &ScopedTracks) -> Result<KeyNodes, EdgeError> {
    let ids = &scoped.table_ids;
    if keys.id.len() != ids.len() {
        return Err(EdgeError::KeyCount { found: keys.id.len(), expected: ids.len() });
    }
    if let Some(row) = (0..ids.len()).find(|&i| keys.id[i] != ids[i]) {
        return Err(EdgeError::KeyOrder { row, found: keys.id[row], expected: ids[row] });
    }
    let r = &scoped.table_rows;
    Ok(KeyNodes {
        id: r.iter().map(|&i| keys.id[i]).collect(),
        role: r.iter().map(|&i| keys.role[i]).collect(),
        t_hat: r.iter().map(|&i| keys.t_hat[i]).collect(),
        significant_period: r.iter().map(|&i| keys.significant_period[i]).collect(),
    })
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
    let (model, scoped) = p.graph.load(settings.graph_scope, ctx)?;
    let tracks = &scoped.tracks;
    let key_path = p.keynodes.join(crate::tables::key_nodes::KeyNodesTable::file_name());
    let keys = keys_in_scope(&crate::tables::key_nodes::read(&key_path)?, &scoped)
        .map_err(|e| anyhow::anyhow!("{}: {e}", key_path.display()))?;
    let rotations = match (&p.scene, settings.needs_rotations()) {
        (Some(dir), true) => {
            super::graph::metric::train_rotations(&crate::scene::Scene::load(dir)?, &model)
        }
        (None, true) => anyhow::bail!(
            "edges: the {:?} profile's anisotropic metric (r-xyz {:?}) needs the training cameras: pass --scene",
            settings.profile,
            settings.r_xyz
        ),
        _ => Vec::new(),
    };
    let (edges, [short, isolated]) = build_with_report(tracks, &keys, &rotations, &settings)
        .map_err(|e| anyhow::anyhow!("{}: {e}", key_path.display()))?;
    ctx.info(format!(
        "edges: {} edges ({} keys, {} Gaussians in the graph); {short} keys had fewer than \
         {} qualifying neighbours, {isolated} none (key-knn-fill {:?})",
        edges.len(),
        keys.num_keys(),
        tracks.len(),
        settings.key_knn_k,
        settings.key_knn_fill
    ));
    let prov = crate::tables::Provenance::new(
        "edges",
        &serde_json::json!({ "params": p, "resolved": settings }),
    )
    .with_metadata(GRAPH_KEY, &graph_metadata(&settings, tracks).to_string());
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
    use crate::stages::params::Profile;
    use crate::util::parse_args;

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
        // issue 15 item 7: uniform start weights in both profiles, learned by the optimiser
        assert_eq!(
            (p.key_edge_weights, r.key_edge_weights),
            (KeyEdgeWeights::Uniform, KeyEdgeWeights::Uniform)
        );
        assert_eq!((p.key_knn_fill, r.key_knn_fill), (KeyKnnFill::Nearest, KeyKnnFill::FirstKeys));
        assert_eq!((p.graph_scope, r.graph_scope), (GraphScope::Dynamic, GraphScope::Dynamic));
        assert_eq!((p.metric_form, r.metric_form), (MetricForm::Weight, MetricForm::Inverse));
        let base = ["--model", "m", "--uncertainty", "u", "--keynodes", "k", "--out", "o"];
        let given =
            ["--key-edge-mode", "euclidean", "--r-xyz", "1,1,0.5", "--metric-form", "inverse"];
        let o: EdgeParams = parse_args(&[&base[..], &given[..]].concat()).unwrap();
        let s = o.resolve().unwrap();
        assert_eq!((s.key_edge_mode, s.r_xyz), (KeyEdgeMode::Euclidean, [1.0, 1.0, 0.5]));
        assert_eq!(s.metric_form, MetricForm::Inverse);
        let err = parse_args::<EdgeParams>(&[&base[..], &["--r-xyz", "1,0"]].concat())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("--r-xyz") && err.contains("expected three positive numbers"),
            "{err}"
        );
        assert!(parse_args::<EdgeParams>(&[&base[..], &["--k", "3"]].concat()).is_err());
    }

    /// Key-key neighbours of each key, by source id, in table order.
    fn key_lists(e: &Edges) -> std::collections::BTreeMap<u32, Vec<u32>> {
        let mut m = std::collections::BTreeMap::<u32, Vec<u32>>::new();
        for k in (0..e.len()).filter(|&k| e.kind[k] == EdgeKind::KeyKey) {
            m.entry(e.src[k]).or_default().push(e.dst[k]);
        }
        m
    }

    /// Issue 15 item 8: a key that qualifies no neighbour (release: never co-confident;
    /// paper: no other key reliable at its t̂) got no key-key edge; now every key has
    /// min(k, K − 1) neighbours, never itself. The release pads with the first keys in key
    /// order (its +∞ rows), the paper with the nearest keys at t̂ in its metric.
    #[test]
    fn no_key_is_left_without_neighbours() {
        // release: the first three keys are never confident
        let (mut tracks, rotations, keys) = setup(Profile::Release);
        let key_rows = keys.rows(Role::Key);
        let nt = tracks.num_frames;
        for &i in &key_rows[..3] {
            for t in 0..nt {
                tracks.u[i * nt + t] = 1e8;
                tracks.reliable[i * nt + t] = false;
            }
        }
        let s = EdgeSettings { contrib_threshold: 1.0, ..EdgeSettings::defaults(Profile::Release) };
        let none = EdgeSettings { key_knn_fill: KeyKnnFill::None, ..s.clone() };
        let (e, [short, isolated]) = build_with_report(&tracks, &keys, &rotations, &none).unwrap();
        assert!(short >= 3 && isolated >= 3, "{short} {isolated}");
        assert_eq!(key_lists(&e).len(), key_rows.len() - 3, "isolated keys have no edge");
        let (e, report) = build_with_report(&tracks, &keys, &rotations, &s).unwrap();
        assert_eq!(report, [short, isolated]);
        let lists = key_lists(&e);
        let want = s.key_knn_k.min(key_rows.len() - 1);
        assert_eq!(lists.len(), key_rows.len());
        for (src, l) in &lists {
            assert_eq!(l.len(), want, "key {src}");
            assert!(!l.contains(src), "key {src} is its own neighbour");
        }
        let id = |a: usize| tracks.ids[key_rows[a]];
        let first: Vec<u32> = (1..=want).map(id).collect();
        assert_eq!(lists[&id(0)], first, "padded with the first keys in key order");
        // paper: no other key reliable at key 0's t̂
        let (mut tracks, rotations, mut keys) = setup(Profile::Paper);
        let key_rows = keys.rows(Role::Key);
        let t0 = keys.t_hat[key_rows[0]] as usize;
        for &i in &key_rows[1..] {
            tracks.u[i * nt + t0] = 1e8;
            tracks.reliable[i * nt + t0] = false;
            if keys.t_hat[i] as usize == t0 {
                keys.t_hat[i] = ((t0 + 1) % nt) as u32;
            }
        }
        let s = EdgeSettings::defaults(Profile::Paper);
        let none = EdgeSettings { key_knn_fill: KeyKnnFill::None, ..s.clone() };
        let e = build(&tracks, &keys, &rotations, &none).unwrap();
        assert!(!key_lists(&e).contains_key(&tracks.ids[key_rows[0]]));
        let (e, [short, isolated]) = build_with_report(&tracks, &keys, &rotations, &s).unwrap();
        assert!(short >= 1 && isolated >= 1, "{short} {isolated}");
        let l = &key_lists(&e)[&tracks.ids[key_rows[0]]];
        assert_eq!(l.len(), s.key_knn_k);
        assert!(!l.contains(&tracks.ids[key_rows[0]]));
    }

    /// Issue 15 item 6: a scene scaled by 10 and rendered at twice the resolution (u =
    /// 1/Σ(Tα)² divided by 4 where measured, φ unchanged) gives the paper profile the same
    /// keys and edges; without the normalisation (`scale-normalise false`, the behaviour
    /// before) the non-key weights change.
    #[test]
    fn scale_and_resolution_do_not_change_the_paper_graph() {
        let (tracks, rotations, _) = synthetic_tracks(1500, 16, 3, 9);
        let mut scaled = tracks.clone();
        for p in &mut scaled.positions {
            *p = p.map(|v| v * 10.0);
        }
        for (u, r) in scaled.u.iter_mut().zip(&scaled.reliable) {
            if *r {
                *u /= 4.0;
            }
        }
        let ks = KeynodeSettings::defaults(Profile::Paper);
        let (k1, k2) = (select(&tracks, &ks), select(&scaled, &ks));
        assert_eq!(k1, k2);
        assert!(k1.num_keys() >= 10, "{} keys", k1.num_keys());
        let s = EdgeSettings::defaults(Profile::Paper);
        let e1 = build(&tracks, &k1, &rotations, &s).unwrap();
        let e2 = build(&scaled, &k2, &rotations, &s).unwrap();
        assert_eq!((&e1.src, &e1.dst), (&e2.src, &e2.dst));
        let dw = e1.weight.iter().zip(&e2.weight).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
        assert!(dw < 1e-4, "weights differ by {dw}");
        let raw = EdgeSettings { scale_normalise: false, ..s };
        let (r1, r2) =
            (build(&tracks, &k1, &rotations, &raw), build(&scaled, &k2, &rotations, &raw));
        let (r1, r2) = (r1.unwrap(), r2.unwrap());
        let same =
            r1.dst == r2.dst && r1.weight.iter().zip(&r2.weight).all(|(a, b)| (a - b).abs() < 1e-4);
        assert!(!same, "raw units should depend on the scale");
    }
}
