//! Track trajectories in 3D, filled where the tracks are not observed, and the per-frame
//! rigid motion of each track's neighbourhood (the nodes that Gaussians are skinned to).
//!
//! 1. Every kept track (observed in at least two frames) gets a first trajectory `X⁰`:
//!    observed positions, linear interpolation inside gaps, constant outside.
//! 2. The canonical frame c is the frame with most observed tracks (Shape of Motion's
//!    `cano_t`). Each track's neighbourhood is its K nearest tracks at c.
//! 3. At every frame t, the neighbourhood's rigid motion from c to t is a weighted Procrustes
//!    (Kabsch) fit of `X⁰(·, c)` to `X⁰(·, t)`, observed neighbours weighing 1 and filled
//!    ones [`FILLED_WEIGHT`]: where a track is hidden, the visible part of its neighbourhood
//!    says how it moved. Unobserved positions are replaced by that fit's prediction; the
//!    fit's rotation is the node's orientation `R_k(t)` (identity at c).
//! 4. Optionally ([`smooth_in_time`]), each node's positions and orientations are smoothed
//!    over time with a Gaussian of σ frames: every frame's depth prior is lifted on its own,
//!    so the raw node motion jitters from frame to frame (Shape of Motion smooths its motion
//!    bases in its first optimisation instead).
//!
//! Shapes: positions and rotations are `[T, M]` flattened frame-major (`t·M + k`).

use glam::{DMat3, DQuat, DVec3, Quat, Vec3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

/// Procrustes weight of a neighbour whose position at t is filled, not observed.
pub const FILLED_WEIGHT: f64 = 0.05;

/// Observed 3D track positions, `[T, M]` frame-major (`None` = not observed).
pub struct Observations {
    /// Frames T.
    pub num_frames: usize,
    /// Tracks M.
    pub num_tracks: usize,
    /// `[T, M]` observed positions.
    pub pos: Vec<Option<Vec3>>,
}

/// The nodes: kept tracks with a position and an orientation at every frame.
pub struct Nodes {
    /// Nodes M' (kept tracks).
    pub num_nodes: usize,
    /// The canonical frame c.
    pub canonical: usize,
    /// `[T, M']` positions.
    pub pos: Vec<Vec3>,
    /// `[T, M']` orientations (rotation from frame c to frame t).
    pub rot: Vec<Quat>,
    /// `[T, M']` whether the position is observed (not filled).
    pub observed: Vec<bool>,
}

/// Fill the kept tracks and fit the neighbourhood motions (see the module doc); `k` is the
/// neighbourhood size. `None` when fewer than 3 tracks are observed in two frames or more.
pub fn fit_nodes(obs: &Observations, k: usize) -> Option<Nodes> {
    let (tn, m) = (obs.num_frames, obs.num_tracks);
    let kept: Vec<usize> = (0..m)
        .filter(|&j| (0..tn).filter(|&t| obs.pos[t * m + j].is_some()).count() >= 2)
        .collect();
    let mn = kept.len();
    if mn < 3 {
        return None;
    }
    // X⁰ and observed flags, node-major [M', T] while filling.
    let filled: Vec<(Vec<DVec3>, Vec<bool>)> = kept
        .par_iter()
        .map(|&j| {
            let seen: Vec<Option<DVec3>> =
                (0..tn).map(|t| obs.pos[t * m + j].map(|p| p.as_dvec3())).collect();
            (interpolate(&seen), seen.iter().map(Option::is_some).collect())
        })
        .collect();
    let canonical = (0..tn)
        .max_by_key(|&t| (filled.iter().filter(|f| f.1[t]).count(), std::cmp::Reverse(t)))
        .unwrap_or(0);
    let at_c: Vec<[f64; 3]> = filled.iter().map(|f| f.0[canonical].to_array()).collect();
    let hood = neighbourhoods(&at_c, k.max(3).min(mn));
    let fits: Vec<Vec<(DVec3, DQuat)>> = (0..mn)
        .into_par_iter()
        .map(|i| {
            (0..tn)
                .map(|t| {
                    let pairs = hood[i].iter().map(|&j| {
                        let w = if filled[j].1[t] { 1.0 } else { FILLED_WEIGHT };
                        (filled[j].0[canonical], filled[j].0[t], w)
                    });
                    let (q, a_mean, b_mean) = procrustes(pairs);
                    let p = if filled[i].1[t] {
                        filled[i].0[t]
                    } else {
                        q * (filled[i].0[canonical] - a_mean) + b_mean
                    };
                    (p, q)
                })
                .collect()
        })
        .collect();
    let mut pos = Vec::with_capacity(tn * mn);
    let mut rot = Vec::with_capacity(tn * mn);
    let mut observed = Vec::with_capacity(tn * mn);
    for t in 0..tn {
        for i in 0..mn {
            pos.push(fits[i][t].0.as_vec3());
            rot.push(fits[i][t].1.as_quat());
            observed.push(filled[i].1[t]);
        }
    }
    Some(Nodes { num_nodes: mn, canonical, pos, rot, observed })
}

/// Smooth every node's motion over time, in place: a Gaussian of `sigma` frames (truncated at
/// 3σ, renormalised at the ends of the video) on the positions, and the same weights on the
/// orientations, each neighbour frame's quaternion sign-aligned to the frame's own before
/// the weighted sum is normalised. `sigma` ≤ 0 leaves the nodes as they are.
pub fn smooth_in_time(nodes: &mut Nodes, frames: usize, sigma: f64) {
    let m = nodes.num_nodes;
    if sigma <= 0.0 || frames < 2 || m == 0 {
        return;
    }
    let reach = ((3.0 * sigma).ceil() as usize).min(frames - 1);
    let g: Vec<f64> = (0..=reach).map(|d| (-0.5 * (d as f64 / sigma).powi(2)).exp()).collect();
    let (pos, rot) = (&nodes.pos, &nodes.rot);
    let (new_pos, new_rot): (Vec<Vec3>, Vec<Quat>) = (0..frames * m)
        .into_par_iter()
        .map(|at| {
            let (t, i) = (at / m, at % m);
            let q_t = rot[at].as_dquat();
            let (mut sw, mut sp, mut sq) = (0.0, DVec3::ZERO, DQuat::from_xyzw(0., 0., 0., 0.));
            for s in t.saturating_sub(reach)..(t + reach + 1).min(frames) {
                let w = g[t.abs_diff(s)];
                let q = rot[s * m + i].as_dquat();
                let q = if q.dot(q_t) < 0.0 { -q } else { q };
                sw += w;
                sp += w * pos[s * m + i].as_dvec3();
                sq += q * w;
            }
            let q = if sq.length_squared() > 0.0 { sq.normalize() } else { q_t };
            ((sp / sw).as_vec3(), q.as_quat())
        })
        .unzip();
    (nodes.pos, nodes.rot) = (new_pos, new_rot);
}

/// Linear interpolation inside gaps, constant extrapolation outside (at least one `Some`).
pub fn interpolate(seen: &[Option<DVec3>]) -> Vec<DVec3> {
    let idx: Vec<usize> = (0..seen.len()).filter(|&t| seen[t].is_some()).collect();
    let at = |t: usize| seen[t].unwrap_or_default();
    let mut out = Vec::with_capacity(seen.len());
    let mut next = 0;
    for t in 0..seen.len() {
        while next < idx.len() && idx[next] < t {
            next += 1;
        }
        let v = match (next.checked_sub(1).map(|p| idx[p]), idx.get(next).copied()) {
            (_, Some(b)) if b == t => at(t),
            (Some(a), Some(b)) => at(a).lerp(at(b), (t - a) as f64 / (b - a) as f64),
            (Some(a), None) => at(a),
            (None, Some(b)) => at(b),
            (None, None) => DVec3::ZERO,
        };
        out.push(v);
    }
    out
}

/// The `k` nearest points of every point `[M, 3]` (itself first), ties broken by index.
pub fn neighbourhoods(points: &[[f64; 3]], k: usize) -> Vec<Vec<usize>> {
    let pts: Vec<[f32; 3]> = points.iter().map(|p| p.map(|v| v as f32)).collect();
    let (Ok(tree), Some(kk)) =
        (ImmutableKdTree::<f32, 3>::new_from_slice(&pts), std::num::NonZero::new(k))
    else {
        return vec![Vec::new(); pts.len()];
    };
    pts.par_iter()
        .enumerate()
        .map(|(i, q)| {
            let mut res: Vec<(f32, usize)> = tree
                .query(q)
                .nearest_n::<SquaredEuclidean<f32>>(kk)
                .execute()
                .iter()
                .map(|r| (r.distance, r.item as usize))
                .collect();
            res.sort_by(|a, b| {
                (a.1 != i).cmp(&(b.1 != i)).then(a.0.total_cmp(&b.0)).then(a.1.cmp(&b.1))
            });
            res.into_iter().map(|r| r.1).collect()
        })
        .collect()
}

/// Weighted rigid fit (Horn's quaternion method): the rotation q and the weighted means
/// ā, b̄ minimising Σ w‖q(a − ā) − (b − b̄)‖². Identity for degenerate inputs.
pub fn procrustes(
    pairs: impl Iterator<Item = (DVec3, DVec3, f64)> + Clone,
) -> (DQuat, DVec3, DVec3) {
    let (mut sw, mut sa, mut sb) = (0.0, DVec3::ZERO, DVec3::ZERO);
    for (a, b, w) in pairs.clone() {
        sw += w;
        sa += w * a;
        sb += w * b;
    }
    if sw <= 0.0 {
        return (DQuat::IDENTITY, DVec3::ZERO, DVec3::ZERO);
    }
    let (am, bm) = (sa / sw, sb / sw);
    // S = Σ w (a − ā)(b − b̄)ᵀ, column-major: S.col(j)[i] = S_ij.
    let mut s = DMat3::ZERO;
    for (a, b, w) in pairs {
        let (da, db) = (w * (a - am), b - bm);
        s += DMat3::from_cols(da * db.x, da * db.y, da * db.z);
    }
    let e = |i: usize, j: usize| s.col(j)[i];
    let (sxx, sxy, sxz) = (e(0, 0), e(0, 1), e(0, 2));
    let (syx, syy, syz) = (e(1, 0), e(1, 1), e(1, 2));
    let (szx, szy, szz) = (e(2, 0), e(2, 1), e(2, 2));
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let v = max_eigenvector(n);
    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]);
    let q = if q.length_squared() > 0.5 && q.is_finite() { q.normalize() } else { DQuat::IDENTITY };
    (if q.w < 0.0 { -q } else { q }, am, bm)
}

/// Eigenvector of the largest eigenvalue of a symmetric 4x4 matrix (cyclic Jacobi).
fn max_eigenvector(mut a: [[f64; 4]; 4]) -> [f64; 4] {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..30 {
        let off: f64 = (0..4)
            .flat_map(|i| (0..4).map(move |j| (i, j)))
            .filter(|(i, j)| i != j)
            .map(|(i, j)| a[i][j] * a[i][j])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..3 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let sign = if theta >= 0.0 { 1.0 } else { -1.0 };
                let t = sign / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..4 {
                    let (akp, akq) = (a[k][p], a[k][q]);
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for k in 0..4 {
                    let (apk, aqk) = (a[p][k], a[q][k]);
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for row in v.iter_mut() {
                    let (vkp, vkq) = (row[p], row[q]);
                    row[p] = c * vkp - s * vkq;
                    row[q] = s * vkp + c * vkq;
                }
            }
        }
    }
    let best = (0..4).max_by(|&i, &j| a[i][i].total_cmp(&a[j][j])).unwrap_or(0);
    [v[0][best], v[1][best], v[2][best], v[3][best]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn procrustes_recovers_a_rigid_motion() {
        let q = DQuat::from_axis_angle(DVec3::new(1.0, 2.0, -0.5).normalize(), 1.1);
        let shift = DVec3::new(0.3, -2.0, 1.0);
        let a: Vec<DVec3> =
            [[0.0, 0.0, 0.0], [1.0, 0.2, 0.0], [0.1, 1.0, 0.3], [0.4, 0.3, 1.2], [-0.5, 0.7, 0.2]]
                .iter()
                .map(|p| DVec3::from_array(*p))
                .collect();
        let pairs = a.iter().map(|&p| (p, q * p + shift, 1.0));
        let (fit, am, bm) = procrustes(pairs);
        assert!(fit.angle_between(q) < 1e-9, "{fit:?} vs {q:?}");
        for &p in &a {
            assert!((fit * (p - am) + bm - (q * p + shift)).length() < 1e-9);
        }
        // A 180° turn, where the largest eigenvalue's vector has w = 0.
        let half = DQuat::from_rotation_z(std::f64::consts::PI);
        let (fit, ..) = procrustes(a.iter().map(|&p| (p, half * p, 1.0)));
        assert!(fit.angle_between(half) < 1e-9);
    }

    #[test]
    fn smoothing_in_time_keeps_steady_motion_and_removes_jitter() {
        let (tn, m) = (30, 2);
        let steady = |t: usize| {
            (Vec3::new(0.1 * t as f32, 1.0, -0.5), Quat::from_rotation_y(0.05 * t as f32))
        };
        let mut nodes = Nodes {
            num_nodes: m,
            canonical: 0,
            pos: Vec::new(),
            rot: Vec::new(),
            observed: vec![true; tn * m],
        };
        for t in 0..tn {
            let (p, q) = steady(t);
            let jitter = if t % 2 == 0 { 0.05 } else { -0.05 };
            // node 0 moves steadily; node 1 the same plus a frame-to-frame jitter (and -q)
            nodes.pos.extend([p, p + Vec3::splat(jitter)]);
            nodes.rot.extend([q, -q]);
        }
        let before = (nodes.pos.clone(), nodes.rot.clone());
        smooth_in_time(&mut nodes, tn, 0.0);
        assert_eq!((&nodes.pos, &nodes.rot), (&before.0, &before.1), "σ = 0 changes nothing");
        smooth_in_time(&mut nodes, tn, 2.0);
        for t in 6..tn - 6 {
            let (p, q) = steady(t);
            assert!((nodes.pos[t * m] - p).length() < 1e-5, "t={t}: {}", nodes.pos[t * m]);
            assert!(nodes.rot[t * m].angle_between(q) < 1e-3, "t={t}");
            assert!((nodes.pos[t * m + 1] - p).length() < 1e-3, "jitter left at t={t}");
            assert!(nodes.rot[t * m + 1].angle_between(q) < 1e-3, "sign flip at t={t}");
        }
    }

    #[test]
    fn interpolation_fills_gaps_and_holds_ends() {
        let s = |x: f64| Some(DVec3::splat(x));
        let out = interpolate(&[None, s(1.0), None, None, s(4.0), None]);
        let xs: Vec<f64> = out.iter().map(|v| v.x).collect();
        assert_eq!(xs, vec![1.0, 1.0, 2.0, 3.0, 4.0, 4.0]);
    }

    #[test]
    fn hidden_track_follows_its_visible_neighbours() {
        // Five tracks translate by +t along x and rotate about z; track 0 is hidden at t=1..3.
        let base =
            [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.3], [0.2, 0.2, 0.1]];
        let tn = 5;
        let motion = |t: usize, p: [f64; 3]| {
            DQuat::from_rotation_z(0.2 * t as f64) * DVec3::from_array(p) + DVec3::X * t as f64
        };
        let mut pos = Vec::new();
        for t in 0..tn {
            for (j, p) in base.iter().enumerate() {
                let hidden = j == 0 && (1..=3).contains(&t);
                pos.push((!hidden).then(|| motion(t, *p).as_vec3()));
            }
        }
        let obs = Observations { num_frames: tn, num_tracks: 5, pos };
        let nodes = fit_nodes(&obs, 5).unwrap();
        assert_eq!(nodes.canonical, 0, "frame 0 sees every track; ties go to the first");
        for t in 0..tn {
            let err = (nodes.pos[t * 5].as_dvec3() - motion(t, base[0])).length();
            assert!(err < 1e-5, "frame {t}: error {err}");
            let angle =
                nodes.rot[t * 5].as_dquat().angle_between(DQuat::from_rotation_z(0.2 * t as f64));
            assert!(angle < 2e-3, "frame {t}: rotation off by {angle}");
        }
    }
}
