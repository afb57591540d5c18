//! The USplat4D graph losses (paper Sec. 4.3): L_key (Eq. 9) and L_non-key (Eq. 11), with the
//! release's variants (official-release.md §5.1, §5.3) as named settings.
//!
//! - Anchors Σ_t Σ_i ‖p_{i,t} − p°_{i,t}‖ for keys (and non-keys) in the metric of
//!   [`AnchorMetric`] built from u_{i,t} and the training camera of frame t (Eq. 6); for
//!   the non-keys' anchor and DQB terms, [`MetricFrame`] chooses between that and Eq. 11's
//!   U_{w,i} (u and camera of the non-key's most reliable frame t̂_i).
//! - DQB term Σ_{t ∈ batch} Σ_{u ∈ non-keys} ‖p_{u,t} − p^DQB_{u,t}‖ (Eq. 10-11): DQB of the
//!   non-key's keys' motions from its most reliable frame t̂_u to t ([`crate::math::dqb`]),
//!   with the blend weights of [`super::nonkey_weights`] (trainable per-key sharpness θ and
//!   per-edge offsets Δw over the table's weights or the current distances at t̂_u),
//!   applied to a trainable source pose (release `src_xyz_1`, `src_xyzw_1`, initialised from
//!   p°_{u,t̂}), plus, as a setting, the release's trainable per-non-key offsets `[nu, 7]`
//!   added to (p^DQB, q^DQB) (`per_nonkeyGaussian_dxyz_dxyzw`); gradients reach the key
//!   trajectories at t and t̂. The release adds ‖q^DQB − q_{u,t}‖ on unit quaternions and the
//!   L2 penalties mean(Δw²) and mean(offset²). Each key's relative transform
//!   T_k(t) T_k(t̂)⁻¹ is computed once per (key, t̂, batch frame) and shared by the non-keys
//!   that use it.
//! - Key motion losses over key-key edges ([`super::motion`]): the paper's iso + rigid +
//!   0.01·rot (Δ = 1, normalised by 1/E, summed over frames), or the release's L_rigid_extra
//!   (edges with w > 1e-4, a seeded 80 % kept per step; rigid + rot + 100·iso + 100·rigid_Δ50 +
//!   100·rigid_Δ10, means). Key-key weights are learned as the release does:
//!   w_ij = |W_ij| / Σ_j |W_ij| (W initialised to the table's weights), with trainable rest
//!   lengths D_ij (initialised to mean_t ‖p°_i − p°_j‖) in the release form; the paper form
//!   keeps D_ij = ‖p°_j − p°_i‖ at the canonical frame fixed.
//! - L^{motion,non-key} (App. A.2 with i ∈ V_n, j ∈ E_i): isometry (rest lengths at the
//!   canonical frame), rigidity and relative rotation (Δ = 1) over each non-key's key edges
//!   with the edges table's normalised weights, λ_iso, λ_rigid, λ_rot as for the keys, at the
//!   batch frames like the DQB term (paper; the release's L_nonkey has none).
//! - Velocity and acceleration over keys and non-keys ([`MotionForm`]).
//!
//! Memory: O(T·(keys + non-keys)) plus O(T·keys) dual quaternions and O(non-key edges)
//! scratch; nothing of size keys × non-keys × frames.

use std::collections::HashMap;

use glam::DMat3;
use rayon::prelude::*;

use super::motion::{self, EdgeGrad, EdgeSet, EdgeTerms, MotionForm, Track, TrackGrad};
use super::nonkey_weights::NonkeyWeights;
use super::poses::{PoseGrads, Poses};
use super::smoothness;
use super::timing::PhaseTimes;
use crate::math::quat64::{self as q4, M3, V3};
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::key_nodes::{KeyNodes, Role};
use crate::util::rng::rank_key;
use dqb_term::{DqbScratch, Pairs};

mod dqb_term;

mod init;
pub use init::{GraphInit, InitReport};

/// The metric of the anchor and DQB position terms (profile rows 16-17, 40-42).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum AnchorMetric {
    /// ‖x‖_{U⁻¹} read literally: √(xᵀ U⁻¹ x), U = R_wc diag(r u) R_wcᵀ (Eq. 6), i.e.
    /// Σ_c (R_cw x)_c² / (r_c u): depth (r_z = 0.01) is 100× stiffer, unreliable u weaker.
    PaperLiteral,
    /// The release's precision: √(xᵀ R_cwᵀ diag(r) R_cw x), u only through the confidence
    /// mask u < 1/contrib_threshold (terms outside it are 0); depth is cheaper.
    Release,
    /// Plain Euclidean ‖x‖ (ablation (c) of Table 3, `--no-loss-weighting`).
    Euclidean,
}

/// Which frame's U weighs a non-key's anchor and DQB terms at frame t (Eq. 11).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum MetricFrame {
    /// U_{w,t,i}, as L_key (Eq. 9): the frame's own u_{i,t} and camera, so both pulls fade
    /// at the frames where the non-key is unreliable.
    Each,
    /// U_{w,i} as Eq. 11 writes it, read as U_{w,t̂_i,i}: the u and camera of the non-key's
    /// most reliable frame t̂_i at every t, so both pulls keep that frame's strength.
    MostReliable,
}

/// How the graph objective's sums over frames and Gaussians (or edges) are reduced.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Deserialize, serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Reduction {
    /// Σ_t Σ_i, as the paper's formulas are written (edge terms: 1/(k|V|) Σ_t Σ_e).
    Sum,
    /// The mean over the terms (the release's `mean`, the base models' normalisation).
    Mean,
}

/// Settings of the graph objective (every profile difference is one field).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GraphSettings {
    /// Metric of the anchor and DQB position terms.
    pub anchor_metric: AnchorMetric,
    /// Which frame's U weighs the non-keys' anchor and DQB terms.
    pub nonkey_metric_frame: MetricFrame,
    /// r_x, r_y, r_z of Eq. 6.
    pub r_xyz: [f64; 3],
    /// Release confidence mask: u < 1/contrib_threshold.
    pub contrib_threshold: f64,
    /// Reduction of the anchor and DQB terms, and of the paper form's key edge and
    /// smoothness terms over frames and Gaussians (the release form is always a mean).
    pub reduction: Reduction,
    /// Weight of the key anchor (paper 1, release 0: prep only).
    pub key_anchor: f64,
    /// Weight of the non-key anchor (paper 1, release 0).
    pub nonkey_anchor: f64,
    /// Weight of the DQB position term (paper 1, release 1).
    pub dqb: f64,
    /// Weight of the release's DQB rotation term ‖q^DQB − q‖ (paper 0, release 1).
    pub dqb_rotation: f64,
    /// Form of the key motion and smoothness terms.
    pub motion: MotionForm,
    /// Weight of the key edge terms (paper 1; release λ_graph·λ_key = 2·100).
    pub key_motion: f64,
    /// Weight of the non-key edge terms of L^{motion,non-key} (paper 1, release 0).
    pub nonkey_motion: f64,
    /// λ_iso, λ_rigid, λ_rot of the paper form (1, 1, 0.01).
    pub lambda_iso_rigid_rot: [f64; 3],
    /// λ_vel, λ_acc (paper 0.01, 0.01; release 100, 1).
    pub lambda_vel_acc: [f64; 2],
    /// Fraction of key edges kept per step in the release form (0.8).
    pub edge_keep_ratio: f64,
    /// Canonical frame of the paper's fixed rest lengths.
    pub canonical_frame: usize,
    /// The graph initialisation before fine-tuning ([`GraphInit`]).
    pub init: GraphInit,
    /// Log-base of the non-key blend weights before θ and Δw (row 32).
    pub nonkey_weights: NonkeyWeights,
    /// Weight of mean(Δw²) (release λ_graph · 1e-5; row 42).
    pub nonkey_dweight_l2: f64,
    /// Whether trainable per-non-key offsets `[nu, 7]` are added to (p^DQB, q^DQB) (row 36).
    pub nonkey_pose_offsets: bool,
    /// Weight of mean(offset²) (release λ_graph · 1e-3; row 42).
    pub nonkey_offset_l2: f64,
}

impl GraphSettings {
    /// The defaults of `profile` (official-release.md Sec. 11).
    pub fn defaults(profile: crate::stages::params::Profile) -> Self {
        let paper = profile == crate::stages::params::Profile::Paper;
        GraphSettings {
            anchor_metric: if paper { AnchorMetric::PaperLiteral } else { AnchorMetric::Release },
            nonkey_metric_frame: MetricFrame::Each,
            r_xyz: if paper { [1.0, 1.0, 0.01] } else { [1.0, 1.0, 0.1] },
            contrib_threshold: 2.0,
            reduction: if paper { Reduction::Sum } else { Reduction::Mean },
            key_anchor: if paper { 1.0 } else { 0.0 },
            nonkey_anchor: if paper { 1.0 } else { 0.0 },
            dqb: if paper { 1.0 } else { 2.0 },
            dqb_rotation: if paper { 0.0 } else { 2.0 },
            motion: if paper { MotionForm::Paper } else { MotionForm::Release },
            key_motion: if paper { 1.0 } else { 200.0 },
            nonkey_motion: if paper { 1.0 } else { 0.0 },
            lambda_iso_rigid_rot: [1.0, 1.0, 0.01],
            lambda_vel_acc: if paper { [0.01, 0.01] } else { [100.0, 1.0] },
            edge_keep_ratio: if paper { 1.0 } else { 0.8 },
            canonical_frame: 0,
            init: GraphInit {
                max_iters: if paper { 0 } else { 10_000 },
                lr: 0.1,
                edge_keep_ratio: 0.7,
                batch_frames: 30,
                acceleration: 0.1,
            },
            nonkey_weights: if paper { NonkeyWeights::Table } else { NonkeyWeights::Current },
            nonkey_dweight_l2: if paper { 1e-5 } else { 2e-5 },
            nonkey_pose_offsets: !paper,
            nonkey_offset_l2: if paper { 1e-3 } else { 2e-3 },
        }
    }
}

/// A trainable tensor of the objective, for the training loop's Adam.
pub struct ParamSlice<'a> {
    /// Name (the release's tensor name where there is one).
    pub name: &'static str,
    /// Values, flat.
    pub values: &'a mut [f32],
    /// Gradients of the last [`GraphObjective::evaluate`], same layout.
    pub grads: &'a [f32],
    /// Learning-rate key of the profile (release `OptimCFG`: `dists_key` 1.6e-4,
    /// `weight_dist_key` 1e-4, `src_xyz_1_nonkey` 1e-4, ...).
    pub lr_key: &'static str,
}

/// The graph objective over the Gaussians of a [`Poses`] (indices are pose indices `0..N`).
pub struct GraphObjective {
    s: GraphSettings,
    frames: usize,
    n: usize,
    ids: Vec<u32>,
    keys: Vec<u32>,
    /// Non-key pose indices, ordered by t̂ (stable), and the position there of each non-key
    /// of the inputs.
    nonkeys: Vec<u32>,
    nk_order: Vec<u32>,
    /// Key-key edges, compact indices into `keys`, grouped by source.
    ksrc: Vec<u32>,
    kdst: Vec<u32>,
    /// Trainable raw key-key weights W `[E]` and rest lengths D `[E]`.
    w_raw: Vec<f32>,
    rest: Vec<f32>,
    g_w_raw: Vec<f32>,
    g_rest: Vec<f32>,
    /// Non-key → key edges, CSR over `nonkeys`: `nk_off[u]..nk_off[u+1]`, compact key index,
    /// the table's normalised weight, the source's index in [`Self::nodes`] and the rest
    /// length at the canonical frame `[E_n]`.
    nk_off: Vec<usize>,
    nk_key: Vec<u32>,
    nk_w: Vec<f64>,
    nk_src: Vec<u32>,
    nk_rest: Vec<f64>,
    t_hat: Vec<u32>,
    /// λ / unit² of [`NonkeyWeights::Current`].
    nk_lambda: f64,
    /// The distinct (key, t̂) pairs of the non-key edges.
    pairs: Pairs,
    /// Trainable source poses `[nu, 3]`, `[nu, 4]`.
    src_p: Vec<f32>,
    src_q: Vec<f32>,
    g_src_p: Vec<f32>,
    g_src_q: Vec<f32>,
    /// Trainable sharpness θ `[K]` (init 1), weight offsets Δw `[E_n]` (init 0) and, with
    /// `nonkey_pose_offsets`, pose offsets `[nu, 7]` (Δp xyz, Δq wxyz; init 0, else empty).
    theta: Vec<f32>,
    dw: Vec<f32>,
    offsets: Vec<f32>,
    g_theta: Vec<f32>,
    g_dw: Vec<f32>,
    g_offsets: Vec<f32>,
    /// The blend weights w' of the last evaluation (at construction: of p°) `[E_n]`.
    nk_w_eff: Vec<f64>,
    scratch: DqbScratch,
    /// The frame whose U weighs pose i at every frame `[N]` (t̂ of a non-key under
    /// [`MetricFrame::MostReliable`]), [`Self::OWN_FRAME`] for the frame's own; empty when
    /// every pose uses its own.
    metric_frame: Vec<u32>,
    /// p° `[T, N]`, u `[T, N]`, R_cw `[T]`.
    p0: Vec<[f32; 3]>,
    u: Vec<f32>,
    rot: Vec<M3>,
}

/// What the graph terms hold on to from before optimisation, in pose index order. Owned,
/// so that the objective keeps p° and u as given instead of copying them; of q° only what
/// DQB reads, so that no `[T, N]` rotations are held for it.
pub struct Anchors {
    /// T, the number of frames.
    pub frames: usize,
    /// p°: the positions before optimisation `[T, N]`.
    pub p0: Vec<[f32; 3]>,
    /// u_{t,i} `[T, N]`.
    pub u: Vec<f32>,
    /// q° of each pose at its most reliable frame t̂ `[N]`, read for the non-keys (their DQB
    /// source rotation).
    pub q_hat: Vec<[f32; 4]>,
}

#[cfg(test)]
impl Anchors {
    /// The anchors of `poses` with u `u`, q° at t̂ for the non-keys `nonkeys` with their t̂
    /// `t_hat` (the identity for the other poses).
    pub(crate) fn of_poses(poses: &Poses, u: Vec<f32>, nonkeys: &[u32], t_hat: &[u32]) -> Self {
        let mut q_hat = vec![[1.0, 0.0, 0.0, 0.0]; poses.n];
        for (&i, &t) in nonkeys.iter().zip(t_hat) {
            q_hat[i as usize] = poses.q(t as usize, i as usize);
        }
        Anchors { frames: poses.frames, p0: poses.position.clone(), u, q_hat }
    }
}

/// Inputs of [`GraphObjective::new`], all in pose index order.
pub struct GraphInputs<'a> {
    /// p°, u and q° at t̂.
    pub anchors: Anchors,
    /// gaussian_id of each pose index `[N]`.
    pub ids: &'a [u32],
    /// Key pose indices `[K]`.
    pub keys: &'a [u32],
    /// Non-key pose indices `[nu]`, their t̂ `[nu]`, and their key edges as
    /// `(pose index of the key, weight)` lists `[nu][k]`.
    pub nonkeys: &'a [u32],
    /// t̂ of each non-key `[nu]`.
    pub t_hat: &'a [u32],
    /// Key edges of each non-key.
    pub nonkey_edges: &'a [Vec<(u32, f32)>],
    /// Key-key edges `(src pose index, dst pose index, weight)`, grouped by source.
    pub key_edges: &'a [(u32, u32, f32)],
    /// λ / unit² of [`NonkeyWeights::Current`] (the edges table's `nonkey-weight-sharpness`
    /// over its `nonkey-distance-unit`²); unused by [`NonkeyWeights::Table`].
    pub nonkey_lambda: f64,
    /// World-to-camera rotation R_cw of each frame's training camera `[T]`.
    pub rot_cw: &'a [DMat3],
}

/// The graph tables [`GraphObjective::from_tables`] reads.
pub struct GraphTables<'a> {
    /// The key-node table.
    pub key_nodes: &'a KeyNodes,
    /// The edges table.
    pub edges: &'a Edges,
    /// λ / unit² of the edges table's non-key weights ([`GraphInputs::nonkey_lambda`]).
    pub nonkey_lambda: f64,
}

impl GraphObjective {
    /// Build from plain arrays. Errors name the inconsistent input.
    pub fn new(inp: GraphInputs, s: GraphSettings) -> Result<Self, String> {
        let Anchors { frames: t, p0, u, q_hat } = inp.anchors;
        let n = inp.ids.len();
        if p0.len() != t * n || u.len() != t * n || q_hat.len() != n || inp.rot_cw.len() != t {
            return Err(format!(
                "graph objective: {} p°, {} u, {} q° at t̂, {} rotations for N = {n}, T = {t}",
                p0.len(),
                u.len(),
                q_hat.len(),
                inp.rot_cw.len()
            ));
        }
        let nu = inp.nonkeys.len();
        if inp.t_hat.len() != nu || inp.nonkey_edges.len() != nu {
            return Err("graph objective: one t_hat and one edge list per non-key".into());
        }
        let key_of: HashMap<u32, u32> =
            inp.keys.iter().enumerate().map(|(k, &i)| (i, k as u32)).collect();
        let compact = |i: u32| {
            key_of.get(&i).copied().ok_or_else(|| format!("edge to pose {i}, which is no key"))
        };
        let (mut ksrc, mut kdst, mut w_raw, mut rest) = (vec![], vec![], vec![], vec![]);
        let cf = s.canonical_frame.min(t.saturating_sub(1));
        for &(a, b, w) in inp.key_edges {
            let (ca, cb) = (compact(a)?, compact(b)?);
            ksrc.push(ca);
            kdst.push(cb);
            w_raw.push(w);
            let d = |f: usize| distance(&p0[f * n..(f + 1) * n], a, b);
            rest.push(match s.motion {
                MotionForm::Paper => d(cf) as f32,
                MotionForm::Release => ((0..t).map(d).sum::<f64>() / t.max(1) as f64) as f32,
            });
        }
        let (mut nk_off, mut nk_key, mut nk_w) = (vec![0], vec![], vec![]);
        let (mut nk_src, mut nk_rest) = (vec![], vec![]);
        let (mut src_p, mut src_q) = (Vec::with_capacity(3 * nu), Vec::with_capacity(4 * nu));
        // the non-keys ordered by t̂ (stable), for the DQB term's groups
        let mut order: Vec<usize> = (0..nu).collect();
        order.sort_by_key(|&u| inp.t_hat[u]);
        for (v, &u) in order.iter().enumerate() {
            let list = &inp.nonkey_edges[u];
            let sum: f64 = list.iter().map(|e| e.1 as f64).sum();
            for &(k, w) in list {
                nk_key.push(compact(k)?);
                nk_w.push(if sum > 0.0 { w as f64 / sum } else { 1.0 / list.len() as f64 });
                nk_src.push((inp.keys.len() + v) as u32);
                nk_rest.push(distance(&p0[cf * n..(cf + 1) * n], inp.nonkeys[u], k));
            }
            nk_off.push(nk_key.len());
            let th = inp.t_hat[u] as usize;
            if th >= t {
                return Err(format!("non-key {u}: t_hat {th} out of range (T = {t})"));
            }
            src_p.extend(p0[th * n + inp.nonkeys[u] as usize]);
            src_q.extend(q_hat[inp.nonkeys[u] as usize]);
        }
        let ne = ksrc.len();
        let lambda = inp.nonkey_lambda;
        if s.nonkey_weights == NonkeyWeights::Current && !(lambda.is_finite() && lambda > 0.0) {
            return Err(format!("non-key weights from distances need λ > 0, got {lambda}"));
        }
        let t_hat: Vec<u32> = order.iter().map(|&u| inp.t_hat[u]).collect();
        let pairs = Pairs::new(&nk_off, &nk_key, &t_hat, inp.keys.len());
        let mut nk_order = vec![0u32; nu];
        for (v, &u) in order.iter().enumerate() {
            nk_order[u] = v as u32;
        }
        let n_edges = nk_key.len();
        let mut metric_frame = Vec::new();
        if s.nonkey_metric_frame == MetricFrame::MostReliable {
            metric_frame = vec![Self::OWN_FRAME; n];
            for (u, &i) in inp.nonkeys.iter().enumerate() {
                metric_frame[i as usize] = inp.t_hat[u];
            }
        }
        let mut obj = GraphObjective {
            frames: t,
            n,
            ids: inp.ids.to_vec(),
            keys: inp.keys.to_vec(),
            nonkeys: order.iter().map(|&u| inp.nonkeys[u]).collect(),
            nk_order,
            ksrc,
            kdst,
            g_w_raw: vec![0.0; ne],
            g_rest: vec![0.0; ne],
            w_raw,
            rest,
            nk_off,
            nk_key,
            nk_w,
            nk_src,
            nk_rest,
            t_hat,
            nk_lambda: inp.nonkey_lambda,
            pairs,
            g_src_p: vec![0.0; src_p.len()],
            g_src_q: vec![0.0; src_q.len()],
            src_p,
            src_q,
            theta: vec![1.0; inp.keys.len()],
            dw: vec![0.0; n_edges],
            offsets: vec![0.0; if s.nonkey_pose_offsets { 7 * nu } else { 0 }],
            g_theta: vec![0.0; inp.keys.len()],
            g_dw: vec![0.0; n_edges],
            g_offsets: vec![0.0; if s.nonkey_pose_offsets { 7 * nu } else { 0 }],
            nk_w_eff: vec![0.0; n_edges],
            scratch: DqbScratch::default(),
            metric_frame,
            p0,
            u,
            rot: inp
                .rot_cw
                .iter()
                .map(|r| {
                    let c = r.to_cols_array_2d();
                    [0, 1, 2].map(|i| [c[0][i], c[1][i], c[2][i]])
                })
                .collect(),
            s,
        };
        let p0 = std::mem::take(&mut obj.p0);
        obj.blend_weights_of(&p0);
        obj.p0 = p0;
        Ok(obj)
    }

    /// Build from the tables: the [`Anchors`] (u φ where unmeasured) of the Gaussians
    /// `ids` (pose index order), the key-node and edges tables and the training cameras'
    /// R_cw `[T]`. Gaussians of the tables that are not in `ids` are
    /// an error; `unlinked`/`culled` roles get no graph terms.
    pub fn from_tables(
        anchors: Anchors,
        ids: &[u32],
        tables: GraphTables,
        rot_cw: &[DMat3],
        s: GraphSettings,
    ) -> Result<Self, String> {
        let GraphTables { key_nodes, edges, nonkey_lambda } = tables;
        let index: HashMap<u32, u32> =
            ids.iter().enumerate().map(|(i, &id)| (id, i as u32)).collect();
        let pose = |id: u32, what: &str| {
            index
                .get(&id)
                .copied()
                .ok_or_else(|| format!("{what}: Gaussian {id} is not in the model"))
        };
        let (mut keys, mut nonkeys, mut t_hat) = (vec![], vec![], vec![]);
        let mut nonkey_row: HashMap<u32, usize> = HashMap::new();
        for (row, (&id, role)) in key_nodes.id.iter().zip(&key_nodes.role).enumerate() {
            match role {
                Role::Key => keys.push(pose(id, "key_nodes")?),
                Role::Nonkey => {
                    nonkey_row.insert(id, nonkeys.len());
                    nonkeys.push(pose(id, "key_nodes")?);
                    t_hat.push(key_nodes.t_hat[row]);
                }
                Role::Unlinked | Role::Culled => {}
            }
        }
        let mut nonkey_edges = vec![Vec::new(); nonkeys.len()];
        let mut key_edges = Vec::new();
        for e in 0..edges.len() {
            let (a, b, w) = (edges.src[e], edges.dst[e], edges.weight[e]);
            match edges.kind[e] {
                EdgeKind::KeyKey => key_edges.push((pose(a, "edges")?, pose(b, "edges")?, w)),
                EdgeKind::NonkeyKey => {
                    let u = *nonkey_row
                        .get(&a)
                        .ok_or_else(|| format!("edges: row {e}: source {a} is not a non-key"))?;
                    nonkey_edges[u].push((pose(b, "edges")?, w));
                }
            }
        }
        key_edges.sort_by_key(|e| e.0);
        let inp = GraphInputs {
            anchors,
            ids,
            keys: &keys,
            nonkeys: &nonkeys,
            t_hat: &t_hat,
            nonkey_edges: &nonkey_edges,
            key_edges: &key_edges,
            rot_cw,
            nonkey_lambda,
        };
        Self::new(inp, s)
    }

    /// The settings.
    pub fn settings(&self) -> &GraphSettings {
        &self.s
    }

    /// The trainable tensors and the gradients of the last evaluation.
    pub fn params_mut(&mut self) -> Vec<ParamSlice<'_>> {
        let mut out = vec![
            ParamSlice {
                name: "src_xyz_1_nonkey",
                values: &mut self.src_p,
                grads: &self.g_src_p,
                lr_key: "graph",
            },
            ParamSlice {
                name: "src_xyzw_1_nonkey",
                values: &mut self.src_q,
                grads: &self.g_src_q,
                lr_key: "graph",
            },
            ParamSlice {
                name: "weight_dist_key",
                values: &mut self.w_raw,
                grads: &self.g_w_raw,
                lr_key: "graph",
            },
            ParamSlice {
                name: "weight_param_key",
                values: &mut self.theta,
                grads: &self.g_theta,
                lr_key: "graph",
            },
            ParamSlice {
                name: "per_nonkeyGaussian_dweight_nonkey",
                values: &mut self.dw,
                grads: &self.g_dw,
                lr_key: "graph",
            },
        ];
        if self.s.nonkey_pose_offsets {
            out.push(ParamSlice {
                name: "per_nonkeyGaussian_dxyz_dxyzw",
                values: &mut self.offsets,
                grads: &self.g_offsets,
                lr_key: "graph",
            });
        }
        if self.s.motion == MotionForm::Release {
            out.push(ParamSlice {
                name: "dists_key",
                values: &mut self.rest,
                grads: &self.g_rest,
                lr_key: "dists_key",
            });
        }
        out
    }

    /// The current key-key weights w_ij = |W_ij| / Σ_j |W_ij| `[E]`.
    fn key_weights(&self) -> Vec<f64> {
        let mut w = vec![0.0; self.ksrc.len()];
        for (_, run) in motion::by_source(&self.ksrc) {
            let sum: f64 = self.w_raw[run.clone()].iter().map(|x| x.abs() as f64).sum();
            for k in run {
                w[k] = if sum > 0.0 { self.w_raw[k].abs() as f64 / sum } else { 0.0 };
            }
        }
        w
    }

    /// The learned graph as an edges table: key-key edges with the current w_ij and learned
    /// canonical length D_ij (release form; the paper form's fixed lengths are not learned
    /// and left out), nonkey-key edges with the blend weights w' of the last evaluation.
    pub fn learned_edges(&self) -> Edges {
        let mut out = Edges::default();
        let w = self.key_weights();
        let id = |pose: u32| self.ids[pose as usize];
        let learned = self.s.motion == MotionForm::Release;
        for e in 0..self.ksrc.len() {
            let (a, b) = (self.keys[self.ksrc[e] as usize], self.keys[self.kdst[e] as usize]);
            let d = learned.then_some(self.rest[e]);
            out.push_trained(id(a), id(b), EdgeKind::KeyKey, w[e] as f32, d);
        }
        for &u in &self.nk_order {
            let (u, nk) = (u as usize, self.nonkeys[u as usize]);
            for e in self.nk_off[u]..self.nk_off[u + 1] {
                let key = self.keys[self.nk_key[e] as usize];
                out.push(id(nk), id(key), EdgeKind::NonkeyKey, self.nk_w_eff[e] as f32);
            }
        }
        out
    }

    /// Hand over the `[T, N]` p° and u (for the objective that replaces this one after a
    /// density pass, which gathers its rows from them) and drop the step buffers
    /// ([`Self::carry_over`] reads only the graph and trainable tensors), so that the old
    /// objective holds no `[T, N]` array beside its replacement's.
    pub fn take_anchors(&mut self) -> (Vec<[f32; 3]>, Vec<f32>) {
        self.scratch = Default::default();
        (std::mem::take(&mut self.p0), std::mem::take(&mut self.u))
    }

    /// Take over the trained tensors of `old` (the objective before a density pass): the
    /// key-key rest lengths by (source, destination) id, θ by key id, and each non-key's
    /// source pose, Δw, pose offsets and table weights (the base of θ and Δw, not the
    /// learned w' the rebuilt objective was built from) by its id, or, for a Gaussian that
    /// density control created, by the id of the input Gaussian it descends from (`origin`;
    /// the release's `densify_params` copies the parent's). The key-key weights come in
    /// through the learned edges the objective was built from.
    pub fn carry_over(&mut self, old: &GraphObjective, origin: impl Fn(u32) -> u32) {
        let key_id = |o: &GraphObjective, k: u32| o.ids[o.keys[k as usize] as usize];
        let rest: HashMap<(u32, u32), f32> = (0..old.ksrc.len())
            .map(|e| ((key_id(old, old.ksrc[e]), key_id(old, old.kdst[e])), old.rest[e]))
            .collect();
        for e in 0..self.ksrc.len() {
            let pair = (key_id(self, self.ksrc[e]), key_id(self, self.kdst[e]));
            if let Some(&d) = rest.get(&pair) {
                self.rest[e] = d;
            }
        }
        let theta: HashMap<u32, f32> =
            (0..old.keys.len()).map(|k| (key_id(old, k as u32), old.theta[k])).collect();
        for k in 0..self.keys.len() {
            if let Some(&th) = theta.get(&key_id(self, k as u32)) {
                self.theta[k] = th;
            }
        }
        let src: HashMap<u32, usize> =
            old.nonkeys.iter().enumerate().map(|(u, &i)| (old.ids[i as usize], u)).collect();
        for (u, &i) in self.nonkeys.iter().enumerate() {
            let id = self.ids[i as usize];
            let Some(&v) = src.get(&id).or_else(|| src.get(&origin(id))) else { continue };
            self.src_p[3 * u..3 * u + 3].copy_from_slice(&old.src_p[3 * v..3 * v + 3]);
            self.src_q[4 * u..4 * u + 4].copy_from_slice(&old.src_q[4 * v..4 * v + 4]);
            if !self.offsets.is_empty() && !old.offsets.is_empty() {
                self.offsets[7 * u..7 * u + 7].copy_from_slice(&old.offsets[7 * v..7 * v + 7]);
            }
            let (a, b) = (self.nk_off[u], self.nk_off[u + 1]);
            let (c, d) = (old.nk_off[v], old.nk_off[v + 1]);
            let same =
                |e: usize| key_id(self, self.nk_key[e]) == key_id(old, old.nk_key[c + e - a]);
            if b - a == d - c && (a..b).all(same) {
                self.dw[a..b].copy_from_slice(&old.dw[c..d]);
                self.nk_w[a..b].copy_from_slice(&old.nk_w[c..d]);
            }
        }
    }

    /// [`Self::metric_frame`]'s entry of a pose that uses each frame's own U.
    const OWN_FRAME: u32 = u32::MAX;

    /// The frame whose u and camera weigh pose i's terms at frame t.
    #[inline]
    fn metric_frame(&self, t: usize, i: usize) -> usize {
        match self.metric_frame.get(i) {
            Some(&f) if f != Self::OWN_FRAME => f as usize,
            _ => t,
        }
    }

    /// The metric of Gaussian i weighed by frame f (its [`Self::metric_frame`]): per-axis
    /// factors in the camera frame of f (already multiplied by the weight of u_{i,f}), or
    /// `None` when the term is masked out.
    fn metric(&self, f: usize, i: usize) -> Option<V3> {
        let r = self.s.r_xyz;
        let u = self.u[f * self.n + i] as f64;
        match self.s.anchor_metric {
            AnchorMetric::Euclidean => Some([1.0; 3]),
            AnchorMetric::PaperLiteral => {
                Some([1.0 / (r[0] * u), 1.0 / (r[1] * u), 1.0 / (r[2] * u)])
            }
            AnchorMetric::Release => (u < 1.0 / self.s.contrib_threshold).then_some(r),
        }
    }

    /// √(Σ_c k_c (R_f x)_c² + 1e-8) and its gradient with respect to x, in the camera of
    /// frame f.
    fn distance(&self, f: usize, k: V3, x: V3) -> (f64, V3) {
        let rm = &self.rot[f];
        let y = q4::mat_vec(rm, x);
        let d = (k[0] * y[0] * y[0] + k[1] * y[1] * y[1] + k[2] * y[2] * y[2] + 1e-8).sqrt();
        let gy = [0, 1, 2].map(|c| k[c] * y[c] / d);
        (d, q4::mat_t_vec(rm, gy))
    }

    /// The anchor metric as w_{t,i} · Aₜ: Aₜ = R_tᵀ diag(r') R_t `[T]` (r' = 1/r for the
    /// literal reading, r for the release's, 1 for Euclidean), so that Σ_c k_c (R_t x)_c² of
    /// [`Self::metric`] is w_{t,i} xᵀ Aₜ x.
    fn anchor_matrices(&self) -> Vec<M3> {
        let r = self.s.r_xyz;
        let diag = match self.s.anchor_metric {
            AnchorMetric::Euclidean => [1.0; 3],
            AnchorMetric::PaperLiteral => r.map(|x| 1.0 / x),
            AnchorMetric::Release => r,
        };
        let a = |m: &M3| {
            let mut out = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    out[i][j] = (0..3).map(|c| m[c][i] * diag[c] * m[c][j]).sum();
                }
            }
            out
        };
        self.rot.iter().map(a).collect()
    }

    /// The weight of [`Self::anchor_matrices`] from u_{i,f} at Gaussian i's metric frame f
    /// (1/u, or the release's mask as 1), `None` when the term is masked out.
    #[inline]
    fn anchor_weight(&self, f: usize, i: usize) -> Option<f64> {
        let u = self.u[f * self.n + i] as f64;
        match self.s.anchor_metric {
            AnchorMetric::Euclidean => Some(1.0),
            AnchorMetric::PaperLiteral => Some(1.0 / u),
            AnchorMetric::Release => (u < 1.0 / self.s.contrib_threshold).then_some(1.0),
        }
    }

    /// Anchors Σ_t Σ_i ‖p_{i,t} − p°_{i,t}‖ of the keys and of the non-keys, all frames, in
    /// one pass over the poses; adds `weights ·` their gradients, returns both sums. Parallel
    /// over frames (each writes its own gradient row), sums reduced in frame order.
    fn anchors(&self, poses: &Poses, weights: [f64; 2], grads: &mut PoseGrads) -> [f64; 2] {
        let n = self.n;
        // role of each pose: 0 none (or weight 0), 1 key, 2 non-key
        let mut role = vec![0u8; n];
        for (list, r) in [(&self.keys, 0), (&self.nonkeys, 1)] {
            if weights[r] != 0.0 {
                list.iter().for_each(|&i| role[i as usize] = r as u8 + 1);
            }
        }
        if role.iter().all(|&r| r == 0) {
            return [0.0; 2];
        }
        let norm = match self.s.reduction {
            Reduction::Sum => [1.0; 2],
            Reduction::Mean => {
                let count = |r: u8| -> usize {
                    (0..self.frames)
                        .into_par_iter()
                        .map(|t| {
                            (0..n)
                                .filter(|&i| {
                                    role[i] == r
                                        && self.anchor_weight(self.metric_frame(t, i), i).is_some()
                                })
                                .count()
                        })
                        .sum()
                };
                [1, 2].map(|r| 1.0 / count(r).max(1) as f64)
            }
        };
        let scale = [0, 1].map(|r| weights[r] * norm[r]);
        let mats = self.anchor_matrices();
        let sums: Vec<[f64; 2]> = grads
            .position
            .par_chunks_mut(n)
            .enumerate()
            .map(|(t, row)| {
                let mut sum = [0.0; 2];
                for i in 0..n {
                    let r = match role[i] {
                        0 => continue,
                        r => r as usize - 1,
                    };
                    let f = self.metric_frame(t, i);
                    let Some(w) = self.anchor_weight(f, i) else { continue };
                    let a = &mats[f];
                    let o = t * n + i;
                    let x = [0, 1, 2].map(|c| (poses.position[o][c] - self.p0[o][c]) as f64);
                    let y = q4::mat_vec(a, x);
                    let d = (w * (x[0] * y[0] + x[1] * y[1] + x[2] * y[2]) + 1e-8).sqrt();
                    sum[r] += d;
                    let k = scale[r] * w / d;
                    for c in 0..3 {
                        row[i][c] += (k * y[c]) as f32;
                    }
                }
                sum
            })
            .collect();
        let total = sums.iter().fold([0.0; 2], |s, x| [s[0] + x[0], s[1] + x[1]]);
        [total[0] * norm[0], total[1] * norm[1]]
    }

    /// Evaluate every term on `poses` (DQB terms on the batch `frames`), add the gradients
    /// to `grads` (poses) and to the objective's own tensors (see [`Self::params_mut`];
    /// reset here), and return each term's contribution (weight × value) by name.
    /// Each part's wall time is added to `timer`.
    pub fn evaluate(
        &mut self,
        poses: &Poses,
        frames: &[usize],
        rng_seed: u64,
        grads: &mut PoseGrads,
        timer: &mut PhaseTimes,
    ) -> Vec<(&'static str, f64)> {
        assert_eq!((poses.frames, poses.n), (self.frames, self.n), "poses [T, N]");
        self.g_w_raw.fill(0.0);
        self.g_rest.fill(0.0);
        self.g_src_p.fill(0.0);
        self.g_src_q.fill(0.0);
        self.g_theta.fill(0.0);
        self.g_dw.fill(0.0);
        self.g_offsets.fill(0.0);
        let mut out = Vec::new();
        let s = self.s.clone();
        let [ka, na] = timer
            .time("graph anchors", || self.anchors(poses, [s.key_anchor, s.nonkey_anchor], grads));
        out.push(("key_anchor", s.key_anchor * ka));
        out.push(("nonkey_anchor", s.nonkey_anchor * na));
        let [dp, dq] = timer.time("graph DQB", || self.dqb_terms(poses, frames, grads));
        out.push(("nonkey_dqb", s.dqb * dp));
        out.push(("nonkey_dqb_rotation", s.dqb_rotation * dq));
        let [dw, off] = self.offset_penalties();
        out.push(("nonkey_dweight", s.nonkey_dweight_l2 * dw));
        if s.nonkey_pose_offsets {
            out.push(("nonkey_offset", s.nonkey_offset_l2 * off));
        }
        let key = timer.time("graph key motion", || self.key_motion(poses, rng_seed, grads));
        out.extend(key);
        let nonkey =
            timer.time("graph non-key motion", || self.nonkey_motion(poses, frames, grads));
        out.extend(nonkey);
        // Smoothness over keys and non-keys.
        let [vel, acc] = timer.time("graph smoothness", || self.smoothness(poses, grads));
        let [lv, la] = s.lambda_vel_acc;
        out.push(("velocity", lv * vel));
        out.push(("acceleration", la * acc));
        out
    }

    /// The keys, then the non-keys: the Gaussians of the smoothness and non-key edge terms.
    fn nodes(&self) -> Vec<u32> {
        self.keys.iter().chain(&self.nonkeys).copied().collect()
    }

    /// Velocity and acceleration (unweighted) over keys and non-keys; adds the λ-weighted
    /// gradients.
    fn smoothness(&self, poses: &Poses, grads: &mut PoseGrads) -> [f64; 2] {
        let all = self.nodes();
        let [lv, la] = self.s.lambda_vel_acc;
        let form = self.s.motion;
        let (nv, na) = if form == MotionForm::Release || self.s.reduction == Reduction::Mean {
            smoothness::smoothness_means(self.frames, all.len())
        } else {
            (1.0, 1.0)
        };
        smoothness::smoothness(poses, &all, form, (nv, lv), (na, la), grads)
    }

    /// L^{motion,non-key}'s edge terms over every non-key's key edges at the batch `frames`,
    /// as the DQB term (frame t with t − 1 as context: non-key i is the edge's source, so
    /// rigidity moves the keys in its frame); returns their weighted contributions (none at
    /// weight 0). Frames are evaluated in parallel, a thread's worth at a time, and their
    /// gradients added in batch order.
    fn nonkey_motion(
        &self,
        poses: &Poses,
        frames: &[usize],
        grads: &mut PoseGrads,
    ) -> Vec<(&'static str, f64)> {
        let wm = self.s.nonkey_motion;
        if wm == 0.0 {
            return Vec::new();
        }
        let nodes = self.nodes();
        let es = EdgeSet { src: &self.nk_src, dst: &self.nk_key, w: &self.nk_w };
        // 1/(k|V|) per frame; summed over the batch frames, or their mean.
        let norm = 1.0
            / (self.nk_src.len().max(1)
                * if self.s.reduction == Reduction::Mean { frames.len() } else { 1 })
            .max(1) as f64;
        let [li, lr, lo] = self.s.lambda_iso_rigid_rot;
        let one = |t: usize| {
            let track = Track::gather_frames(poses, &nodes, t.saturating_sub(1)..t + 1, t.min(1));
            let mut g = TrackGrad::zeros(&track);
            let [iso, rigid] = motion::isometry_rigidity(
                &track,
                es,
                &self.nk_rest,
                (norm, wm * li),
                (norm, wm * lr),
                &mut g,
                None,
            );
            let terms = &mut EdgeTerms { track: &track, edges: es, g: &mut g, g_edges: None };
            let rot = motion::relative_rotation(terms, 1, norm, wm * lo);
            (track, g, [iso, rigid, rot])
        };
        let mut sums = [0.0; 3];
        for chunk in frames.chunks(rayon::current_num_threads().max(1)) {
            let parts: Vec<_> = chunk.par_iter().map(|&t| one(t)).collect();
            for (track, g, v) in parts {
                g.scatter(&track, &nodes, self.n, grads);
                for (s, x) in sums.iter_mut().zip(v) {
                    *s += x;
                }
            }
        }
        let [iso, rigid, rot] = sums;
        vec![
            ("nonkey_isometry", wm * li * iso),
            ("nonkey_rigidity", wm * lr * rigid),
            ("nonkey_rotation", wm * lo * rot),
        ]
    }

    /// Key edge terms; returns their weighted contributions.
    fn key_motion(
        &mut self,
        poses: &Poses,
        seed: u64,
        grads: &mut PoseGrads,
    ) -> Vec<(&'static str, f64)> {
        let s = self.s.clone();
        let track = Track::gather(poses, &self.keys);
        let mut tg = TrackGrad::zeros(&track);
        let w_all = self.key_weights();
        // Kept edges: all (paper), or w > 1e-4 and a seeded fraction (release).
        let kept: Vec<usize> = (0..self.ksrc.len())
            .filter(|&e| match s.motion {
                MotionForm::Paper => true,
                MotionForm::Release => {
                    let r =
                        (rank_key(seed, 0x6564_6765, e as u64) >> 11) as f64 / (1u64 << 53) as f64;
                    w_all[e] > 1e-4 && r < s.edge_keep_ratio
                }
            })
            .collect();
        let src: Vec<u32> = kept.iter().map(|&e| self.ksrc[e]).collect();
        let dst: Vec<u32> = kept.iter().map(|&e| self.kdst[e]).collect();
        let w: Vec<f64> = kept.iter().map(|&e| w_all[e]).collect();
        let rest: Vec<f64> = kept.iter().map(|&e| self.rest[e] as f64).collect();
        let es = EdgeSet { src: &src, dst: &dst, w: &w };
        let mut ge = EdgeGrad::zeros(kept.len());
        let ne = kept.len().max(1) as f64;
        let nt = self.frames;
        let km = s.key_motion;
        // The mean over the kept edges and the frames a term with offset d covers.
        let mean = |d: usize| 1.0 / (ne * nt.saturating_sub(d).max(1) as f64);
        let mut out = Vec::new();
        match s.motion {
            MotionForm::Paper => {
                let [li, lr, lo] = s.lambda_iso_rigid_rot;
                // 1/(k|V|) per frame; summed over frames, or their mean.
                let per = |d: usize| match s.reduction {
                    Reduction::Sum => 1.0 / ne,
                    Reduction::Mean => mean(d),
                };
                let (iso, rigid) = ((per(0), km * li), (per(1), km * lr));
                let [vi, vr] = motion::isometry_rigidity(
                    &track,
                    es,
                    &rest,
                    iso,
                    rigid,
                    &mut tg,
                    Some(&mut ge),
                );
                out.push(("key_isometry", km * li * vi));
                out.push(("key_rigidity", km * lr * vr));
                let terms =
                    &mut EdgeTerms { track: &track, edges: es, g: &mut tg, g_edges: Some(&mut ge) };
                let v = motion::relative_rotation(terms, 1, per(1), km * lo);
                out.push(("key_rotation", km * lo * v));
            }
            MotionForm::Release => {
                let terms =
                    &mut EdgeTerms { track: &track, edges: es, g: &mut tg, g_edges: Some(&mut ge) };
                let v = motion::rigidity(terms, 1, mean(1), km);
                out.push(("key_rigidity", km * v));
                let v = motion::relative_rotation(terms, 1, mean(1), km);
                out.push(("key_rotation", km * v));
                let v = motion::isometry(terms, &rest, mean(0), 100.0 * km);
                out.push(("key_isometry", 100.0 * km * v));
                for (name, d, on) in [
                    ("key_rigidity_long", (nt / 2).min(50), nt > 40),
                    ("key_rigidity_10", 10, nt > 20),
                ] {
                    let v = if on { motion::rigidity(terms, d, mean(d), 100.0 * km) } else { 0.0 };
                    out.push((name, 100.0 * km * v));
                }
            }
        }
        tg.scatter(&track, &self.keys, self.n, grads);
        // Chain the per-edge gradients to W (row L1 normalisation) and D.
        let mut g_w = vec![0.0f64; self.ksrc.len()];
        for (k, &e) in kept.iter().enumerate() {
            g_w[e] += ge.w[k];
            self.g_rest[e] += ge.rest[k] as f32;
        }
        if s.motion == MotionForm::Paper {
            self.g_rest.fill(0.0);
        }
        for (_, run) in motion::by_source(&self.ksrc) {
            let sum: f64 = self.w_raw[run.clone()].iter().map(|x| x.abs() as f64).sum();
            if sum > 0.0 {
                let dot: f64 = run.clone().map(|k| g_w[k] * w_all[k]).sum();
                for k in run {
                    let sg = if self.w_raw[k] >= 0.0 { 1.0 } else { -1.0 };
                    self.g_w_raw[k] += (sg * (g_w[k] - dot) / sum) as f32;
                }
            }
        }
        out
    }
}

/// ‖p_b − p_a‖ of Gaussians `a` and `b` in one frame's positions (a canonical rest length).
fn distance(frame: &[[f32; 3]], a: u32, b: u32) -> f64 {
    let (pa, pb) = (frame[a as usize], frame[b as usize]);
    let d = [0, 1, 2].map(|c| (pb[c] - pa[c]) as f64);
    (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::dqb::{self, Dq};
    use crate::math::quat64::tests::TestRng;
    use crate::stages::params::Profile;

    /// T = 22 frames (so the release's Δ = 10 term is on), 3 keys and 4 non-keys, λ = 1.
    fn case(s: GraphSettings) -> (GraphObjective, Poses) {
        case_weighted(s, &|_, _, _, _, w| w)
    }

    /// [`case`] with the table's non-key weights `weight(p°, non-key, t̂, key, default)`.
    fn case_weighted(
        s: GraphSettings,
        weight: &dyn Fn(&Poses, u32, usize, u32, f32) -> f32,
    ) -> (GraphObjective, Poses) {
        let (t, n) = (22, 7);
        let mut rng = TestRng(21);
        let mut p0 = Poses::identity(t, n);
        for k in 0..t * n {
            p0.position[k] = rng.v().map(|x| x as f32);
            p0.rotation[k] = rng.q().map(|x| (x + 0.7) as f32);
        }
        let keys = [0u32, 2, 4];
        let nonkeys = [1u32, 3, 5, 6];
        let key_edges: Vec<(u32, u32, f32)> = keys
            .iter()
            .flat_map(|&a| keys.iter().filter(move |&&b| b != a).map(move |&b| (a, b, 0.5)))
            .collect();
        let t_hat = [3, 0, 7, 1];
        let nonkey_edges: Vec<Vec<(u32, f32)>> =
            [vec![(0, 0.6), (2, 0.4)], vec![(2, 1.0), (4, 1.0), (0, 0.5)], vec![(4, 1.0)], vec![]]
                .into_iter()
                .enumerate()
                .map(|(u, list)| {
                    let node = nonkeys[u];
                    list.into_iter().map(|(k, w)| (k, weight(&p0, node, t_hat[u], k, w))).collect()
                })
                .collect();
        let u: Vec<f32> = (0..t * n).map(|_| (0.55 + 0.45 * rng.next()) as f32).collect();
        let rot: Vec<DMat3> = (0..t)
            .map(|f| DMat3::from_euler(glam::EulerRot::XYZ, 0.1 * f as f64, -0.7, 0.3))
            .collect();
        let ids: Vec<u32> = (100..100 + n as u32).collect();
        let t_hat = t_hat.map(|t| t as u32);
        let inp = GraphInputs {
            anchors: Anchors::of_poses(&p0, u, &nonkeys, &t_hat),
            ids: &ids,
            keys: &keys,
            nonkeys: &nonkeys,
            t_hat: &t_hat,
            nonkey_edges: &nonkey_edges,
            key_edges: &key_edges,
            rot_cw: &rot,
            nonkey_lambda: 1.0,
        };
        let obj = GraphObjective::new(inp, s).unwrap();
        // Move the poses away from p° (and the raw weights off uniform) so no term is at a kink.
        let mut poses = p0.clone();
        for k in 0..t * n {
            for c in 0..3 {
                poses.position[k][c] += (0.2 * rng.next()) as f32;
            }
            for c in 0..4 {
                poses.rotation[k][c] += (0.2 * rng.next()) as f32;
            }
        }
        (obj, poses)
    }

    fn total(obj: &mut GraphObjective, poses: &Poses) -> f64 {
        let mut g = PoseGrads::zeros(poses.frames, poses.n);
        obj.evaluate(poses, &[1, 4, 20], 7, &mut g, &mut PhaseTimes::default())
            .iter()
            .map(|x| x.1)
            .sum()
    }

    #[test]
    fn every_graph_term_matches_finite_differences() {
        let mut fails = Vec::new();
        let mut report = Vec::new();
        let variants = [
            ("paper", GraphSettings::defaults(Profile::Paper)),
            ("release", GraphSettings::defaults(Profile::Release)),
            (
                "release-with-anchors",
                GraphSettings {
                    key_anchor: 1.0,
                    nonkey_anchor: 1.0,
                    ..GraphSettings::defaults(Profile::Release)
                },
            ),
            (
                "no-loss-weighting",
                GraphSettings {
                    anchor_metric: AnchorMetric::Euclidean,
                    ..GraphSettings::defaults(Profile::Paper)
                },
            ),
            (
                "paper-with-most-reliable-metric-frame",
                GraphSettings {
                    nonkey_metric_frame: MetricFrame::MostReliable,
                    ..GraphSettings::defaults(Profile::Paper)
                },
            ),
            (
                "paper-with-current-weights-and-offsets",
                GraphSettings {
                    nonkey_weights: NonkeyWeights::Current,
                    nonkey_pose_offsets: true,
                    ..GraphSettings::defaults(Profile::Paper)
                },
            ),
        ];
        for (name, s) in variants {
            let (mut obj, mut poses) = case(s);
            for k in 0..obj.w_raw.len() {
                obj.w_raw[k] *= 1.0 + 0.3 * (k as f32 * 0.37).sin();
            }
            // θ, Δw and the pose offsets away from their initial values (Δw > 0 keeps the
            // blend weights off the kink of |ŵ + Δw|)
            for (k, x) in obj.theta.iter_mut().enumerate() {
                *x = 1.0 + 0.3 * (k as f32 * 1.3).sin();
            }
            for (k, x) in obj.dw.iter_mut().enumerate() {
                *x = 0.02 + 0.03 * (k as f32 * 0.7).sin().abs();
            }
            for (k, x) in obj.offsets.iter_mut().enumerate() {
                *x = 0.05 * (k as f32 * 0.9).cos();
            }
            let mut g = PoseGrads::zeros(poses.frames, poses.n);
            let terms = obj.evaluate(&poses, &[1, 4, 20], 7, &mut g, &mut PhaseTimes::default());
            assert!(terms.iter().all(|t| t.1.is_finite()), "{name}: {terms:?}");
            let own: Vec<(&str, Vec<f32>)> =
                obj.params_mut().into_iter().map(|p| (p.name, p.grads.to_vec())).collect();
            let h = 1e-4f32;
            let mut worst = 0.0f64;
            let mut check = |what: String, analytic: f64, fp: f64, fm: f64, step: f64| {
                let fd = (fp - fm) / step;
                let err = (analytic - fd).abs();
                let tol = 2e-3 * (1.0 + fd.abs());
                worst = worst.max(err / (1.0 + fd.abs()));
                if err > tol {
                    fails.push(format!("{name} {what}: analytic {analytic} fd {fd}"));
                }
            };
            for k in 0..poses.position.len() {
                for c in 0..7 {
                    let x = get(&poses, k, c);
                    set(&mut poses, k, c, x + h);
                    let xp = get(&poses, k, c);
                    let fp = total(&mut obj, &poses);
                    set(&mut poses, k, c, x - h);
                    let xm = get(&poses, k, c);
                    let fm = total(&mut obj, &poses);
                    set(&mut poses, k, c, x);
                    let a = if c < 3 { g.position[k][c] } else { g.rotation[k][c - 3] };
                    check(format!("pose {k} comp {c}"), a as f64, fp, fm, (xp - xm) as f64);
                }
            }
            for (pi, (pname, grads)) in own.iter().enumerate() {
                for k in 0..grads.len() {
                    let mut eval = |d: f32| {
                        let x = {
                            let mut ps = obj.params_mut();
                            let v = &mut ps[pi].values[k];
                            let x = *v;
                            *v = x + d;
                            (x, *v)
                        };
                        let f = total(&mut obj, &poses);
                        obj.params_mut()[pi].values[k] = x.0;
                        (f, x.1 as f64)
                    };
                    let (fp, xp) = eval(h);
                    let (fm, xm) = eval(-h);
                    check(format!("{pname}[{k}]"), grads[k] as f64, fp, fm, xp - xm);
                }
            }
            report.push(format!("{name}: max rel err {worst:.1e}"));
        }
        eprintln!("graph objective FD: {}", report.join(", "));
        assert!(
            fails.is_empty(),
            "{} failures:\n{}",
            fails.len(),
            fails[..fails.len().min(30)].join("\n")
        );
    }

    #[test]
    fn the_most_reliable_metric_frame_weighs_every_frame_as_the_nonkeys_t_hat() {
        // non-key pose 1 has t̂ = 3; key pose 0 keeps its own frames
        let d = [0.03f32, -0.02, 0.05];
        let grads = |frame: MetricFrame| {
            let s = GraphSettings {
                nonkey_metric_frame: frame,
                ..GraphSettings::defaults(Profile::Paper)
            };
            let (obj, _) = case(s);
            let (n, mut poses) = (obj.n, obj_p0(&obj));
            for (t, i) in [(3, 1), (9, 1), (3, 0), (9, 0)] {
                (0..3).for_each(|c| poses.position[t * n + i][c] += d[c]);
            }
            let mut g = PoseGrads::zeros(poses.frames, n);
            obj.anchors(&poses, [1.0, 1.0], &mut g);
            [(3, 1), (9, 1), (3, 0), (9, 0)].map(|(t, i)| g.position[t * n + i])
        };
        let close = |a: [f32; 3], b: [f32; 3]| {
            (0..3).all(|c| (a[c] - b[c]).abs() <= 1e-4 * a[c].abs().max(1.0))
        };
        let [own3, own9, key3, key9] = grads(MetricFrame::Each);
        let [fix3, fix9, fkey3, fkey9] = grads(MetricFrame::MostReliable);
        assert!(!close(own3, own9), "each frame's own U: {own3:?} vs {own9:?}");
        assert!(close(fix3, fix9), "t̂'s U at frame 9: {fix3:?} vs {fix9:?}");
        assert_eq!((own3, key3, key9), (fix3, fkey3, fkey9), "t̂ itself and the keys are unchanged");
    }

    /// p° of the objective as poses (rotations identity: the anchors read positions only).
    fn obj_p0(obj: &GraphObjective) -> Poses {
        let mut p = Poses::identity(obj.frames, obj.n);
        p.position.clone_from(&obj.p0);
        p
    }

    fn get(p: &Poses, k: usize, c: usize) -> f32 {
        if c < 3 { p.position[k][c] } else { p.rotation[k][c - 3] }
    }

    fn set(p: &mut Poses, k: usize, c: usize, v: f32) {
        if c < 3 { p.position[k][c] = v } else { p.rotation[k][c - 3] = v }
    }

    /// Timing at the brief's size: T = 121, N = 20,000 (400 keys), batch 8. Run with
    /// `cargo test --release --lib evaluate_timing -- --ignored --nocapture`.
    #[test]
    #[ignore = "timing, not a check"]
    fn evaluate_timing_t121_n20k() {
        let (t, n, nk) = (121, 20_000, 400);
        let mut rng = TestRng(5);
        let mut p0 = Poses::identity(t, n);
        for k in 0..t * n {
            p0.position[k] = rng.v().map(|x| x as f32);
            p0.rotation[k] = rng.q().map(|x| (x + 0.7) as f32);
        }
        let keys: Vec<u32> = (0..nk as u32).map(|k| k * 50).collect();
        let nonkeys: Vec<u32> = (0..n as u32).filter(|i| i % 50 != 0).collect();
        let u: Vec<f32> = (0..t * n).map(|_| (0.55 + 0.45 * rng.next()) as f32).collect();
        let rot = vec![DMat3::IDENTITY; t];
        let ids: Vec<u32> = (0..n as u32).collect();
        let t_hat: Vec<u32> = nonkeys.iter().map(|i| i % t as u32).collect();
        let nonkey_edges: Vec<Vec<(u32, f32)>> = nonkeys
            .iter()
            .map(|i| (0..5).map(|j| (keys[(*i as usize / 50 + j) % nk], 0.2)).collect())
            .collect();
        for (profile, k) in [(Profile::Paper, 8), (Profile::Release, 120)] {
            let key_edges: Vec<(u32, u32, f32)> = (0..nk)
                .flat_map(|a| (1..=k).map(move |d| (a, (a + d) % nk)))
                .map(|(a, b)| (keys[a], keys[b], 1.0))
                .collect();
            let inp = GraphInputs {
                anchors: Anchors::of_poses(&p0, u.clone(), &nonkeys, &t_hat),
                ids: &ids,
                keys: &keys,
                nonkeys: &nonkeys,
                t_hat: &t_hat,
                nonkey_edges: &nonkey_edges,
                key_edges: &key_edges,
                rot_cw: &rot,
                nonkey_lambda: 100.0,
            };
            let mut obj = GraphObjective::new(inp, GraphSettings::defaults(profile)).unwrap();
            let mut g = PoseGrads::zeros(t, n);
            let frames = [3, 17, 30, 44, 58, 71, 90, 111];
            let start = std::time::Instant::now();
            let reps = 3;
            for r in 0..reps {
                g.clear();
                obj.evaluate(&p0, &frames, r, &mut g, &mut PhaseTimes::default());
            }
            let ms = start.elapsed().as_secs_f64() * 1e3 / reps as f64;
            let part = |f: &mut dyn FnMut()| {
                let s = std::time::Instant::now();
                f();
                s.elapsed().as_secs_f64() * 1e3
            };
            let smooth = part(&mut || {
                obj.smoothness(&p0, &mut g);
            });
            let dqb_ms = part(&mut || {
                obj.dqb_terms(&p0, &frames, &mut g);
            });
            let key_ms = part(&mut || {
                obj.key_motion(&p0, 1, &mut g);
            });
            let anchor_ms = part(&mut || {
                obj.anchors(&p0, [1.0, 1.0], &mut g);
            });
            eprintln!(
                "  smoothness {smooth:.0} ms, DQB {dqb_ms:.0} ms, key motion {key_ms:.0} ms, anchors {anchor_ms:.0} ms"
            );
            eprintln!(
                "evaluate {profile:?} (key k = {k}): {ms:.0} ms, {} threads",
                rayon::current_num_threads()
            );
        }
    }

    #[test]
    fn a_rebuilt_objective_keeps_the_trained_lengths_sharpness_offsets_and_source_poses() {
        let (mut old, _) = case(GraphSettings::defaults(Profile::Release));
        old.rest.iter_mut().enumerate().for_each(|(e, d)| *d = 10.0 + e as f32);
        old.src_p.iter_mut().enumerate().for_each(|(k, x)| *x = -1.0 - k as f32);
        old.src_q.iter_mut().for_each(|x| *x = 0.5);
        old.theta.iter_mut().enumerate().for_each(|(k, x)| *x = 2.0 + k as f32);
        old.dw.iter_mut().enumerate().for_each(|(e, x)| *x = 0.1 * e as f32);
        old.offsets.iter_mut().enumerate().for_each(|(k, x)| *x = 0.01 * k as f32);
        old.nk_w.iter_mut().for_each(|x| *x = 0.25);
        let (mut new, _) = case(GraphSettings::defaults(Profile::Release));
        // the new objective's last non-key is Gaussian 200, created from 101
        new.ids[6] = 200;
        new.carry_over(&old, |id| if id == 200 { 101 } else { id });
        assert_eq!(new.rest, old.rest);
        assert!(new.src_q.iter().all(|&x| x == 0.5));
        assert_eq!(new.theta, old.theta, "θ by key id");
        let at = |o: &GraphObjective, id: u32| {
            o.nonkeys.iter().position(|&i| o.ids[i as usize] == id).unwrap()
        };
        for (id, from) in [(101, 101), (103, 103), (105, 105), (200, 101)] {
            let (u, v) = (at(&new, id), at(&old, from));
            assert_eq!(new.src_p[3 * u..3 * u + 3], old.src_p[3 * v..3 * v + 3], "{id}");
            assert_eq!(new.offsets[7 * u..7 * u + 7], old.offsets[7 * v..7 * v + 7], "{id}");
            // 200 has no edges (it is the case's edgeless non-key), 101-105 keep their Δw
            let (a, b) = (new.nk_off[u], new.nk_off[u + 1]);
            if id != 200 {
                assert_eq!(new.dw[a..b], old.dw[old.nk_off[v]..old.nk_off[v + 1]], "{id}");
            }
        }
        assert!(new.nk_w.iter().all(|&w| w == 0.25), "the table weights, the base of θ and Δw");
    }

    /// The DQB terms with only them on, Euclidean, summed: (position, rotation).
    fn dqb_only(s: GraphSettings) -> GraphSettings {
        GraphSettings {
            anchor_metric: AnchorMetric::Euclidean,
            reduction: Reduction::Sum,
            key_anchor: 0.0,
            nonkey_anchor: 0.0,
            dqb: 1.0,
            dqb_rotation: 1.0,
            key_motion: 0.0,
            lambda_vel_acc: [0.0; 2],
            ..s
        }
    }

    /// The DQB terms on `poses` as computed before θ, Δw and the pose offsets existed: per
    /// non-key and frame, each edge's own relative transform, the given weights `w` `[E_n]`
    /// (normalised per non-key), [`dqb::warp`], Euclidean, summed.
    fn todays_dqb(obj: &GraphObjective, poses: &Poses, frames: &[usize], w: &[f64]) -> [f64; 2] {
        let mut out = [0.0; 2];
        let pose = |t: usize, i: usize| {
            let o = t * obj.n + i;
            dqb::from_pose(q4::q64(poses.rotation[o]), q4::v64(poses.position[o])).0
        };
        for (u, &node) in obj.nonkeys.iter().enumerate() {
            let (a, b) = (obj.nk_off[u], obj.nk_off[u + 1]);
            if a == b {
                continue;
            }
            let th = obj.t_hat[u] as usize;
            for &t in frames {
                let rel: Vec<Dq> = (a..b)
                    .map(|e| {
                        let key = obj.keys[obj.nk_key[e] as usize] as usize;
                        dqb::relative(&pose(t, key), &pose(th, key)).0
                    })
                    .collect();
                let sp = [0, 1, 2].map(|c| obj.src_p[3 * u + c] as f64);
                let sq = [0, 1, 2, 3].map(|c| obj.src_q[4 * u + c] as f64);
                let r = dqb::warp(&rel, &w[a..b], sp, sq);
                let o = t * obj.n + node as usize;
                let x = [0, 1, 2].map(|c| poses.position[o][c] as f64 - r.p[c]);
                out[0] += (x.iter().map(|v| v * v).sum::<f64>() + 1e-8).sqrt();
                let (qu, _) = q4::normalize(q4::q64(poses.rotation[o]));
                out[1] += q4::norm([0, 1, 2, 3].map(|c| r.q[c] - qu[c]));
            }
        }
        out
    }

    fn dqb_terms_of(obj: &mut GraphObjective, poses: &Poses, frames: &[usize]) -> [f64; 2] {
        let mut g = PoseGrads::zeros(poses.frames, poses.n);
        let terms = obj.evaluate(poses, frames, 3, &mut g, &mut PhaseTimes::default());
        let get = |name: &str| terms.iter().find(|t| t.0 == name).unwrap().1;
        [get("nonkey_dqb"), get("nonkey_dqb_rotation")]
    }

    #[test]
    fn at_unit_sharpness_and_zero_offsets_the_dqb_terms_are_todays() {
        let frames = [1, 4, 20, 4];
        let s = GraphSettings {
            nonkey_weights: NonkeyWeights::Table,
            ..dqb_only(GraphSettings::defaults(Profile::Release))
        };
        let (mut obj, poses) = case(s);
        assert!(obj.s.nonkey_pose_offsets && obj.offsets.iter().all(|&x| x == 0.0));
        let table = obj.nk_w.clone();
        let got = dqb_terms_of(&mut obj, &poses, &frames);
        let want = todays_dqb(&obj, &poses, &frames, &table);
        for k in 0..2 {
            assert!((got[k] - want[k]).abs() < 1e-12 * want[k].abs(), "{got:?} vs {want:?}");
        }
        let mut by_edge = HashMap::new();
        for (u, &i) in obj.nonkeys.iter().enumerate() {
            for e in obj.nk_off[u]..obj.nk_off[u + 1] {
                let key = obj.keys[obj.nk_key[e] as usize];
                by_edge.insert((obj.ids[i as usize], obj.ids[key as usize]), table[e] as f32);
            }
        }
        let learned = obj.learned_edges();
        let nonkey_edges = (0..learned.len()).filter(|&e| learned.kind[e] == EdgeKind::NonkeyKey);
        let mut srcs = Vec::new();
        for e in nonkey_edges {
            assert_eq!(learned.weight[e], by_edge[&(learned.src[e], learned.dst[e])]);
            srcs.push(learned.src[e]);
        }
        srcs.dedup();
        assert_eq!(srcs, [101, 103, 105], "in the inputs' order");
    }

    #[test]
    fn current_weights_at_the_prior_are_the_tables_exp_minus_lambda_d2() {
        // the table's weights as the edges stage makes them at p° (λ = 1), normalised by new()
        let table = |p0: &Poses, node: u32, th: usize, key: u32, _: f32| {
            let d2 = dqb_term::dist2(p0.p(th, node as usize), p0.p(th, key as usize));
            (-d2).exp() as f32
        };
        let s = dqb_only(GraphSettings::defaults(Profile::Release));
        let (mut obj, _) = case_weighted(s, &table);
        let (mut p0, frames) = (Poses::identity(obj.frames, obj.n), [0, 7, 13]);
        p0.position.clone_from(&obj.p0);
        let (mut todays, _) = case_weighted(
            GraphSettings { nonkey_weights: NonkeyWeights::Table, ..obj.s.clone() },
            &table,
        );
        for e in 0..obj.nk_w.len() {
            assert!((obj.nk_w_eff[e] - obj.nk_w[e]).abs() < 1e-6, "edge {e}");
        }
        // the same poses (p° positions) through both objectives
        let got = dqb_terms_of(&mut obj, &p0, &frames);
        let want = dqb_terms_of(&mut todays, &p0, &frames);
        for k in 0..2 {
            assert!((got[k] - want[k]).abs() < 1e-6 * want[k].abs(), "{got:?} vs {want:?}");
        }
    }

    /// L^{motion,non-key} is zero when the whole graph moves as one rigid body from the
    /// canonical frame, and a non-key leaving its keys' rigid motion at a batch frame raises
    /// its isometry and rigidity, not the keys' isometry; at another frame it does not count.
    #[test]
    fn nonkey_motion_is_zero_for_a_rigid_motion_and_sees_a_displaced_nonkey() {
        // p° at frame 0 (the canonical frame of the rest lengths), any rotations
        let (mut obj, p0) = case(GraphSettings::defaults(Profile::Paper));
        let mut poses = p0.clone();
        for t in 0..p0.frames {
            let a = 0.1 * t as f64;
            let r = q4::normalize4([a.cos(), 0.3 * a.sin(), a.sin(), -0.2 * a.sin()]);
            for i in 0..p0.n {
                let x = obj.p0[i].map(|c| c as f64);
                let p = q4::rotate(r, x);
                poses.position[t * p0.n + i] = [p[0] + 0.5 * a, p[1], p[2] - a].map(|c| c as f32);
                let q = p0.q(0, i).map(|c| c as f64);
                poses.rotation[t * p0.n + i] = q4::mul(r, q).map(|c| c as f32);
            }
        }
        let terms = |obj: &mut GraphObjective, poses: &Poses| {
            let mut g = PoseGrads::zeros(poses.frames, poses.n);
            let all = obj.evaluate(poses, &[0, 5], 7, &mut g, &mut PhaseTimes::default());
            let get = |name: &str| all.iter().find(|x| x.0 == name).map(|x| x.1).unwrap();
            ["nonkey_isometry", "nonkey_rigidity", "nonkey_rotation", "key_isometry"].map(get)
        };
        let rigid = terms(&mut obj, &poses);
        assert!(rigid.iter().all(|&v| v.abs() < 1e-5), "{rigid:?}");
        poses.position[5 * p0.n + 3][1] += 0.3; // non-key 3 at frame 5, a batch frame
        let moved = terms(&mut obj, &poses);
        assert!(moved[0] > 0.01 && moved[1] > 0.01, "{moved:?}");
        assert!(moved[3].abs() < 1e-5, "{moved:?}");
        poses.position[5 * p0.n + 3][1] -= 0.3;
        poses.position[7 * p0.n + 3][1] += 0.3; // and at frame 7, outside the batch
        let outside = terms(&mut obj, &poses);
        assert!(outside.iter().all(|&v| v.abs() < 1e-5), "{outside:?}");
        let off = GraphSettings { nonkey_motion: 0.0, ..GraphSettings::defaults(Profile::Paper) };
        let (mut obj, _) = case(off);
        let mut g = PoseGrads::zeros(poses.frames, poses.n);
        let all = obj.evaluate(&poses, &[1, 4], 7, &mut g, &mut PhaseTimes::default());
        assert!(all.iter().all(|x| !x.0.starts_with("nonkey_iso")), "{all:?}");
    }

    #[test]
    fn graph_terms_do_not_depend_on_the_thread_count() {
        let run = |threads: usize, profile: Profile| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (mut obj, poses) = case(GraphSettings::defaults(profile));
                let mut g = PoseGrads::zeros(poses.frames, poses.n);
                let terms =
                    obj.evaluate(&poses, &[1, 4, 20], 7, &mut g, &mut PhaseTimes::default());
                let bits = |v: &mut dyn Iterator<Item = f32>| v.map(f32::to_bits).collect();
                let pose: Vec<u32> = bits(
                    &mut g.position.iter().flatten().chain(g.rotation.iter().flatten()).copied(),
                );
                let own: Vec<u32> =
                    bits(&mut obj.params_mut().iter().flat_map(|p| p.grads.to_vec()));
                (terms.iter().map(|t| t.1.to_bits()).collect::<Vec<_>>(), pose, own)
            })
        };
        for profile in [Profile::Paper, Profile::Release] {
            assert_eq!(run(1, profile), run(3, profile), "{profile:?}");
        }
    }

    #[test]
    fn learned_edges_are_normalised_per_source() {
        let (obj, _) = case(GraphSettings::defaults(Profile::Release));
        let edges = obj.learned_edges();
        let rest: Vec<f32> = edges.rest_length.iter().flatten().copied().collect();
        assert_eq!(rest, obj.rest, "the key-key edges carry their learned lengths");
        let kk: f32 = (0..edges.len())
            .filter(|&e| edges.kind[e] == EdgeKind::KeyKey && edges.src[e] == 100)
            .map(|e| edges.weight[e])
            .sum();
        assert!((kk - 1.0).abs() < 1e-6);
        assert_eq!(edges.len(), 6 + 6);
    }
}
