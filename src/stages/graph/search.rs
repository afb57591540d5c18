//! Exact nearest-key searches of the edge stage, each with an accelerated version and the
//! brute-force reference it must equal (tests and `usplat4d bench graph` compare them).
//!
//! Positions are searched in the transformed space q = M_t p of the metric's
//! [`MetricForm`]: B_t = diag(r)^{1/2} R_cw for `weight`, A_t = diag(r)^{-1/2} R_cw for
//! `inverse`. A frame's squared cost is then s(‖Δq‖², u_i + u_l) with s(x, v) = x·v
//! (`weight`) or x/v (`inverse`), [`MetricForm::scale`]. For a set of keys, let u_b be
//! u_min (`weight`) or u_max (`inverse`) of the set ([`MetricForm::bound_u`]): since s is
//! non-decreasing in x and s(x, u_i + u_b) ≤ s(x, u_i + u_l) for every member l (IEEE
//! rounding is monotone, so this holds for the computed floats), s(d_lo, u_i + u_b) is a
//! lower bound of every member's cost whenever d_lo ≤ its ‖Δq‖.
//!
//! All searches rank keys by a total order `(cost, key index)`, so ties are broken the same
//! way by every path. Exactness arguments, one per search:
//! - [`knn_at_frame`] (Eq. 7 and the single-frame release/ablation variants): kiddo returns
//!   the m nearest eligible keys in q, the last at squared distance R². Every key it did
//!   not return has ‖Δq‖² ≥ R², hence cost ≥ s(R², u_i + u_b), u_b over the keys eligible at
//!   t (unweighted metrics: cost ≥ R²). When the k-th exact cost is below that bound (with
//!   a 1e-5 relative margin on R² for kiddo's own rounding) no unseen key can enter the top
//!   k; otherwise m doubles, up to all keys.
//! - [`argmin_sum`] (Eq. 8): keys sit in a binary tree ([`key_tree`]: a k-d tree of the
//!   trajectories, median splits along the frame and axis of widest spread, leaves of ≤ 8
//!   keys). Per frame t a node stores the bounding box (in q) of its members counted at t
//!   and their u_b. For a member l counted at t, dist(q_t, box_t) ≤ ‖q_t − q_{l,t}‖, so
//!   c_t = s(dist, √(u_t + u_b,t)) ≤ s(‖Δq‖, √(u_t + u_{l,t})), l's frame-t term; all
//!   terms are ≥ 0. Hence every member's cost is at least the node bound Σ_{t∈F} c_t for
//!   any set F of frames where all members are counted (large nodes, > 32 keys, use only
//!   the query's 32 heaviest frames; smaller ones all such frames). A child's members are
//!   the parent's, so max(parent, child) bounds them too. Nodes are visited best-first by
//!   increasing bound; the search stops when the smallest pending bound exceeds the best
//!   cost so far, so every key left unvisited has a cost above it and cannot be the
//!   argmin, even on a tie. In a leaf, a key is evaluated exactly ([`sum_cost`], the
//!   reference's own float operations and order) unless a partial sum of its terms
//!   already exceeds the best cost. Bounds and partial sums run over chunks of 8 frames
//!   (vectorised, in a structure-of-arrays layout), the query's heaviest chunks first
//!   (for `weight`, where the query is unreliable), with one square root per term
//!   (√(x·v) for √x·√v): they differ from exact terms by rounding only, so they prune
//!   with a 10⁻³ relative margin (f32 rounding of T ≤ 10⁴ non-negative terms stays
//!   below it). The final comparison uses exact costs and the `(cost, key)` order.
//!   Eq. 8 sums over all frames (the paper's Σ_{t=0}^{T−1}) whatever the form. Which
//!   frames a node counts only tightens the bounds: `inverse` counts the frames where the
//!   member is eligible (reliable), since an unreliable frame's term (u = φ) is ≈ 0 and
//!   would only inflate the box; `weight` counts every frame, since there an unreliable
//!   frame gives a large term (the paper's intent: a rarely seen key is a poor anchor).
//! - [`knn_max`] (release non-key assignment): the cost is a maximum over the key's
//!   confident frames, so one of its terms (frame τ_l, a confident frame of key l) is a
//!   lower bound computed by the same float operations; keys whose bound exceeds the current
//!   k-th best are skipped, and running maxima stop when they exceed it.

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::metric::MetricForm;

/// Per-key, per-frame data of the K key nodes, key-major `[K, T]`.
#[derive(Debug, Clone, Default)]
pub struct KeyFrames {
    /// Number of keys K.
    pub num_keys: usize,
    /// Number of frames T.
    pub num_frames: usize,
    /// Positions in the search space (world, or B_t·p / A_t·p for the Mahalanobis metrics)
    /// `[K, T]`.
    pub q: Vec<[f32; 3]>,
    /// Uncertainty u `[K, T]`.
    pub u: Vec<f32>,
    /// Whether the key may be a neighbour at frame t (reliable / confident) `[K, T]`.
    pub eligible: Vec<bool>,
}

impl KeyFrames {
    fn at(&self, l: usize, t: usize) -> usize {
        l * self.num_frames + t
    }
}

/// Squared distance of two points (the one formula every path uses).
#[inline]
pub fn dist2(a: [f32; 3], b: [f32; 3]) -> f32 {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    x * x + y * y + z * z
}

/// Squared cost of Eq. 7 between a query (q, u) and key `l` at frame `t`:
/// s(‖Δq‖², u_i + u_l) for the metric `form` (see the module doc), or ‖Δq‖² when `None`.
#[inline]
fn frame_cost(
    kf: &KeyFrames,
    q: [f32; 3],
    u: f32,
    l: usize,
    t: usize,
    form: Option<MetricForm>,
) -> f32 {
    let d2 = dist2(q, kf.q[kf.at(l, t)]);
    match form {
        Some(f) => f.scale(d2, u + kf.u[kf.at(l, t)]),
        None => d2,
    }
}

/// Insert `(cost, l)` into `best` (ascending, at most `k` entries).
fn push_top(best: &mut Vec<(f32, u32)>, k: usize, c: (f32, u32)) {
    let pos = best.partition_point(|b| lt(*b, c));
    if pos < k {
        best.insert(pos, c);
        best.truncate(k);
    }
}

/// The total order of (cost, index) pairs.
#[inline]
fn lt(a: (f32, u32), b: (f32, u32)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// A kiddo tree over the eligible keys of one frame.
pub struct FrameTree {
    tree: Option<ImmutableKdTree<f32, 3>>,
    members: Vec<u32>,
    u_min: f32,
    u_max: f32,
}

/// One [`FrameTree`] per frame `[T]`.
pub fn frame_trees(kf: &KeyFrames) -> Vec<FrameTree> {
    (0..kf.num_frames)
        .into_par_iter()
        .map(|t| {
            let members: Vec<u32> =
                (0..kf.num_keys).filter(|&l| kf.eligible[kf.at(l, t)]).map(|l| l as u32).collect();
            let pts: Vec<[f32; 3]> = members.iter().map(|&l| kf.q[kf.at(l as usize, t)]).collect();
            let us = members.iter().map(|&l| kf.u[kf.at(l as usize, t)]);
            let u_min = us.clone().fold(f32::INFINITY, f32::min);
            let u_max = us.fold(0.0f32, f32::max);
            let tree =
                if pts.is_empty() { None } else { ImmutableKdTree::new_from_slice(&pts).ok() };
            FrameTree { tree, members, u_min, u_max }
        })
        .collect()
}

impl FrameTree {
    /// The `m` eligible keys nearest to `q` (by kiddo) and the squared distance of the last.
    pub fn nearest(&self, q: [f32; 3], m: usize) -> (Vec<u32>, f32) {
        match (&self.tree, NonZero::new(m)) {
            (Some(tree), Some(m)) => {
                let res = tree.query(&q).nearest_n::<SquaredEuclidean<f32>>(m).execute();
                let last = res.last().map_or(0.0, |r| r.distance);
                (res.iter().map(|r| self.members[r.item as usize]).collect(), last)
            }
            _ => (Vec::new(), 0.0),
        }
    }
}

/// A query of [`knn_at_frame`]: the `k` eligible keys of lowest cost at frame `t` for a
/// point `q` with uncertainty `u` (Eq. 7 in the metric `form` when `Some`; plain Euclidean
/// kNN when `None`), `exclude` left out.
#[derive(Debug, Clone, Copy)]
pub struct FrameQuery {
    /// The query point at frame `t`.
    pub q: [f32; 3],
    /// Its uncertainty at frame `t`.
    pub u: f32,
    /// The frame.
    pub t: usize,
    /// A key left out (the query key itself).
    pub exclude: Option<u32>,
    /// Neighbours wanted.
    pub k: usize,
    /// The metric of Eq. 7, or `None` for Euclidean.
    pub form: Option<MetricForm>,
}

/// Brute-force reference of [`knn_at_frame`].
pub fn knn_at_frame_brute(kf: &KeyFrames, query: &FrameQuery) -> Vec<(f32, u32)> {
    let FrameQuery { q, u, t, exclude, k, form } = *query;
    let mut best = Vec::with_capacity(k + 1);
    for l in 0..kf.num_keys {
        if Some(l as u32) == exclude || !kf.eligible[kf.at(l, t)] {
            continue;
        }
        push_top(&mut best, k, (frame_cost(kf, q, u, l, t, form), l as u32));
    }
    best
}

/// The answer to `query` ([`FrameQuery`]) from the eligible keys' tree of its frame.
/// Equals [`knn_at_frame_brute`] (see the module doc for the argument).
pub fn knn_at_frame(kf: &KeyFrames, tree: &FrameTree, query: &FrameQuery) -> Vec<(f32, u32)> {
    let FrameQuery { q, u, t, exclude, k, form } = *query;
    let total = tree.members.len();
    if k == 0 {
        return Vec::new();
    }
    let mut m = (k + 1).min(total);
    loop {
        let (found, r2) = tree.nearest(q, m);
        let mut best = Vec::with_capacity(k + 1);
        for &l in &found {
            if Some(l) != exclude {
                push_top(&mut best, k, (frame_cost(kf, q, u, l as usize, t, form), l));
            }
        }
        if m >= total {
            return best;
        }
        let r2 = r2 * (1.0 - 1e-5);
        let bound = match form {
            Some(f) => f.scale(r2, u + f.bound_u(tree.u_min, tree.u_max)),
            None => r2,
        };
        if best.len() == k && best[k - 1].0 < bound {
            return best;
        }
        m = (m * 2).min(total);
    }
}

/// Eq. 8's cost Σ_t s(‖q_t − q_{l,t}‖, √(u_t + u_{l,t})) of key `l` for a query trajectory
/// (`q` `[T]`, `u` `[T]`) in the metric `form`, over all frames; stops early once the
/// partial sum exceeds `stop`. Terms and sum are in f64 (issue 15 item 5): in f32, where
/// the query is unseen (u_t = φ = 1e8) φ + u_{l,t} rounds to φ for any u_{l,t} below 4, so
/// the key's reliability at those frames was lost, and those frames, weighted by √φ,
/// dominate the sum; f64 keeps u_{l,t} there (φ + 0.01 is exact to 10⁻⁸).
pub fn sum_cost(
    kf: &KeyFrames,
    q: &[[f32; 3]],
    u: &[f32],
    l: usize,
    stop: f64,
    form: MetricForm,
) -> f64 {
    let mut s = 0.0f64;
    for t in 0..kf.num_frames {
        let i = kf.at(l, t);
        let d = (dist2(q[t], kf.q[i]) as f64).sqrt();
        let v = (u[t] as f64 + kf.u[i] as f64).sqrt();
        s += match form {
            MetricForm::Weight => d * v,
            MetricForm::Inverse => d / v,
        };
        if s > stop {
            break;
        }
    }
    s
}

/// The total order of (Eq. 8 cost, key) pairs.
#[inline]
fn lt64(a: (f64, u32), b: (f64, u32)) -> bool {
    a.0 < b.0 || (a.0 == b.0 && a.1 < b.1)
}

/// Brute-force reference of [`argmin_sum`]: `(cost, key)` of the lowest Eq. 8 cost.
pub fn argmin_sum_brute(
    kf: &KeyFrames,
    q: &[[f32; 3]],
    u: &[f32],
    form: MetricForm,
) -> Option<(f64, u32)> {
    let mut best: Option<(f64, u32)> = None;
    for l in 0..kf.num_keys {
        let c = (sum_cost(kf, q, u, l, f64::INFINITY, form), l as u32);
        if best.is_none_or(|b| lt64(c, b)) {
            best = Some(c);
        }
    }
    best
}

/// Relative margin of the Eq. 8 bounds: a bound `b` prunes a best cost `c` only when
/// `b·(1 − MARGIN) > c`. Bounds are summed in another order than [`sum_cost`] and with
/// one square root per term; f32 rounding of T ≤ 10⁴ non-negative terms, each off by a
/// few ulps, stays far below 10⁻³.
const MARGIN: f32 = 1e-3;

/// Frames per chunk: bounds and partial sums are computed 8 frames at a time
/// (vectorisable), and compared with the best cost once per chunk.
const CHUNK: usize = 8;

/// Nodes with more members than this are bounded on their first [`BIG_CHUNKS`] chunks
/// only (a weaker but valid bound; near the root the boxes are wide anyway).
const BIG_NODE: usize = 32;

/// Chunks of the bound of a node larger than [`BIG_NODE`].
const BIG_CHUNKS: usize = 4;

/// Coordinates of a node's per-frame bounds in [`KeyTree::bounds`].
const LO: usize = 0;
const HI: usize = 3;
const UB: usize = 6;
const ARRAYS: usize = 7;

/// One node of a [`KeyTree`]: members `order[start..end]`, children (none for a leaf).
#[derive(Debug, Clone, Copy)]
struct Node {
    start: u32,
    end: u32,
    children: Option<(u32, u32)>,
}

/// A binary tree over the keys' trajectories, each node with per-frame bounding boxes (in
/// q) and bounding u, for the Eq. 8 search in one metric form.
#[derive(Debug, Clone)]
pub struct KeyTree {
    /// The metric form the bounds are for.
    form: MetricForm,
    /// T rounded up to whole chunks, `T_p`.
    padded: usize,
    /// Keys, permuted so that every node holds a contiguous range `[K]`.
    order: Vec<u32>,
    /// Nodes, the root first.
    nodes: Vec<Node>,
    /// Per node, seven arrays of `[T_p]` (`[nodes, 7, T_p]`): the box's lo x, y, z, hi x,
    /// y, z, and u_b. Frames where not every member is counted (and padding frames) hold
    /// the unbounded box (−∞, +∞) and u_b = 1, so their bound term is 0.
    bounds: Vec<f32>,
    /// The keys' trajectories in the layout of [`Query`] (`[K, 4, T_p]`: x, y, z, u), for
    /// the partial sums.
    keys: Vec<f32>,
}

/// Build the [`KeyTree`] of the keys for the metric `form`: recursive median splits, each
/// along the coordinate (frame t, axis k) of q in which the node's members spread widest
/// (a k-d tree of the trajectories in R^{3T}, so keys that stay close over all frames
/// share nodes), down to leaves of at most `leaf_size` keys. A member is counted at t when
/// eligible there (`inverse`) or always (`weight`), see the module doc. Memory:
/// `28·T` bytes per node, fewer than 4K/`leaf_size` nodes.
pub fn key_tree(kf: &KeyFrames, leaf_size: usize, form: MetricForm) -> KeyTree {
    let nt = kf.num_frames;
    let padded = nt.div_ceil(CHUNK) * CHUNK;
    let counted = |i: usize| form == MetricForm::Weight || kf.eligible[i];
    let mut tree = KeyTree {
        form,
        padded,
        order: (0..kf.num_keys as u32).collect(),
        nodes: Vec::new(),
        bounds: Vec::new(),
        keys: Vec::new(),
    };
    if kf.num_keys == 0 {
        return tree;
    }
    tree.nodes.push(Node { start: 0, end: kf.num_keys as u32, children: None });
    let mut stack = vec![0usize];
    while let Some(id) = stack.pop() {
        let Node { start, end, .. } = tree.nodes[id];
        let members = &mut tree.order[start as usize..end as usize];
        if members.len() <= leaf_size.max(1) || nt == 0 {
            continue;
        }
        let (mut widest, mut axis) = (f32::NEG_INFINITY, (0, 0));
        for t in 0..nt {
            for k in 0..3 {
                let (lo, hi) = members.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |a, &l| {
                    let v = kf.q[kf.at(l as usize, t)][k];
                    (a.0.min(v), a.1.max(v))
                });
                if hi - lo > widest {
                    (widest, axis) = (hi - lo, (t, k));
                }
            }
        }
        let mid = members.len() / 2;
        let coord = |l: u32| kf.q[kf.at(l as usize, axis.0)][axis.1];
        members.select_nth_unstable_by(mid, |&a, &b| coord(a).total_cmp(&coord(b)).then(a.cmp(&b)));
        let (a, b) = (tree.nodes.len(), tree.nodes.len() + 1);
        tree.nodes.push(Node { start, end: start + mid as u32, children: None });
        tree.nodes.push(Node { start: start + mid as u32, end, children: None });
        tree.nodes[id].children = Some((a as u32, b as u32));
        stack.extend([b, a]);
    }
    let bounds: Vec<Vec<f32>> = tree
        .nodes
        .par_iter()
        .map(|node| {
            let members = &tree.order[node.start as usize..node.end as usize];
            let mut b = vec![0.0f32; ARRAYS * padded];
            for t in 0..padded {
                let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
                let (mut u_min, mut u_max, mut all) = (f32::INFINITY, 0.0f32, t < nt);
                for &l in members.iter().filter(|_| t < nt) {
                    let i = kf.at(l as usize, t);
                    if !counted(i) {
                        all = false;
                        continue;
                    }
                    for k in 0..3 {
                        lo[k] = lo[k].min(kf.q[i][k]);
                        hi[k] = hi[k].max(kf.q[i][k]);
                    }
                    u_min = u_min.min(kf.u[i]);
                    u_max = u_max.max(kf.u[i]);
                }
                for k in 0..3 {
                    b[(LO + k) * padded + t] = if all { lo[k] } else { f32::NEG_INFINITY };
                    b[(HI + k) * padded + t] = if all { hi[k] } else { f32::INFINITY };
                }
                b[UB * padded + t] = if all { form.bound_u(u_min, u_max) } else { 1.0 };
            }
            b
        })
        .collect();
    tree.bounds = bounds.concat();
    tree.keys = (0..kf.num_keys)
        .flat_map(|l| {
            let traj = &kf.q[kf.at(l, 0)..kf.at(l, 0) + nt];
            let u = &kf.u[kf.at(l, 0)..kf.at(l, 0) + nt];
            Query::new(traj, u, padded).soa
        })
        .collect();
    tree
}

/// A query trajectory in chunked structure-of-arrays form `[4, T_p]` (x, y, z, u; padding
/// frames at the origin with u = 1).
struct Query {
    soa: Vec<f32>,
    padded: usize,
}

impl Query {
    fn new(q: &[[f32; 3]], u: &[f32], padded: usize) -> Self {
        let mut soa = vec![0.0f32; 4 * padded];
        soa[3 * padded..].fill(1.0);
        for t in 0..q.len() {
            for k in 0..3 {
                soa[k * padded + t] = q[t][k];
            }
            soa[3 * padded + t] = u[t];
        }
        Query { soa, padded }
    }

    /// Array `a` (0..3: x, y, z, u) of chunk `c`.
    #[inline(always)]
    fn get(&self, a: usize, c: usize) -> &[f32; CHUNK] {
        let s = a * self.padded + c * CHUNK;
        self.soa[s..s + CHUNK].try_into().expect("chunk")
    }
}

/// Σ over one chunk of √s(‖x − clamp(x, lo, hi)‖², u + u_b): the bound terms of a node's
/// chunk (or, with lo = hi = a key's positions and u_b its u, the key's terms up to
/// rounding). `WEIGHT` picks the form's s.
#[inline(always)]
fn chunk_terms<const WEIGHT: bool>(
    q: [&[f32; CHUNK]; 4],
    lo: [&[f32; CHUNK]; 3],
    hi: [&[f32; CHUNK]; 3],
    ub: &[f32; CHUNK],
) -> f32 {
    let mut acc = [0.0f32; CHUNK];
    for j in 0..CHUNK {
        let mut d2 = 0.0f32;
        for k in 0..3 {
            let d = q[k][j] - q[k][j].max(lo[k][j]).min(hi[k][j]);
            d2 += d * d;
        }
        let v = q[3][j] + ub[j];
        acc[j] = if WEIGHT { d2 * v } else { d2 / v }.sqrt();
    }
    acc.iter().sum()
}

impl KeyTree {
    /// Lower bound of the Eq. 8 cost of every member of `node` for the query: Σ over the
    /// frames where all members are counted of √s(dist(q_t, box_t)², u_t + u_b,t) (one
    /// square root: the term s(dist, √(u_t + u_b,t)) of the module doc up to rounding,
    /// which the margin covers), over the query's `chunks` (in that order; only the first
    /// [`BIG_CHUNKS`] for nodes larger than [`BIG_NODE`]). `None` as soon as the sum
    /// exceeds `stop` (with the margin; then no member can beat `stop`).
    fn bound(&self, node: usize, q: &Query, chunks: &[u32], stop: f32) -> Option<f32> {
        let n = self.nodes[node];
        let chunks = if (n.end - n.start) as usize > BIG_NODE {
            &chunks[..chunks.len().min(BIG_CHUNKS)]
        } else {
            chunks
        };
        let p = self.padded;
        let b = &self.bounds[node * ARRAYS * p..(node + 1) * ARRAYS * p];
        let arr = |a: usize, c: usize| -> &[f32; CHUNK] {
            b[a * p + c * CHUNK..a * p + (c + 1) * CHUNK].try_into().expect("chunk")
        };
        let mut s = 0.0f32;
        for &c in chunks {
            let c = c as usize;
            let qs = [q.get(0, c), q.get(1, c), q.get(2, c), q.get(3, c)];
            let lo = [arr(LO, c), arr(LO + 1, c), arr(LO + 2, c)];
            let hi = [arr(HI, c), arr(HI + 1, c), arr(HI + 2, c)];
            s += match self.form {
                MetricForm::Weight => chunk_terms::<true>(qs, lo, hi, arr(UB, c)),
                MetricForm::Inverse => chunk_terms::<false>(qs, lo, hi, arr(UB, c)),
            };
            if s * (1.0 - MARGIN) > stop {
                return None;
            }
        }
        Some(s)
    }
}

/// A node waiting in the best-first queue: a lower bound of its members' costs and the
/// node, ordered by (bound, node) reversed for a min-heap.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Pending(f32, u32);

impl Eq for Pending {}

impl Ord for Pending {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        other.0.total_cmp(&self.0).then(other.1.cmp(&self.1))
    }
}

impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

/// The key of lowest Eq. 8 cost for a query trajectory (`q`, `u` `[T]`) in the metric
/// form of `tree`, starting from `candidates` (any keys, e.g. kiddo's nearest at the
/// query's best frame). Equals [`argmin_sum_brute`] (see the module doc for the argument).
pub fn argmin_sum(
    kf: &KeyFrames,
    tree: &KeyTree,
    q: &[[f32; 3]],
    u: &[f32],
    candidates: &[u32],
) -> Option<(f64, u32)> {
    let form = tree.form;
    let mut best: Option<(f64, u32)> = None;
    for &l in candidates {
        let c = (sum_cost(kf, q, u, l as usize, best.map_or(f64::INFINITY, |b| b.0), form), l);
        if best.is_none_or(|b| lt64(c, b)) {
            best = Some(c);
        }
    }
    if tree.nodes.is_empty() {
        return best;
    }
    let query = Query::new(q, u, tree.padded);
    // Chunks by decreasing weight of the query's own factors, so that partial sums grow
    // fastest (for `weight`, chunks where the query is unreliable come first).
    let weight: Vec<f32> = (0..tree.padded / CHUNK)
        .map(|c| query.get(3, c).iter().map(|&u| form.scale(1.0, u)).sum())
        .collect();
    let mut chunks: Vec<u32> = (0..weight.len() as u32).collect();
    chunks.sort_by(|&a, &b| weight[b as usize].total_cmp(&weight[a as usize]).then(a.cmp(&b)));
    // the f32 bounds prune against the f64 best cost rounded to f32 (the margin covers it)
    let stop = |best: Option<(f64, u32)>| best.map_or(f32::INFINITY, |b| b.0 as f32);
    let mut queue = std::collections::BinaryHeap::new();
    if let Some(b) = tree.bound(0, &query, &chunks, stop(best)) {
        queue.push(Pending(b, 0));
    }
    while let Some(Pending(bound, id)) = queue.pop() {
        if bound * (1.0 - MARGIN) > stop(best) {
            break;
        }
        let node = tree.nodes[id as usize];
        match node.children {
            Some((a, b)) => {
                for c in [a, b] {
                    if let Some(cb) = tree.bound(c as usize, &query, &chunks, stop(best)) {
                        queue.push(Pending(cb.max(bound), c));
                    }
                }
            }
            None => {
                for &l in &tree.order[node.start as usize..node.end as usize] {
                    if let Some((stop, _)) = best
                        && tree.key_exceeds(l as usize, &query, &chunks, stop as f32)
                    {
                        continue;
                    }
                    let c = (sum_cost(kf, q, u, l as usize, f64::INFINITY, form), l);
                    if best.is_none_or(|b| lt64(c, b)) {
                        best = Some(c);
                    }
                }
            }
        }
    }
    best
}

impl KeyTree {
    /// Whether a partial sum of key `l`'s Eq. 8 terms over the query's `chunks` (in that
    /// order, one square root per term, with the margin) already exceeds `stop`.
    fn key_exceeds(&self, l: usize, q: &Query, chunks: &[u32], stop: f32) -> bool {
        let p = self.padded;
        let key = &self.keys[l * 4 * p..(l + 1) * 4 * p];
        let arr = |a: usize, c: usize| -> &[f32; CHUNK] {
            key[a * p + c * CHUNK..a * p + (c + 1) * CHUNK].try_into().expect("chunk")
        };
        let mut s = 0.0f32;
        for &c in chunks {
            let c = c as usize;
            let qs = [q.get(0, c), q.get(1, c), q.get(2, c), q.get(3, c)];
            let pos = [arr(0, c), arr(1, c), arr(2, c)];
            s += match self.form {
                MetricForm::Weight => chunk_terms::<true>(qs, pos, pos, arr(3, c)),
                MetricForm::Inverse => chunk_terms::<false>(qs, pos, pos, arr(3, c)),
            };
            if s * (1.0 - MARGIN) > stop {
                return true;
            }
        }
        false
    }
}

/// Squared release cost max_{t: eligible(l, t)} ‖p_t − p_{l,t}‖²; stops once above `stop`
/// (compared as `(cost, l)` pairs); +∞ when key `l` is never eligible.
pub fn max_cost2(kf: &KeyFrames, p: &[[f32; 3]], l: usize, stop: (f32, u32)) -> f32 {
    let mut m = f32::NEG_INFINITY;
    for t in 0..kf.num_frames {
        let i = kf.at(l, t);
        if kf.eligible[i] {
            m = m.max(dist2(p[t], kf.q[i]));
            if lt(stop, (m, l as u32)) {
                return m;
            }
        }
    }
    if m == f32::NEG_INFINITY { f32::INFINITY } else { m }
}

/// Brute-force reference of [`knn_max`]: the `k` keys of lowest [`max_cost2`] (squared).
pub fn knn_max_brute(kf: &KeyFrames, p: &[[f32; 3]], k: usize) -> Vec<(f32, u32)> {
    let mut best = Vec::with_capacity(k + 1);
    for l in 0..kf.num_keys {
        let c = max_cost2(kf, p, l, (f32::INFINITY, u32::MAX));
        if c.is_finite() {
            push_top(&mut best, k, (c, l as u32));
        }
    }
    best
}

/// The `k` keys of lowest release max-distance cost for trajectory `p` `[T]`, starting
/// from `candidates`; `tau[l]` is a frame at which key l is eligible (`u32::MAX` for keys
/// never eligible). Equals [`knn_max_brute`].
pub fn knn_max(
    kf: &KeyFrames,
    tau: &[u32],
    p: &[[f32; 3]],
    k: usize,
    candidates: &[u32],
) -> Vec<(f32, u32)> {
    let mut best: Vec<(f32, u32)> = Vec::with_capacity(k + 1);
    let mut seen = vec![false; kf.num_keys];
    let kth = |best: &Vec<(f32, u32)>| {
        if best.len() == k { best[k - 1] } else { (f32::INFINITY, u32::MAX) }
    };
    let consider = |l: u32, best: &mut Vec<(f32, u32)>| {
        let c = max_cost2(kf, p, l as usize, kth(best));
        if c.is_finite() {
            push_top(best, k, (c, l));
        }
    };
    for &l in candidates {
        if !std::mem::replace(&mut seen[l as usize], true) {
            consider(l, &mut best);
        }
    }
    for l in 0..kf.num_keys {
        let t = tau[l];
        if seen[l] || t == u32::MAX {
            continue;
        }
        let lb = dist2(p[t as usize], kf.q[kf.at(l, t as usize)]);
        if lt(kth(&best), (lb, l as u32)) {
            continue;
        }
        consider(l as u32, &mut best);
    }
    best
}

/// Release key-key cost: max over frames where both keys are eligible of the squared
/// distance (+∞ when never co-eligible); the k lowest for key `i` (exact, with early exit).
pub fn knn_minmax(kf: &KeyFrames, i: usize, k: usize) -> Vec<(f32, u32)> {
    let mut best: Vec<(f32, u32)> = Vec::with_capacity(k + 1);
    for l in 0..kf.num_keys {
        if l == i {
            continue;
        }
        let stop = if best.len() == k { best[k - 1] } else { (f32::INFINITY, u32::MAX) };
        let mut m = f32::NEG_INFINITY;
        for t in 0..kf.num_frames {
            let (a, b) = (kf.at(i, t), kf.at(l, t));
            if kf.eligible[a] && kf.eligible[b] {
                m = m.max(dist2(kf.q[a], kf.q[b]));
                if lt(stop, (m, l as u32)) {
                    break;
                }
            }
        }
        if m.is_finite() {
            push_top(&mut best, k, (m, l as u32));
        }
    }
    best
}

/// Release "max_native" key-key cost: mean over frames of the distance; the k lowest.
pub fn knn_mean(kf: &KeyFrames, i: usize, k: usize) -> Vec<(f32, u32)> {
    let mut best: Vec<(f32, u32)> = Vec::with_capacity(k + 1);
    for l in (0..kf.num_keys).filter(|&l| l != i) {
        let s: f32 =
            (0..kf.num_frames).map(|t| dist2(kf.q[kf.at(i, t)], kf.q[kf.at(l, t)]).sqrt()).sum();
        push_top(&mut best, k, (s / kf.num_frames.max(1) as f32, l as u32));
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::graph::metric::apply;
    use crate::util::rng::Rng;

    /// Random keys in two clusters, anisotropically transformed per frame (for the metric
    /// `form`), with some unreliable (φ) and ineligible frames.
    fn random_keys(
        seed: u64,
        nk: usize,
        nt: usize,
        form: MetricForm,
    ) -> (KeyFrames, Vec<glam::Mat3>) {
        let mut rng = Rng::new(seed);
        let mats: Vec<glam::Mat3> = (0..nt)
            .map(|t| {
                let r = glam::DMat3::from_euler(
                    glam::EulerRot::XYZ,
                    0.1 * t as f64,
                    rng.uniform() * 3.0,
                    0.3,
                );
                form.transform([1.0, 1.0, 0.01], r)
            })
            .collect();
        let mut kf = KeyFrames { num_keys: nk, num_frames: nt, ..Default::default() };
        for l in 0..nk {
            let c = if l % 2 == 0 { 0.0 } else { 3.0 };
            let base = [c + rng.normal() as f32, rng.normal() as f32, rng.normal() as f32];
            let vel = [rng.normal() as f32 * 0.1, 0.05, 0.0];
            for t in 0..nt {
                let p = [0, 1, 2].map(|k| base[k] + vel[k] * t as f32);
                kf.q.push(apply(&mats[t], p));
                let reliable = rng.uniform() > 0.2;
                kf.u.push(if reliable { (0.01 + rng.uniform() * 2.0) as f32 } else { 1e8 });
                kf.eligible.push(reliable);
            }
        }
        (kf, mats)
    }

    fn query(seed: u64, nt: usize, mats: &[glam::Mat3]) -> (Vec<[f32; 3]>, Vec<f32>) {
        let mut rng = Rng::new(seed);
        let base = [rng.normal() as f32 * 2.0, rng.normal() as f32, rng.normal() as f32];
        let q = (0..nt)
            .map(|t| apply(&mats[t], [base[0] + 0.02 * t as f32, base[1], base[2]]))
            .collect();
        let u = (0..nt)
            .map(|_| if rng.uniform() > 0.3 { (0.05 + rng.uniform()) as f32 } else { 1e8 })
            .collect();
        (q, u)
    }

    #[test]
    fn accelerated_searches_equal_brute_force() {
        for (seed, form) in (0..6).flat_map(|s| [(s, MetricForm::Weight), (s, MetricForm::Inverse)])
        {
            let (kf, mats) = random_keys(seed, 150, 12, form);
            let trees = frame_trees(&kf);
            let lv = key_tree(&kf, 4, form);
            let tau: Vec<u32> = (0..kf.num_keys)
                .map(|l| {
                    (0..kf.num_frames)
                        .find(|&t| kf.eligible[kf.at(l, t)])
                        .map_or(u32::MAX, |t| t as u32)
                })
                .collect();
            for qs in 0..25 {
                let (q, u) = query(seed * 100 + qs, kf.num_frames, &mats);
                let t = (qs as usize) % kf.num_frames;
                for (k, f) in [(1, Some(form)), (8, Some(form)), (20, None)] {
                    let query = FrameQuery { q: q[t], u: u[t], t, exclude: Some(3), k, form: f };
                    let fast = knn_at_frame(&kf, &trees[t], &query);
                    let slow = knn_at_frame_brute(&kf, &query);
                    assert_eq!(fast, slow, "{form:?} seed {seed} query {qs} k {k}");
                }
                let cand = trees[t].nearest(q[t], 2).0;
                let want = argmin_sum_brute(&kf, &q, &u, form);
                assert!(want.is_some());
                assert_eq!(argmin_sum(&kf, &lv, &q, &u, &cand), want, "{form:?} seed {seed}");
                assert_eq!(argmin_sum(&kf, &lv, &q, &u, &[]), want, "{form:?} seed {seed}");
                for k in [1, 5] {
                    assert_eq!(knn_max(&kf, &tau, &q, k, &cand), knn_max_brute(&kf, &q, k));
                }
            }
        }
    }

    /// Hard cases of Eq. 8: T not a multiple of the chunk and above the large-node frame
    /// cap, exact duplicate keys (ties), keys and queries unreliable (u = φ) at every frame,
    /// a query on top of a key.
    #[test]
    fn argmin_sum_equals_brute_force_in_hard_cases() {
        for form in [MetricForm::Weight, MetricForm::Inverse] {
            let nt = 45;
            let (mut kf, mats) = random_keys(7, 160, nt, form);
            // keys 1..=4 duplicate key 0; keys 5 and 6 are unreliable at every frame
            for l in 1..=6 {
                for t in 0..nt {
                    let (src, dst) = (kf.at(0, t), kf.at(l, t));
                    if l <= 4 {
                        kf.q[dst] = kf.q[src];
                        kf.u[dst] = kf.u[src];
                        kf.eligible[dst] = kf.eligible[src];
                    } else {
                        kf.u[dst] = 1e8;
                        kf.eligible[dst] = false;
                    }
                }
            }
            for leaf in [1, 3, 8] {
                let tree = key_tree(&kf, leaf, form);
                for qs in 0..30u64 {
                    let (mut q, mut u) = query(qs + 1000, nt, &mats);
                    match qs % 5 {
                        0 => u.fill(1e8),
                        1 => q = (0..nt).map(|t| kf.q[kf.at(0, t)]).collect(),
                        2 => q = (0..nt).map(|t| kf.q[kf.at(5, t)]).collect(),
                        _ => {}
                    }
                    let want = argmin_sum_brute(&kf, &q, &u, form);
                    for cand in [vec![], vec![3], vec![6, 2]] {
                        let got = argmin_sum(&kf, &tree, &q, &u, &cand);
                        assert_eq!(got, want, "{form:?} leaf {leaf} query {qs} {cand:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn ties_are_broken_by_key_index() {
        let kf = KeyFrames {
            num_keys: 4,
            num_frames: 1,
            q: vec![[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5.0]],
            u: vec![1.0; 4],
            eligible: vec![true; 4],
        };
        let trees = frame_trees(&kf);
        let inv = Some(MetricForm::Inverse);
        let query = FrameQuery { q: [0.0; 3], u: 1.0, t: 0, exclude: None, k: 2, form: inv };
        let got = knn_at_frame(&kf, &trees[0], &query);
        assert_eq!(got, vec![(0.5, 0), (0.5, 1)]);
        let got =
            knn_at_frame(&kf, &trees[0], &FrameQuery { form: Some(MetricForm::Weight), ..query });
        assert_eq!(got, vec![(2.0, 0), (2.0, 1)]);
        assert_eq!(
            argmin_sum(&kf, &key_tree(&kf, 1, MetricForm::Inverse), &[[0.0; 3]], &[1.0], &[2]),
            Some((1.0 / 2f64.sqrt(), 0))
        );
        assert_eq!(
            argmin_sum(&kf, &key_tree(&kf, 1, MetricForm::Weight), &[[0.0; 3]], &[1.0], &[2]),
            Some((2f64.sqrt(), 0))
        );
    }

    /// The two forms disagree where the paper's notation matters: a key seen only at the
    /// query's frames wins Eq. 8 under `weight`, a key close but unseen (u = φ) at most
    /// frames wins under `inverse`.
    #[test]
    fn the_weight_form_prefers_keys_that_are_seen() {
        let nt = 4;
        let mut kf = KeyFrames { num_keys: 2, num_frames: nt, ..Default::default() };
        for l in 0..2 {
            for t in 0..nt {
                // key 0: 1.0 away, always reliable; key 1: 0.5 away, unseen but at frame 0
                kf.q.push(if l == 0 { [1.0, 0.0, 0.0] } else { [0.5, 0.0, 0.0] });
                let seen = l == 0 || t == 0;
                kf.u.push(if seen { 0.1 } else { 1e8 });
                kf.eligible.push(seen);
            }
        }
        let (q, u) = (vec![[0.0; 3]; nt], vec![0.1; nt]);
        for (form, want) in [(MetricForm::Weight, 0), (MetricForm::Inverse, 1)] {
            let brute = argmin_sum_brute(&kf, &q, &u, form).unwrap();
            assert_eq!(brute.1, want, "{form:?}");
            assert_eq!(argmin_sum(&kf, &key_tree(&kf, 1, form), &q, &u, &[]), Some(brute));
        }
    }

    /// Issue 15 item 5: where the query is unseen (u = φ = 1e8), f32 rounds φ + u_l to φ
    /// for u_l below 4. Two keys at the same place, equally reliable where the query is
    /// seen, differ only in their reliability (u 3 vs 0.01) at the frames where it is not:
    /// in f32 their sums tie and the lower index (the less reliable key) won; in f64 the
    /// more reliable key does, in the brute force and the tree search alike.
    #[test]
    fn eq8_keeps_the_keys_reliability_where_the_query_is_unseen() {
        let nt = 6;
        let unseen = |t: usize| t >= 2;
        let mut kf = KeyFrames { num_keys: 2, num_frames: nt, ..Default::default() };
        for l in 0..2 {
            for t in 0..nt {
                kf.q.push([1.0, 0.0, 0.0]);
                kf.u.push(match (unseen(t), l) {
                    (true, 0) => 3.0,
                    (true, _) => 0.01,
                    (false, _) => 0.1,
                });
                kf.eligible.push(true);
            }
        }
        assert_eq!(1e8f32 + 3.0, 1e8f32 + 0.01, "the f32 rounding this test is about");
        let q = vec![[0.0; 3]; nt];
        let u: Vec<f32> = (0..nt).map(|t| if unseen(t) { 1e8 } else { 0.1 }).collect();
        let brute = argmin_sum_brute(&kf, &q, &u, MetricForm::Weight).unwrap();
        assert_eq!(brute.1, 1, "{brute:?}");
        for cand in [&[][..], &[0], &[0, 1]] {
            let tree = key_tree(&kf, 1, MetricForm::Weight);
            assert_eq!(argmin_sum(&kf, &tree, &q, &u, cand), Some(brute), "{cand:?}");
        }
    }
}
