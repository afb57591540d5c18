//! Foreground Gaussians: sampled on the masked depth prior of reference frames, coloured
//! from the image, sized by their sampling density, and skinned to their nearest nodes.
//!
//! - Sampling: pixels drawn uniformly (with replacement) among the valid foreground pixels of
//!   a reference frame, jittered uniformly inside the pixel, unprojected at the pixel's depth.
//! - Colour: the pixel's straight RGB. Scale: isotropic, the mean distance to the 3 nearest
//!   samples of the same reference frame, clamped to the 5 %..95 % quantiles over all
//!   samples (Shape of Motion's `init_fg_from_tracks_3d`).
//! - Skinning: the K nearest nodes observed at the Gaussian's reference frame r (all nodes
//!   when fewer than K are observed there), weights `exp(−d²/2σ²)` with σ² the mean of the K
//!   squared distances, normalised to sum 1.
//! - Pose at frame t (linear blend skinning of node-local offsets):
//!   `μ_t = Σ_k w_k [R_k(t) R_k(r)ᵀ (μ_r − X_k(r)) + X_k(t)]`, and the rotation the
//!   hemisphere-aligned, normalised blend of the quaternions `R_k(t) R_k(r)ᵀ` (identity at r).

use glam::{Quat, Vec3, Vec4};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::lift::FrameInputs;
use super::motion::Nodes;
use crate::util::rng::Rng;

/// Gaussians sampled on reference frames, `[N]` each.
#[derive(Debug, Clone, Default)]
pub struct Seeds {
    /// Reference frame r of each Gaussian.
    pub frame: Vec<u32>,
    /// Position at r, world units.
    pub pos: Vec<Vec3>,
    /// Straight RGB in [0, 1].
    pub color: Vec<[f32; 3]>,
    /// Isotropic scale, world units.
    pub scale: Vec<f32>,
}

/// Draw `n` Gaussians on the valid foreground depth of reference frame `frame` (`f` must
/// carry its RGB). Empty when the frame has no valid foreground pixel.
pub fn sample_frame(f: &FrameInputs, frame: u32, n: usize, rng: &mut Rng) -> Seeds {
    let candidates: Vec<usize> = (0..f.depth.len()).filter(|&i| f.depth[i] > 0.0).collect();
    let mut s = Seeds::default();
    let Some(rgb) = f.rgb.as_ref() else { return s };
    if candidates.is_empty() {
        return s;
    }
    for _ in 0..n {
        let i = candidates[(rng.next_u64() % candidates.len() as u64) as usize];
        let (ix, iy) = (i % f.width, i / f.width);
        let (jx, jy) = (rng.uniform(), rng.uniform());
        s.pos.push(f.unproject(ix as f64 + jx, iy as f64 + jy, f.depth[i] as f64));
        s.color.push([rgb.at(ix, iy, 0), rgb.at(ix, iy, 1), rgb.at(ix, iy, 2)]);
        s.frame.push(frame);
    }
    s.scale = knn_scales(&s.pos);
    s
}

/// Mean distance of every point `[N]` to its 3 nearest other points (0 when alone).
pub fn knn_scales(pos: &[Vec3]) -> Vec<f32> {
    let pts: Vec<[f32; 3]> = pos.iter().map(|p| p.to_array()).collect();
    let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(&pts) else {
        return vec![0.0; pts.len()];
    };
    let k =
        std::num::NonZero::new(4.min(pts.len()).max(1)).unwrap_or(std::num::NonZero::<usize>::MIN);
    pts.par_iter()
        .map(|q| {
            let mut d: Vec<f32> = tree
                .query(q)
                .nearest_n::<SquaredEuclidean<f32>>(k)
                .execute()
                .iter()
                .map(|r| r.distance)
                .collect();
            d.sort_by(f32::total_cmp);
            let others = &d[1.min(d.len())..];
            if others.is_empty() {
                0.0
            } else {
                others.iter().map(|x| x.sqrt()).sum::<f32>() / others.len() as f32
            }
        })
        .collect()
}

/// Clamp `v` to its `lo`..`hi` quantiles (Shape of Motion clamps scales to 5 %..95 %).
pub fn clamp_quantiles(v: &mut [f32], lo: f64, hi: f64) {
    if v.is_empty() {
        return;
    }
    let mut sorted = v.to_vec();
    sorted.sort_by(f32::total_cmp);
    let q = |p: f64| sorted[((sorted.len() - 1) as f64 * p).round() as usize];
    let (a, b) = (q(lo), q(hi));
    for x in v {
        *x = x.clamp(a, b);
    }
}

/// Skinning of N Gaussians to K nodes: `[N, K]` node ids and weights (padding: weight 0).
pub struct Skin {
    /// Nodes per Gaussian K.
    pub k: usize,
    /// `[N, K]` node indices.
    pub node: Vec<u32>,
    /// `[N, K]` weights, summing to 1 per Gaussian.
    pub weight: Vec<f32>,
}

/// Skin every seed to its `k` nearest nodes at its reference frame (see the module doc).
pub fn skin(seeds: &Seeds, nodes: &Nodes, k: usize) -> Skin {
    let m = nodes.num_nodes;
    let mut frames: Vec<u32> = seeds.frame.clone();
    frames.sort_unstable();
    frames.dedup();
    // One tree per reference frame over the nodes observed there (all nodes if too few).
    let trees: Vec<(u32, Vec<u32>, Option<ImmutableKdTree<f32, 3>>)> = frames
        .par_iter()
        .map(|&r| {
            let base = r as usize * m;
            let mut members: Vec<u32> =
                (0..m as u32).filter(|&i| nodes.observed[base + i as usize]).collect();
            if members.len() < k {
                members = (0..m as u32).collect();
            }
            let pts: Vec<[f32; 3]> =
                members.iter().map(|&i| nodes.pos[base + i as usize].to_array()).collect();
            (r, members, ImmutableKdTree::new_from_slice(&pts).ok())
        })
        .collect();
    let kk = std::num::NonZero::new(k.min(m).max(1)).unwrap_or(std::num::NonZero::<usize>::MIN);
    let per: Vec<(Vec<u32>, Vec<f32>)> = (0..seeds.pos.len())
        .into_par_iter()
        .map(|g| {
            let (mut ids, mut ws) = (vec![0u32; k], vec![0f32; k]);
            let Some((_, members, Some(tree))) = trees.iter().find(|t| t.0 == seeds.frame[g])
            else {
                return (ids, ws);
            };
            let mut res: Vec<(f32, u32)> = tree
                .query(&seeds.pos[g].to_array())
                .nearest_n::<SquaredEuclidean<f32>>(kk)
                .execute()
                .iter()
                .map(|r| (r.distance, members[r.item as usize]))
                .collect();
            res.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            let var = res.iter().map(|r| r.0).sum::<f32>() / res.len().max(1) as f32;
            let raw: Vec<f32> = res
                .iter()
                .map(|r| if var > 0.0 { (-r.0 / (2.0 * var)).exp() } else { 1.0 })
                .collect();
            let sum: f32 = raw.iter().sum();
            for (j, (r, w)) in res.iter().zip(&raw).enumerate() {
                ids[j] = r.1;
                ws[j] = w / sum;
            }
            (ids, ws)
        })
        .collect();
    let (mut node, mut weight) = (Vec::with_capacity(per.len() * k), Vec::new());
    for (i, w) in per {
        node.extend(i);
        weight.extend(w);
    }
    Skin { k, node, weight }
}

/// Positions and rotations (`w, x, y, z`) `[N]` of the seeds at frame `t`.
pub fn pose(seeds: &Seeds, skin: &Skin, nodes: &Nodes, t: usize) -> (Vec<[f32; 3]>, Vec<[f32; 4]>) {
    let m = nodes.num_nodes;
    (0..seeds.pos.len())
        .into_par_iter()
        .map(|g| {
            let r = seeds.frame[g] as usize;
            let (mut p, mut q) = (Vec3::ZERO, Vec4::ZERO);
            let mut first: Option<Vec4> = None;
            for j in 0..skin.k {
                let w = skin.weight[g * skin.k + j];
                if w == 0.0 {
                    continue;
                }
                let n = skin.node[g * skin.k + j] as usize;
                let rel: Quat = nodes.rot[t * m + n] * nodes.rot[r * m + n].conjugate();
                p += w * (rel * (seeds.pos[g] - nodes.pos[r * m + n]) + nodes.pos[t * m + n]);
                let v = Vec4::from(rel);
                let v = match first {
                    Some(f) if f.dot(v) < 0.0 => -v,
                    Some(_) => v,
                    None => {
                        first = Some(v);
                        v
                    }
                };
                q += w * v;
            }
            if first.is_none() {
                return (seeds.pos[g].to_array(), [1.0, 0.0, 0.0, 0.0]);
            }
            let q = Quat::from_vec4(q).normalize();
            (p.to_array(), [q.w, q.x, q.y, q.z])
        })
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knn_scale_of_a_grid_is_its_spacing() {
        let pos: Vec<Vec3> =
            (0..25).map(|i| Vec3::new((i % 5) as f32 * 0.1, (i / 5) as f32 * 0.1, 0.0)).collect();
        let s = knn_scales(&pos);
        // The centre point's three nearest neighbours are all at 0.1.
        assert!((s[12] - 0.1).abs() < 1e-6, "{}", s[12]);
        let mut v = vec![0.0, 1.0, 2.0, 3.0, 100.0];
        clamp_quantiles(&mut v, 0.25, 0.75);
        assert_eq!(v, vec![1.0, 1.0, 2.0, 3.0, 3.0]);
    }

    #[test]
    fn skinned_pose_follows_a_rigidly_moving_node_set() {
        // Three nodes translate by +1 in x and turn 90° about z between frames 0 and 1.
        let rot = Quat::from_rotation_z(std::f32::consts::FRAC_PI_2);
        let p0 = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let p1: Vec<Vec3> = p0.iter().map(|&p| rot * p + Vec3::X).collect();
        let nodes = Nodes {
            num_nodes: 3,
            canonical: 0,
            pos: p0.iter().copied().chain(p1).collect(),
            rot: vec![Quat::IDENTITY, Quat::IDENTITY, Quat::IDENTITY, rot, rot, rot],
            observed: vec![true; 6],
        };
        let seeds = Seeds {
            frame: vec![0],
            pos: vec![Vec3::new(0.3, 0.2, 0.5)],
            color: vec![[0.5; 3]],
            scale: vec![0.1],
        };
        let sk = skin(&seeds, &nodes, 3);
        assert!((sk.weight.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let (p, q) = pose(&seeds, &sk, &nodes, 1);
        let want = rot * seeds.pos[0] + Vec3::X;
        assert!((Vec3::from_array(p[0]) - want).length() < 1e-5, "{p:?} vs {want}");
        let got = Quat::from_xyzw(q[0][1], q[0][2], q[0][3], q[0][0]);
        assert!(got.angle_between(rot) < 2e-3, "{got:?}");
        let (p, _) = pose(&seeds, &sk, &nodes, 0);
        assert!((Vec3::from_array(p[0]) - seeds.pos[0]).length() < 1e-6);
    }
}
