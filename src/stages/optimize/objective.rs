//! The recipe's non-image terms, rebuilt whenever density control changes the Gaussians:
//! - vanilla: the base models' motion locality among all dynamic Gaussians, kNN isometry +
//!   rigidity (edges and rest lengths at frame 0) plus velocity and acceleration in App.
//!   A.2's forms, each a mean over its terms (edges × frames, Gaussians × frames) as the base
//!   models (MoSca, SoM) average theirs, with the base model's weights: MoSca's photometric
//!   phase, λ_iso = λ_rigid = 10, λ_vel = λ_acc = 5 (`--vanilla-knn`, `--vanilla-vel`,
//!   `--vanilla-acc`). App. A.2's sums over every Gaussian and frame would outweigh the
//!   per-pixel mean of L_rgb by about 10⁴, so positions would follow the smoothness terms,
//!   not the images;
//! - usplat4d: [`GraphObjective`] (L_key + L_non-key) on the graph of the trained Gaussians.
//!   Its p° and u of a Gaussian are those of the input Gaussian it descends from
//!   ([`TrainState::origin`]); a new Gaussian is a non-key with its origin's t̂ and edges.
//!   At a density pass the objective is rebuilt with the learned key-key weights and takes
//!   over the learned rest lengths, the keys' θ and the non-keys' trained source poses,
//!   weight and pose offsets ([`GraphObjective::carry_over`], the release's
//!   `densify_params`).

use std::collections::HashMap;

use glam::DMat3;

use super::graph_loss::{Anchors, GraphObjective, GraphSettings, GraphTables};
use super::motion::{self, EdgeSet, MotionForm};
use super::poses::{PoseGrads, Poses};
use super::smoothness;
use super::state::TrainState;
use crate::tables::edges::{EdgeKind, Edges};
use crate::tables::key_nodes::{KeyNodes, Role};

/// What the graph objective is built from (fixed for a run; its `[T, N]` p° and u come
/// and go with the objective, [`OriginAnchors`]).
pub struct GraphSource {
    /// The input key-node table.
    pub keys: KeyNodes,
    /// The input edges table.
    pub edges: Edges,
    /// q° at t̂ (the key-node table's) of each input Gaussian of that table, by
    /// `gaussian_id`: the DQB source rotation of the non-keys that descend from it.
    pub q_hat: HashMap<u32, [f32; 4]>,
    /// R_cw of each frame's training camera `[T]`.
    pub rot_cw: Vec<DMat3>,
    /// λ / unit² of the input edges table's non-key weights (from its graph metadata;
    /// `None` when it has none).
    pub nonkey_lambda: Option<f64>,
}

/// p° and u `[T, rows]` of Gaussians by the input Gaussian each descends from: read from
/// the input model and uncertainty table when a run starts, handed over by the objective
/// ([`GraphObjective::take_anchors`]) at a density pass. Every Gaussian of one origin has
/// the same rows.
pub struct OriginAnchors {
    /// The origin of each row.
    pub origin: Vec<u32>,
    /// p° `[T, rows]`.
    pub p0: Vec<[f32; 3]>,
    /// u `[T, rows]` (φ = 1e8 where the table has no value).
    pub u: Vec<f32>,
}

/// The vanilla recipe's kNN motion graph over the dynamic Gaussians.
pub struct KnnMotion {
    nodes: Vec<u32>,
    src: Vec<u32>,
    dst: Vec<u32>,
    w: Vec<f64>,
    rest: Vec<f64>,
}

impl KnnMotion {
    /// kNN edges among the dynamic Gaussians of `state` at frame 0.
    pub fn new(state: &TrainState, k: usize) -> Self {
        let nodes: Vec<u32> =
            (0..state.n() as u32).filter(|&i| state.dynamic[i as usize]).collect();
        let p0: Vec<[f32; 3]> = nodes.iter().map(|&i| state.positions(0)[i as usize]).collect();
        Self::from_positions(nodes, &p0, k)
    }

    /// kNN edges among `nodes`, whose frame-0 positions are `p0`. The nodes are then
    /// relabelled in Z-order (Morton order) of `p0`, so that neighbours lie close together in
    /// the frame blocks that the terms gather and write (the terms read each edge's ends at
    /// random otherwise); the edges are the same, listed by the new source order.
    fn from_positions(nodes: Vec<u32>, p0: &[[f32; 3]], k: usize) -> Self {
        let (src, dst, w, rest) = motion::knn_edges(p0, k);
        let order = z_order(p0);
        let mut new_of = vec![0u32; order.len()];
        for (new, &old) in order.iter().enumerate() {
            new_of[old] = new as u32;
        }
        let mut first = vec![0usize; p0.len() + 1];
        for &s in &src {
            first[s as usize + 1] += 1;
        }
        for i in 0..p0.len() {
            first[i + 1] += first[i];
        }
        // stored as f32 in checkpoints: round now so a resumed run sees the same values
        let r32 = |x: f64| x as f32 as f64;
        let mut g = KnnMotion {
            nodes: order.iter().map(|&old| nodes[old]).collect(),
            src: Vec::with_capacity(src.len()),
            dst: Vec::with_capacity(src.len()),
            w: Vec::with_capacity(src.len()),
            rest: Vec::with_capacity(src.len()),
        };
        for (new, &old) in order.iter().enumerate() {
            for e in first[old]..first[old + 1] {
                g.src.push(new as u32);
                g.dst.push(new_of[dst[e] as usize]);
                g.w.push(r32(w[e]));
                g.rest.push(r32(rest[e]));
            }
        }
        g
    }

    /// The graph as named tensors for a checkpoint (indices are exact in f32 below 2²⁴),
    /// since a resumed run's current positions would give other neighbours.
    pub fn to_tensors(&self) -> Vec<(String, Vec<f32>)> {
        let f = |v: &[u32]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let g = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        vec![
            ("knn_nodes".into(), f(&self.nodes)),
            ("knn_src".into(), f(&self.src)),
            ("knn_dst".into(), f(&self.dst)),
            ("knn_w".into(), g(&self.w)),
            ("knn_rest".into(), self.rest.iter().map(|&x| x as f32).collect()),
        ]
    }

    /// The graph saved by [`Self::to_tensors`]; `None` when the tensors are not one.
    pub fn from_tensors(t: &[(String, Vec<f32>)]) -> Option<Self> {
        let get = |name: &str| t.iter().find(|(k, _)| k == name).map(|(_, v)| v);
        let u = |v: &Vec<f32>| v.iter().map(|&x| x as u32).collect::<Vec<u32>>();
        let d = |v: &Vec<f32>| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
        Some(KnnMotion {
            nodes: u(get("knn_nodes")?),
            src: u(get("knn_src")?),
            dst: u(get("knn_dst")?),
            w: d(get("knn_w")?),
            rest: d(get("knn_rest")?),
        })
    }

    /// Evaluate on `poses` with `[λ_iso = λ_rigid, λ_vel, λ_acc]`, add gradients, return the
    /// weighted terms.
    pub fn evaluate(
        &self,
        poses: &Poses,
        [lk, lv, la]: [f64; 3],
        grads: &mut PoseGrads,
    ) -> Vec<(&'static str, f64)> {
        if self.nodes.is_empty() {
            return Vec::new();
        }
        let es = EdgeSet { src: &self.src, dst: &self.dst, w: &self.w };
        let (nt, e) = (poses.frames, self.src.len());
        let per = |terms: usize| 1.0 / terms.max(1) as f64;
        let (iso_norm, rigid_norm) = (per(e * nt), per(e * nt.saturating_sub(1)));
        let (vel_norm, acc_norm) = smoothness::smoothness_means(nt, self.nodes.len());
        let [iso, rigid] = motion::stream_frames(poses, &self.nodes, 1, grads, |tr, g| {
            motion::isometry_rigidity(tr, es, &self.rest, (iso_norm, lk), (rigid_norm, lk), g, None)
        });
        let [vel, acc] = smoothness::smoothness(
            poses,
            &self.nodes,
            MotionForm::Paper,
            (vel_norm, lv),
            (acc_norm, la),
            grads,
        );
        vec![
            ("knn_isometry", lk * iso),
            ("knn_rigidity", lk * rigid),
            ("velocity", lv * vel),
            ("acceleration", la * acc),
        ]
    }
}

/// The indices of `points` in Z-order: Morton codes of 10 bits per axis over their bounding
/// box, ties by index.
fn z_order(points: &[[f32; 3]]) -> Vec<usize> {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in points {
        for c in 0..3 {
            lo[c] = lo[c].min(p[c]);
            hi[c] = hi[c].max(p[c]);
        }
    }
    let spread = |x: u32| {
        // bits b of x to bit 3b
        let mut v = x & 0x3ff;
        v = (v | (v << 16)) & 0x0300_00ff;
        v = (v | (v << 8)) & 0x0300_f00f;
        v = (v | (v << 4)) & 0x030c_30c3;
        (v | (v << 2)) & 0x0924_9249
    };
    let code = |p: &[f32; 3]| {
        (0..3).fold(0u32, |acc, c| {
            let span = hi[c] - lo[c];
            let q = if span > 0.0 { ((p[c] - lo[c]) / span * 1023.0) as u32 } else { 0 };
            acc | spread(q.min(1023)) << c
        })
    };
    let mut order: Vec<(u32, usize)> =
        points.iter().enumerate().map(|(i, p)| (code(p), i)).collect();
    order.sort_unstable();
    order.into_iter().map(|(_, i)| i).collect()
}

/// The usplat4d objective for the current Gaussians of `state`, the graph given by `edges`
/// (the input table at the start, the learned one at a density pass), with p° and u from
/// `anchors`, gathered into the state's order. The gathered copies are new buffers rather
/// than `anchors`' rearranged in place: steps ran about 6% slower on the rearranged ones
/// (`bench optimize` at N = 46,444 on 2 threads), and the copy's transient is only p° and
/// u, 16 bytes per Gaussian and frame.
pub fn build_graph(
    src: &GraphSource,
    state: &TrainState,
    edges: &Edges,
    anchors: OriginAnchors,
    settings: &GraphSettings,
) -> anyhow::Result<GraphObjective> {
    let (keys, edges) = trained_graph(state, &src.keys, edges);
    let OriginAnchors { origin, p0, u } = anchors;
    let mut row: HashMap<u32, usize> = HashMap::with_capacity(origin.len());
    for (r, &o) in origin.iter().enumerate() {
        row.entry(o).or_insert(r);
    }
    let rows = (state.origin.iter())
        .map(|o| row.get(o).copied())
        .collect::<Option<Vec<usize>>>()
        .ok_or_else(|| anyhow::anyhow!("graph objective: a Gaussian without p° and u"))?;
    let (nt, m) = (state.frames(), origin.len());
    let (p0, u) = (gather_rows(p0, nt, m, &rows), gather_rows(u, nt, m, &rows));
    let identity = [1.0, 0.0, 0.0, 0.0];
    let q_hat = state.origin.iter().map(|o| src.q_hat.get(o).copied().unwrap_or(identity));
    let anchors = Anchors { frames: nt, p0, u, q_hat: q_hat.collect() };
    let tables = GraphTables {
        key_nodes: &keys,
        edges: &edges,
        nonkey_lambda: src.nonkey_lambda.unwrap_or(f64::NAN),
    };
    GraphObjective::from_tables(anchors, &state.ids, tables, &src.rot_cw, settings.clone())
        .map_err(|e| anyhow::anyhow!("graph objective: {e}"))
}

/// Rows `rows` of the `[frames, m]` tensor `v` into a new `[frames, rows.len()]` one (`v`
/// dropped on return).
fn gather_rows<T: Copy>(v: Vec<T>, frames: usize, m: usize, rows: &[usize]) -> Vec<T> {
    let v = &v;
    (0..frames).flat_map(|t| rows.iter().map(move |&r| v[t * m + r])).collect()
}

/// Roles and edges of the trained Gaussians: inputs' rows for surviving Gaussians, the
/// origin's t̂ and non-key edges for new ones (role `nonkey`).
pub fn trained_graph(st: &TrainState, keys: &KeyNodes, edges: &Edges) -> (KeyNodes, Edges) {
    let row: HashMap<u32, usize> = keys.id.iter().enumerate().map(|(r, &i)| (i, r)).collect();
    let alive: std::collections::HashSet<u32> = st.ids.iter().copied().collect();
    let mut out = KeyNodes::default();
    for (&id, &origin) in st.ids.iter().zip(&st.origin) {
        let Some(&r) = row.get(&origin) else { continue };
        let own = id == origin;
        out.id.push(id);
        out.role.push(if own { keys.role[r] } else { Role::Nonkey });
        out.t_hat.push(keys.t_hat[r]);
        out.significant_period.push(if own { keys.significant_period[r] } else { 0 });
    }
    let mut by_src: HashMap<u32, Vec<usize>> = HashMap::new();
    for e in 0..edges.len() {
        by_src.entry(edges.src[e]).or_default().push(e);
    }
    let mut e_out = Edges::default();
    for kind in [EdgeKind::KeyKey, EdgeKind::NonkeyKey] {
        for (&id, &origin) in st.ids.iter().zip(&st.origin) {
            for &e in by_src.get(&origin).map(Vec::as_slice).unwrap_or(&[]) {
                let new_nonkey = id != origin;
                let k = if new_nonkey { EdgeKind::NonkeyKey } else { edges.kind[e] };
                if k == kind
                    && alive.contains(&edges.dst[e])
                    && (!new_nonkey || edges.kind[e] == EdgeKind::NonkeyKey)
                {
                    e_out.push(id, edges.dst[e], k, edges.weight[e]);
                }
            }
        }
    }
    (out, e_out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Z-order relabelling keeps the kNN graph: the same (source, destination) pairs of
    /// nodes with their rest lengths, grouped by source, and Z-order is spatial.
    #[test]
    fn relabelled_knn_graph_has_the_same_edges() {
        let mut rng = crate::util::rng::Rng::new(5);
        let p0: Vec<[f32; 3]> = (0..300).map(|_| [0; 3].map(|_| rng.uniform() as f32)).collect();
        let nodes: Vec<u32> = (0..300u32).map(|i| 3 * i + 1).collect();
        let g = KnnMotion::from_positions(nodes.clone(), &p0, 6);
        let (src, dst, _, rest) = motion::knn_edges(&p0, 6);
        let key = |a: u32, b: u32, r: f64| (a, b, (r as f32).to_bits());
        let mut want: Vec<_> = (0..src.len())
            .map(|e| key(nodes[src[e] as usize], nodes[dst[e] as usize], rest[e]))
            .collect();
        let mut got: Vec<_> = (0..g.src.len())
            .map(|e| key(g.nodes[g.src[e] as usize], g.nodes[g.dst[e] as usize], g.rest[e]))
            .collect();
        want.sort_unstable();
        got.sort_unstable();
        assert_eq!(got, want);
        assert!(g.src.windows(2).all(|s| s[0] <= s[1]), "grouped by source");
        let mut sorted = g.nodes.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, nodes);
        // neighbours are near in the new labels: mean |src − dst| far below random (~100)
        let mean = (0..g.src.len()).map(|e| g.src[e].abs_diff(g.dst[e]) as f64).sum::<f64>()
            / g.src.len() as f64;
        assert!(mean < 40.0, "mean label distance {mean}");
    }

    /// Every Gaussian translating by `v` per frame: the rigid terms vanish and the velocity
    /// term is λ_vel ‖v‖₁ whatever the number of frames and Gaussians (a mean, not a sum).
    #[test]
    fn vanilla_terms_are_means_over_gaussians_and_frames() {
        let v = [0.01f32, -0.02, 0.005];
        let velocity = |frames: usize, n: usize, weights: [f64; 3]| {
            let mut rng = crate::util::rng::Rng::new(3);
            let p0: Vec<[f32; 3]> = (0..n).map(|_| [0; 3].map(|_| rng.uniform() as f32)).collect();
            let mut poses = Poses::identity(frames, n);
            for t in 0..frames {
                for (i, p) in p0.iter().enumerate() {
                    let j = poses.idx(t, i);
                    poses.position[j] = [0, 1, 2].map(|c| p[c] + t as f32 * v[c]);
                }
            }
            let knn = KnnMotion::from_positions((0..n as u32).collect(), &p0, 4);
            let terms = knn.evaluate(&poses, weights, &mut PoseGrads::zeros(frames, n));
            let get = |name: &str| terms.iter().find(|(k, _)| *k == name).unwrap().1;
            assert!(get("knn_isometry").abs() < 1e-6 && get("knn_rigidity").abs() < 1e-6);
            assert!(get("acceleration").abs() < 1e-6, "{terms:?}");
            get("velocity")
        };
        let speed = v.iter().map(|x| x.abs() as f64).sum::<f64>();
        for (frames, n) in [(5, 20), (24, 20), (24, 200)] {
            for lv in [0.01, 5.0] {
                let got = velocity(frames, n, [10.0, lv, 5.0]);
                assert!((got - lv * speed).abs() < 1e-8 * lv.max(1.0), "T={frames} N={n}: {got}");
            }
        }
    }
}
