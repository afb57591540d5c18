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
//! - [`argmin_sum`] (Eq. 8): keys are grouped in leaves; per frame t a leaf stores the
//!   bounding box of the q of its members counted at t and their u_b. For such a member l,
//!   dist(q_i, box_t) ≤ ‖q_i − q_l‖, so c_t = s(dist, √(u_i + u_b)) bounds its frame-t term
//!   s(‖Δq‖, √(u_i + u_l)); its other terms are ≥ 0. Hence a key's cost is at least
//!   Σ_t [l counted at t]·c_t, and every member's cost at least the leaf bound
//!   Σ_t [all members counted at t]·c_t. Leaves are visited by increasing bound and the
//!   search stops at the first whose bound exceeds the best cost so far; inside a leaf, keys
//!   whose own bound exceeds it are skipped. Bounds are summed in another order than the
//!   exact cost, so they are compared with a 1e-3 relative margin (f32 rounding of T ≤ 10⁴
//!   non-negative terms is below 10⁻³); exact partial sums stop once above the best.
//!   Eq. 8 sums over all frames (the paper's Σ_{t=0}^{T−1}) whatever the form. Which
//!   frames a leaf counts only tightens the bounds: `inverse` counts the frames where the
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

use super::MetricForm;

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

/// Brute-force reference of [`knn_at_frame`].
pub fn knn_at_frame_brute(
    kf: &KeyFrames,
    q: [f32; 3],
    u: f32,
    t: usize,
    exclude: Option<u32>,
    k: usize,
    form: Option<MetricForm>,
) -> Vec<(f32, u32)> {
    let mut best = Vec::with_capacity(k + 1);
    for l in 0..kf.num_keys {
        if Some(l as u32) == exclude || !kf.eligible[kf.at(l, t)] {
            continue;
        }
        push_top(&mut best, k, (frame_cost(kf, q, u, l, t, form), l as u32));
    }
    best
}

/// The k eligible keys of lowest cost at frame `t` for a query at `q` with uncertainty
/// `u` (Eq. 7 in the metric `form` when `Some`; plain Euclidean kNN when `None`),
/// `exclude` left out.
/// Equals [`knn_at_frame_brute`] (see the module doc for the argument).
pub fn knn_at_frame(
    kf: &KeyFrames,
    tree: &FrameTree,
    q: [f32; 3],
    u: f32,
    t: usize,
    exclude: Option<u32>,
    k: usize,
    form: Option<MetricForm>,
) -> Vec<(f32, u32)> {
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
/// partial sum exceeds `stop`.
pub fn sum_cost(
    kf: &KeyFrames,
    q: &[[f32; 3]],
    u: &[f32],
    l: usize,
    stop: f32,
    form: MetricForm,
) -> f32 {
    let mut s = 0.0f32;
    for t in 0..kf.num_frames {
        let i = kf.at(l, t);
        s += form.scale(dist2(q[t], kf.q[i]).sqrt(), (u[t] + kf.u[i]).sqrt());
        if s > stop {
            break;
        }
    }
    s
}

/// Brute-force reference of [`argmin_sum`]: `(cost, key)` of the lowest Eq. 8 cost.
pub fn argmin_sum_brute(
    kf: &KeyFrames,
    q: &[[f32; 3]],
    u: &[f32],
    form: MetricForm,
) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    for l in 0..kf.num_keys {
        let c = (sum_cost(kf, q, u, l, f32::INFINITY, form), l as u32);
        if best.is_none_or(|b| lt(c, b)) {
            best = Some(c);
        }
    }
    best
}

/// Keys grouped spatially, with per-frame bounding boxes (in q) and bounding u, for the
/// Eq. 8 search in one metric form.
#[derive(Debug, Clone)]
pub struct Leaves {
    /// The metric form the bounds are for.
    form: MetricForm,
    /// Member keys of each leaf.
    keys: Vec<Vec<u32>>,
    /// Per leaf `[T]`: bounding box of the members counted at t (empty: lo > hi).
    lo: Vec<Vec<[f32; 3]>>,
    hi: Vec<Vec<[f32; 3]>>,
    /// Per leaf `[T]`: u_b of the members counted at t (u_min for `weight`, u_max for
    /// `inverse`).
    u_b: Vec<Vec<f32>>,
    /// Per leaf `[members, T]`: 1 where the member is counted at t, else 0.
    mask: Vec<Vec<f32>>,
    /// Per leaf `[T]`: 1 where every member is counted at t, else 0.
    all: Vec<Vec<f32>>,
}

/// Group the keys into leaves of at most `size` by recursive median splits of their
/// time-averaged positions along the widest axis, with the bounds of the metric `form`:
/// a member is counted at t when eligible there (`inverse`) or always (`weight`), see the
/// module doc.
pub fn leaves(kf: &KeyFrames, size: usize, form: MetricForm) -> Leaves {
    let counted = |i: usize| form == MetricForm::Weight || kf.eligible[i];
    let nt = kf.num_frames;
    let mean: Vec<[f32; 3]> = (0..kf.num_keys)
        .map(|l| {
            let mut m = [0.0f64; 3];
            for t in 0..nt {
                let p = kf.q[kf.at(l, t)];
                (0..3).for_each(|k| m[k] += p[k] as f64);
            }
            m.map(|v| (v / nt.max(1) as f64) as f32)
        })
        .collect();
    let mut groups = Vec::new();
    let mut stack = vec![(0..kf.num_keys as u32).collect::<Vec<u32>>()];
    while let Some(mut g) = stack.pop() {
        if g.len() <= size.max(1) {
            groups.push(g);
            continue;
        }
        let axis = (0..3)
            .max_by(|&a, &b| {
                let ext = |k: usize| {
                    let (lo, hi) =
                        g.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &l| {
                            (lo.min(mean[l as usize][k]), hi.max(mean[l as usize][k]))
                        });
                    hi - lo
                };
                ext(a).total_cmp(&ext(b))
            })
            .unwrap_or(0);
        g.sort_unstable_by(|a, b| {
            mean[*a as usize][axis].total_cmp(&mean[*b as usize][axis]).then(a.cmp(b))
        });
        let right = g.split_off(g.len() / 2);
        stack.push(right);
        stack.push(g);
    }
    let mut out = Leaves {
        form,
        keys: Vec::new(),
        lo: Vec::new(),
        hi: Vec::new(),
        u_b: Vec::new(),
        mask: Vec::new(),
        all: Vec::new(),
    };
    for g in groups {
        let mut lo = vec![[f32::INFINITY; 3]; nt];
        let mut hi = vec![[f32::NEG_INFINITY; 3]; nt];
        let mut u_min = vec![f32::INFINITY; nt];
        let mut u_max = vec![0.0f32; nt];
        let mut mask = Vec::with_capacity(g.len() * nt);
        for &l in &g {
            for t in 0..nt {
                let i = kf.at(l as usize, t);
                mask.push(if counted(i) { 1.0 } else { 0.0 });
                if !counted(i) {
                    continue;
                }
                for k in 0..3 {
                    lo[t][k] = lo[t][k].min(kf.q[i][k]);
                    hi[t][k] = hi[t][k].max(kf.q[i][k]);
                }
                u_min[t] = u_min[t].min(kf.u[i]);
                u_max[t] = u_max[t].max(kf.u[i]);
            }
        }
        let all = (0..nt)
            .map(|t| if g.iter().all(|&l| counted(kf.at(l as usize, t))) { 1.0 } else { 0.0 })
            .collect();
        let u_b = u_min.iter().zip(&u_max).map(|(&a, &b)| form.bound_u(a, b)).collect();
        out.keys.push(g);
        out.lo.push(lo);
        out.hi.push(hi);
        out.u_b.push(u_b);
        out.mask.push(mask);
        out.all.push(all);
    }
    out
}

/// Per-frame lower bounds `[T]` of the Eq. 8 terms of the members of leaf `g` counted at
/// t: s(dist(q_t, box_t), √(u_t + u_b,t)) (0 where no member is counted), and the leaf's
/// bound (their sum over the frames where every member is counted); `None` as soon as that
/// bound exceeds `stop` (then no member can beat it).
fn leaf_terms(
    lv: &Leaves,
    g: usize,
    q: &[[f32; 3]],
    u: &[f32],
    stop: f32,
) -> Option<(f32, Vec<f32>)> {
    let (lo, hi, ub, all) = (&lv.lo[g], &lv.hi[g], &lv.u_b[g], &lv.all[g]);
    let mut terms = Vec::with_capacity(q.len());
    let mut leaf_lb = 0.0f32;
    for t in 0..q.len() {
        let c = if lo[t][0] > hi[t][0] {
            0.0
        } else {
            let c = [0, 1, 2].map(|k| q[t][k].clamp(lo[t][k], hi[t][k]));
            lv.form.scale(dist2(q[t], c).sqrt(), (u[t] + ub[t]).sqrt())
        };
        terms.push(c);
        leaf_lb += all[t] * c;
        if leaf_lb * (1.0 - 1e-3) > stop {
            return None;
        }
    }
    Some((leaf_lb, terms))
}

/// Σ_t mask_t · c_t with eight accumulators (vectorisable; order differs from
/// [`sum_cost`], hence the relative margin where it is compared).
fn masked_sum(mask: &[f32], c: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (m8, c8) = (mask.chunks_exact(8), c.chunks_exact(8));
    let (mr, cr) = (m8.remainder(), c8.remainder());
    for (m, c) in m8.zip(c8) {
        for k in 0..8 {
            acc[k] += m[k] * c[k];
        }
    }
    let tail: f32 = mr.iter().zip(cr).map(|(m, c)| m * c).sum();
    acc.iter().sum::<f32>() + tail
}

/// The key of lowest Eq. 8 cost for a query trajectory (`q`, `u` `[T]`) in the metric
/// form of `lv`, starting from `candidates` (any keys, e.g. kiddo's nearest at the query's
/// best frame). Equals [`argmin_sum_brute`] (see the module doc for the argument).
pub fn argmin_sum(
    kf: &KeyFrames,
    lv: &Leaves,
    q: &[[f32; 3]],
    u: &[f32],
    candidates: &[u32],
) -> Option<(f32, u32)> {
    let mut best: Option<(f32, u32)> = None;
    let consider = |l: u32, best: &mut Option<(f32, u32)>| {
        let stop = best.map_or(f32::INFINITY, |b| b.0);
        let c = (sum_cost(kf, q, u, l as usize, stop, lv.form), l);
        if best.is_none_or(|b| lt(c, b)) {
            *best = Some(c);
        }
    };
    for &l in candidates {
        consider(l, &mut best);
    }
    let nt = q.len();
    // A leaf's bound: the frames where all its members are counted. Leaves are visited by
    // increasing bound; once one exceeds the best cost, so do all that follow.
    let stop = best.map_or(f32::INFINITY, |b| b.0);
    let mut order: Vec<(f32, usize, Vec<f32>)> = (0..lv.keys.len())
        .filter_map(|g| leaf_terms(lv, g, q, u, stop).map(|(lb, terms)| (lb, g, terms)))
        .collect();
    order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    for (leaf_lb, g, terms) in order {
        if best.is_some_and(|b| leaf_lb * (1.0 - 1e-3) > b.0) {
            break;
        }
        for (m, &l) in lv.keys[g].iter().enumerate() {
            // Lower bound of key l: its counted frames' leaf bounds (other frames
            // contribute ≥ 0). Summed in another order than `sum_cost`, so compared with a
            // relative margin far above f32 rounding of T ≤ 10^4 non-negative terms.
            let lb = masked_sum(&lv.mask[g][m * nt..(m + 1) * nt], &terms);
            if best.is_some_and(|b| lb * (1.0 - 1e-3) > b.0) {
                continue;
            }
            consider(l, &mut best);
        }
    }
    best
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
    use crate::stages::graph::{Rng, apply};

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
            let lv = leaves(&kf, 8, form);
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
                    let fast = knn_at_frame(&kf, &trees[t], q[t], u[t], t, Some(3), k, f);
                    let slow = knn_at_frame_brute(&kf, q[t], u[t], t, Some(3), k, f);
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
        let got = knn_at_frame(&kf, &trees[0], [0.0; 3], 1.0, 0, None, 2, inv);
        assert_eq!(got, vec![(0.5, 0), (0.5, 1)]);
        let got = knn_at_frame(&kf, &trees[0], [0.0; 3], 1.0, 0, None, 2, Some(MetricForm::Weight));
        assert_eq!(got, vec![(2.0, 0), (2.0, 1)]);
        assert_eq!(
            argmin_sum(&kf, &leaves(&kf, 1, MetricForm::Inverse), &[[0.0; 3]], &[1.0], &[2]),
            Some((1.0 / 2f32.sqrt(), 0))
        );
        assert_eq!(
            argmin_sum(&kf, &leaves(&kf, 1, MetricForm::Weight), &[[0.0; 3]], &[1.0], &[2]),
            Some((2f32.sqrt(), 0))
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
            assert_eq!(argmin_sum(&kf, &leaves(&kf, 1, form), &q, &u, &[]), Some(brute));
        }
    }
}
