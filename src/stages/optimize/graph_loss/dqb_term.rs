//! The DQB term of L_non-key (paper Eq. 10-11; official-release.md §5.2 `__DQB_warp2__`, §5.3
//! `L_nonkey`) for [`GraphObjective`]: the blend weights of [`super::super::nonkey_weights`],
//! the warp of each non-key's source pose by the blend of its keys' relative transforms
//! T_k(t) T_k(t̂_u)⁻¹ ([`crate::math::dqb`]), the optional pose offsets, the release's L2
//! penalties on Δw and the offsets, and all their gradients.
//!
//! Work per step, frame by frame, parallel over the groups of non-keys that share a t̂ (the
//! objective orders its non-keys by t̂): each group computes the relative transform of each
//! of its (key, t̂) pairs once, its non-keys' terms, and accumulates their cotangents per pair
//! before one VJP per pair, all in its own slices of the buffers; then each key sums its
//! pairs' cotangents in pair order. So the result does not depend on the number of threads.
//! The buffers ([`DqbScratch`]) are kept across steps.

use rayon::prelude::*;

use super::super::nonkey_weights::{self, NonkeyWeights, Row};
use super::super::poses::{PoseGrads, Poses};
use super::{AnchorMetric, GraphObjective, Reduction};
use crate::math::dqb::{self, Dq};
use crate::math::quat64 as q4;

/// The distinct (key, t̂) pairs of the non-key edges, whose relative transforms the edges
/// share, sorted by t̂ then key, and the groups of non-keys that share a t̂ (contiguous, as
/// the objective orders its non-keys by t̂), each with its contiguous edges and pairs.
#[derive(Debug, Default)]
pub(super) struct Pairs {
    /// The pair of each non-key edge `[E_n]`.
    of_edge: Vec<u32>,
    /// Compact key and t̂ of each pair `[P]`.
    key: Vec<u32>,
    t: Vec<u32>,
    /// The pairs of key k: `key_pairs[key_off[k]..key_off[k + 1]]`, ascending.
    key_off: Vec<usize>,
    key_pairs: Vec<u32>,
    /// Group g holds the non-keys `group_u[g]..group_u[g + 1]`, their edges
    /// `group_e[g]..group_e[g + 1]` and pairs `group_p[g]..group_p[g + 1]` `[G + 1]`.
    group_u: Vec<usize>,
    group_e: Vec<usize>,
    group_p: Vec<usize>,
}

impl Pairs {
    /// The pairs of the non-key edges given as CSR `nk_off` `[nu + 1]` over compact keys
    /// `nk_key` `[E_n]`, with each non-key's t̂ `[nu]` (ascending), among `num_keys` keys.
    pub(super) fn new(nk_off: &[usize], nk_key: &[u32], t_hat: &[u32], num_keys: usize) -> Self {
        debug_assert!(t_hat.is_sorted(), "non-keys ordered by t̂");
        let mut by_pair: Vec<(u32, u32, u32)> = (0..t_hat.len())
            .flat_map(|u| (nk_off[u]..nk_off[u + 1]).map(move |e| (u, e)))
            .map(|(u, e)| (t_hat[u], nk_key[e], e as u32))
            .collect();
        by_pair.sort_unstable();
        let mut of_edge = vec![0u32; nk_key.len()];
        let (mut key, mut t) = (Vec::new(), Vec::new());
        for (i, &(th, k, e)) in by_pair.iter().enumerate() {
            if i == 0 || (by_pair[i - 1].0, by_pair[i - 1].1) != (th, k) {
                key.push(k);
                t.push(th);
            }
            of_edge[e as usize] = (key.len() - 1) as u32;
        }
        let mut key_off = vec![0usize; num_keys + 1];
        for &k in &key {
            key_off[k as usize + 1] += 1;
        }
        for k in 0..num_keys {
            key_off[k + 1] += key_off[k];
        }
        let mut key_pairs = vec![0u32; key.len()];
        let mut next = key_off.clone();
        for (p, &k) in key.iter().enumerate() {
            key_pairs[next[k as usize]] = p as u32;
            next[k as usize] += 1;
        }
        let mut group_u: Vec<usize> =
            (0..t_hat.len()).filter(|&u| u == 0 || t_hat[u] != t_hat[u - 1]).collect();
        let group_p = group_u
            .iter()
            .map(|&u| t.partition_point(|&x| x < t_hat[u]))
            .chain([key.len()])
            .collect();
        group_u.push(t_hat.len());
        let group_e = group_u.iter().map(|&u| nk_off[u]).collect();
        Pairs { of_edge, key, t, key_off, key_pairs, group_u, group_e, group_p }
    }
}

impl GraphObjective {
    /// mean(Δw²) over the non-key edges and mean(offset²) over the non-keys' offsets
    /// (the release's L2 penalties); adds their weighted gradients.
    pub(super) fn offset_penalties(&mut self) -> [f64; 2] {
        let mut out = [0.0; 2];
        let s = &self.s;
        for (k, (v, g, w)) in [
            (&self.dw, &mut self.g_dw, s.nonkey_dweight_l2),
            (&self.offsets, &mut self.g_offsets, s.nonkey_offset_l2),
        ]
        .into_iter()
        .enumerate()
        {
            if v.is_empty() {
                continue;
            }
            let n = v.len() as f64;
            out[k] = v.iter().map(|&x| (x as f64) * (x as f64)).sum::<f64>() / n;
            for (g, &x) in g.iter_mut().zip(v) {
                *g += (2.0 * w * x as f64 / n) as f32;
            }
        }
        out
    }

    /// [`Self::blend_weights`] into the objective's own scratch.
    pub(super) fn blend_weights_of(&mut self, positions: &[[f32; 3]]) {
        let mut sc = std::mem::take(&mut self.scratch);
        self.blend_weights(positions, &mut sc.weights);
        self.scratch = sc;
    }

    /// The blend weights w' of every non-key edge ([`super::nonkey_weights`]) from
    /// `positions` `[T, N]` (read by [`NonkeyWeights::Current`]) into `nk_w_eff`, keeping each
    /// edge's log-base, θ and Δw in `sc` for [`Self::blend_weights_vjp`].
    fn blend_weights(&mut self, positions: &[[f32; 3]], sc: &mut WeightScratch) {
        let ne = self.nk_key.len();
        for v in [&mut sc.l, &mut sc.theta, &mut sc.dw] {
            v.resize(ne, 0.0);
        }
        for u in 0..self.nonkeys.len() {
            let (a, b) = (self.nk_off[u], self.nk_off[u + 1]);
            let th = self.t_hat[u] as usize * self.n;
            let pu = positions[th + self.nonkeys[u] as usize];
            for e in a..b {
                let k = self.nk_key[e] as usize;
                sc.l[e] = match self.s.nonkey_weights {
                    NonkeyWeights::Table => self.nk_w[e].ln(),
                    NonkeyWeights::Current => {
                        let pk = positions[th + self.keys[k] as usize];
                        -self.nk_lambda * dist2(pu, pk)
                    }
                };
                sc.theta[e] = self.theta[k] as f64;
                sc.dw[e] = self.dw[e] as f64;
            }
            let r = Row { l: &sc.l[a..b], theta: &sc.theta[a..b], dw: &sc.dw[a..b] };
            nonkey_weights::row(r, &mut self.nk_w_eff[a..b]);
        }
    }

    /// VJP of [`Self::blend_weights`] for the cotangents `g_w` of w' `[E_n]`: adds to the
    /// gradients of θ and Δw and, with [`NonkeyWeights::Current`], of the positions at t̂.
    fn blend_weights_vjp(
        &mut self,
        positions: &[[f32; 3]],
        g_w: &[f64],
        sc: &mut WeightScratch,
        grads: &mut PoseGrads,
    ) {
        let ne = self.nk_key.len();
        for v in [&mut sc.g_l, &mut sc.g_theta, &mut sc.g_dw] {
            v.clear();
            v.resize(ne, 0.0);
        }
        sc.g_theta_key.clear();
        sc.g_theta_key.resize(self.keys.len(), 0.0);
        for u in 0..self.nonkeys.len() {
            let (a, b) = (self.nk_off[u], self.nk_off[u + 1]);
            if a == b {
                continue;
            }
            sc.tmp.resize(2 * (b - a), 0.0);
            let r = Row { l: &sc.l[a..b], theta: &sc.theta[a..b], dw: &sc.dw[a..b] };
            let (gl, gt, gd) = (&mut sc.g_l[a..b], &mut sc.g_theta[a..b], &mut sc.g_dw[a..b]);
            nonkey_weights::row_vjp(r, &g_w[a..b], &mut sc.tmp, gl, gt, gd);
            let th = self.t_hat[u] as usize * self.n;
            let node = th + self.nonkeys[u] as usize;
            for e in a..b {
                let k = self.nk_key[e] as usize;
                sc.g_theta_key[k] += sc.g_theta[e];
                self.g_dw[e] += sc.g_dw[e] as f32;
                if self.s.nonkey_weights == NonkeyWeights::Current {
                    // L = −λ‖p_u − p_k‖²
                    let key = th + self.keys[k] as usize;
                    let (pu, pk) = (positions[node], positions[key]);
                    for c in 0..3 {
                        let d = pu[c] as f64 - pk[c] as f64;
                        let g = -2.0 * self.nk_lambda * sc.g_l[e] * d;
                        grads.position[node][c] += g as f32;
                        grads.position[key][c] -= g as f32;
                    }
                }
            }
        }
        for (g, v) in self.g_theta.iter_mut().zip(&sc.g_theta_key) {
            *g += *v as f32;
        }
    }

    /// The DQB position and rotation terms (unweighted) over non-keys and the batch frames,
    /// computed as the module doc says; adds the gradients of the poses, source poses, θ, Δw
    /// and pose offsets.
    pub(super) fn dqb_terms(
        &mut self,
        poses: &Poses,
        frames: &[usize],
        grads: &mut PoseGrads,
    ) -> [f64; 2] {
        let s = &self.s;
        if (s.dqb == 0.0 && s.dqb_rotation == 0.0) || self.nonkeys.is_empty() {
            return [0.0; 2];
        }
        let mut sc = std::mem::take(&mut self.scratch);
        let out = self.dqb_with(poses, frames, grads, &mut sc);
        self.scratch = sc;
        out
    }

    /// [`Self::dqb_terms`] with its scratch.
    fn dqb_with(
        &mut self,
        poses: &Poses,
        frames: &[usize],
        grads: &mut PoseGrads,
        sc: &mut DqbScratch,
    ) -> [f64; 2] {
        let (n, nk, nu) = (self.n, self.keys.len(), self.nonkeys.len());
        let (ne, np) = (self.nk_key.len(), self.pairs.key.len());
        self.blend_weights(&poses.position, &mut sc.weights);
        // Unit dual quaternions of the keys' poses at every frame `[T, K]`.
        let keys = &self.keys;
        sc.dq_key.resize(self.frames * nk, (dqb::IDENTITY, 1.0));
        sc.dq_key.par_iter_mut().enumerate().for_each(|(x, d)| {
            let o = (x / nk) * n + keys[x % nk] as usize;
            *d = dqb::from_pose(q4::q64(poses.rotation[o]), q4::v64(poses.position[o]));
        });
        sc.g_dq.clear();
        sc.g_dq.resize(self.frames * nk, [0.0; 8]);
        sc.pair.clear();
        sc.pair.resize(np, PairCot::default());
        sc.g_w.clear();
        sc.g_w.resize(ne, 0.0);
        sc.nonkey.clear();
        sc.nonkey.resize(nu, NonkeyCot::default());
        let linked = (0..nu).filter(|&u| self.nk_off[u + 1] > self.nk_off[u]).count();
        let norm = match self.s.reduction {
            Reduction::Sum => 1.0,
            Reduction::Mean => 1.0 / (linked * frames.len()).max(1) as f64,
        };
        let pairs = &self.pairs;
        let mut sums = [0.0; 2];
        for &t in frames {
            let dq = &sc.dq_key;
            let parts: Vec<[f64; 2]> = split_at_bounds(&mut sc.nonkey, &pairs.group_u)
                .into_par_iter()
                .zip(split_at_bounds(&mut sc.g_w, &pairs.group_e))
                .zip(split_at_bounds(&mut sc.pair, &pairs.group_p))
                .enumerate()
                .map(|(g, ((nonkeys, g_w), pair))| {
                    let group = Group { g, nonkeys, g_w, pairs: pair };
                    self.dqb_group(poses, t, dq, norm, group)
                })
                .collect();
            for p in parts {
                sums[0] += p[0];
                sums[1] += p[1];
            }
            for (u, c) in sc.nonkey.iter().enumerate() {
                if self.nk_off[u + 1] > self.nk_off[u] {
                    let o = t * n + self.nonkeys[u] as usize;
                    for k in 0..3 {
                        grads.position[o][k] += c.pose[k] as f32;
                    }
                    for k in 0..4 {
                        grads.rotation[o][k] += c.pose[3 + k] as f32;
                    }
                }
            }
            // each key's cotangent at t: its pairs' in pair order
            let pc = &sc.pair;
            sc.g_dq[t * nk..(t + 1) * nk].par_iter_mut().enumerate().for_each(|(k, g)| {
                for &p in &pairs.key_pairs[pairs.key_off[k]..pairs.key_off[k + 1]] {
                    let d = &pc[p as usize].g_dst;
                    for c in 0..8 {
                        g[c] += d[c];
                    }
                }
            });
        }
        for (p, pc) in sc.pair.iter().enumerate() {
            let x = pairs.t[p] as usize * nk + pairs.key[p] as usize;
            for c in 0..8 {
                sc.g_dq[x][c] += pc.g_src[c];
            }
        }
        for (u, c) in sc.nonkey.iter().enumerate() {
            for k in 0..3 {
                self.g_src_p[3 * u + k] = c.src[k] as f32;
            }
            for k in 0..4 {
                self.g_src_q[4 * u + k] = c.src[3 + k] as f32;
            }
            if !self.offsets.is_empty() {
                for k in 0..7 {
                    self.g_offsets[7 * u + k] += c.offset[k] as f32;
                }
            }
        }
        self.blend_weights_vjp(&poses.position, &sc.g_w, &mut sc.weights, grads);
        // the keys' poses
        let (g_dq, dq, keys) = (&sc.g_dq, &sc.dq_key, &self.keys);
        sc.key_grad.resize(self.frames * nk, ([0.0; 4], [0.0; 3]));
        sc.key_grad.par_iter_mut().enumerate().for_each(|(x, kg)| {
            let g = &g_dq[x];
            if g.iter().any(|v| *v != 0.0) {
                let o = (x / nk) * n + keys[x % nk] as usize;
                let (d, qn) = &dq[x];
                *kg = dqb::from_pose_vjp(d, *qn, q4::v64(poses.position[o]), g);
            }
        });
        for (x, (gq, gp)) in sc.key_grad.iter().enumerate() {
            if g_dq[x].iter().all(|v| *v == 0.0) {
                continue;
            }
            let o = (x / nk) * n + keys[x % nk] as usize;
            for c in 0..3 {
                grads.position[o][c] += gp[c] as f32;
            }
            for c in 0..4 {
                grads.rotation[o][c] += gq[c] as f32;
            }
        }
        [sums[0] * norm, sums[1] * norm]
    }

    /// The DQB terms of one group's non-keys at frame `t` (key dual quaternions `dq`
    /// `[T, K]`): its pairs' relative transforms, then per non-key the terms, its pose
    /// cotangent at t (written) and its source-pose, offset and weight cotangents (added),
    /// and its pairs' cotangents, then one VJP per pair (the cotangent of the key at t
    /// written, at t̂ added). Returns the group's (position, rotation) sums.
    fn dqb_group(
        &self,
        poses: &Poses,
        t: usize,
        dq: &[(Dq, f64)],
        norm: f64,
        group: Group,
    ) -> [f64; 2] {
        let Group { g, nonkeys: uc, g_w, pairs: pc } = group;
        let pairs = &self.pairs;
        let nk = self.keys.len();
        let (u0, e0, p0) = (pairs.group_u[g], pairs.group_e[g], pairs.group_p[g]);
        for (lp, c) in pc.iter_mut().enumerate() {
            let (k, th) = (pairs.key[p0 + lp] as usize, pairs.t[p0 + lp] as usize);
            (c.rel, c.sign) = dqb::relative(&dq[t * nk + k].0, &dq[th * nk + k].0);
            c.g = [0.0; 8];
        }
        let s = &self.s;
        let (wp, wq) = (s.dqb * norm, s.dqb_rotation * norm);
        let mut sums = [0.0; 2];
        for (lu, u) in (u0..pairs.group_u[g + 1]).enumerate() {
            let (a, b) = (self.nk_off[u], self.nk_off[u + 1]);
            if a == b {
                continue;
            }
            let node = self.nonkeys[u] as usize;
            let w = &self.nk_w_eff[a..b];
            let mut blend = [0.0; 8];
            for e in a..b {
                let r = &pc[pairs.of_edge[e] as usize - p0].rel;
                for c in 0..8 {
                    blend[c] += w[e - a] * r[c];
                }
            }
            let sp = [0, 1, 2].map(|c| self.src_p[3 * u + c] as f64);
            let sq = [0, 1, 2, 3].map(|c| self.src_q[4 * u + c] as f64);
            let warp = dqb::Warp::new(&blend, sp, sq);
            let (mut out_p, mut out_q) = (warp.out.p, warp.out.q);
            if !self.offsets.is_empty() {
                let off = &self.offsets[7 * u..7 * u + 7];
                for c in 0..3 {
                    out_p[c] += off[c] as f64;
                }
                for c in 0..4 {
                    out_q[c] += off[3 + c] as f64;
                }
            }
            let o = t * self.n + node;
            let x = [0, 1, 2].map(|c| poses.position[o][c] as f64 - out_p[c]);
            let f = self.metric_frame(t, node);
            let k = match s.anchor_metric {
                AnchorMetric::Release => Some([1.0; 3]),
                _ => self.metric(f, node),
            };
            let (mut g_p, mut g_q) = ([0.0; 3], [0.0; 4]);
            let cot = &mut uc[lu];
            cot.pose = [0.0; 7];
            if let Some(k) = k {
                let (d, g) = self.distance(f, k, x);
                sums[0] += d;
                g_p = g.map(|v| -wp * v);
                for c in 0..3 {
                    cot.pose[c] = wp * g[c];
                }
            }
            if s.dqb_rotation != 0.0 {
                let (qu, qn) = q4::normalize(q4::q64(poses.rotation[o]));
                let r = [0, 1, 2, 3].map(|c| out_q[c] - qu[c]);
                let len = q4::norm(r);
                sums[1] += len;
                if len > 0.0 {
                    g_q = r.map(|v| wq * v / len);
                    let own = q4::normalize_vjp(qu, qn, g_q.map(|v| -v));
                    cot.pose[3..].copy_from_slice(&own);
                }
            }
            let wg = warp.vjp(g_p, g_q);
            for c in 0..3 {
                cot.src[c] += wg.src_p[c];
                cot.offset[c] += g_p[c];
            }
            for c in 0..4 {
                cot.src[3 + c] += wg.src_q[c];
                cot.offset[3 + c] += g_q[c];
            }
            for e in a..b {
                let c = &mut pc[pairs.of_edge[e] as usize - p0];
                g_w[e - e0] += (0..8).map(|k| c.rel[k] * wg.blend[k]).sum::<f64>();
                for k in 0..8 {
                    c.g[k] += w[e - a] * wg.blend[k];
                }
            }
        }
        for (lp, c) in pc.iter_mut().enumerate() {
            let (k, th) = (pairs.key[p0 + lp] as usize, pairs.t[p0 + lp] as usize);
            let (gd, gs) = dqb::relative_vjp(&dq[t * nk + k].0, &dq[th * nk + k].0, c.sign, &c.g);
            c.g_dst = gd;
            for k in 0..8 {
                c.g_src[k] += gs[k];
            }
        }
        sums
    }
}

/// A group of non-keys sharing a t̂ in [`GraphObjective::dqb_terms`], with its own slices:
/// `nonkeys` of its non-keys, `g_w` of their edges, `pairs` of its (key, t̂) pairs.
struct Group<'a> {
    g: usize,
    nonkeys: &'a mut [NonkeyCot],
    g_w: &'a mut [f64],
    pairs: &'a mut [PairCot],
}

/// ‖a − b‖² in f64.
pub(super) fn dist2(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3).map(|c| (a[c] as f64 - b[c] as f64).powi(2)).sum()
}

/// `v` cut at `bounds` (ascending, from 0 to `v.len()`) into consecutive slices.
fn split_at_bounds<'a, T>(mut v: &'a mut [T], bounds: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(bounds.len().saturating_sub(1));
    for w in bounds.windows(2) {
        let (head, tail) = std::mem::take(&mut v).split_at_mut(w[1] - w[0]);
        out.push(head);
        v = tail;
    }
    out
}

/// One (key, t̂) pair in [`GraphObjective::dqb_terms`].
#[derive(Debug, Clone, Copy, Default)]
struct PairCot {
    /// The relative transform T_k(t) T_k(t̂)⁻¹ at the current frame t, and its sign.
    rel: Dq,
    sign: f64,
    /// Its cotangent at t: Σ over its edges of w'_e · g_blend.
    g: Dq,
    /// The cotangent of the key's dual quaternion at t, and at t̂ summed over the frames.
    g_dst: Dq,
    g_src: Dq,
}

/// The cotangents of one non-key in [`GraphObjective::dqb_terms`].
#[derive(Debug, Clone, Copy, Default)]
struct NonkeyCot {
    /// Of its pose (position, raw rotation) at the current frame.
    pose: [f64; 7],
    /// Of its source pose (position, raw rotation), summed over the batch frames.
    src: [f64; 7],
    /// Of its pose offsets, summed over the batch frames.
    offset: [f64; 7],
}

/// Buffers of the blend weights' forward and backward passes, `[E_n]` each but `tmp`.
#[derive(Debug, Default)]
struct WeightScratch {
    l: Vec<f64>,
    theta: Vec<f64>,
    dw: Vec<f64>,
    g_l: Vec<f64>,
    g_theta: Vec<f64>,
    g_dw: Vec<f64>,
    tmp: Vec<f64>,
    /// The cotangent of θ `[K]`.
    g_theta_key: Vec<f64>,
}

/// Buffers of [`GraphObjective::dqb_terms`], kept across steps.
#[derive(Debug, Default)]
pub(super) struct DqbScratch {
    /// Unit dual quaternions of the keys' poses with ‖q‖, their cotangents and the pose
    /// cotangents they give `[T, K]`.
    dq_key: Vec<(Dq, f64)>,
    g_dq: Vec<Dq>,
    key_grad: Vec<([f64; 4], [f64; 3])>,
    /// Per (key, t̂) pair `[P]`, per non-key edge (the cotangent of w', summed over the
    /// frames) `[E_n]`, per non-key `[nu]`.
    pair: Vec<PairCot>,
    g_w: Vec<f64>,
    nonkey: Vec<NonkeyCot>,
    weights: WeightScratch,
}
