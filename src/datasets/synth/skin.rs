//! Posing: morph targets and linear blend skinning of every vertex (glTF 2.0 §3.7.3).
//!
//! A skinned vertex is `Σ_k w_k · world(joint_k) · inverseBind_k · p` with `p` the bind
//! position plus the weighted morph deltas; the skinned node's own transform is ignored, as
//! the spec requires. Unskinned parts take their node's world matrix. Output is glTF world
//! space, `[V, 3]` in flat vertex order; rayon over parts, each part writing its own range.

use glam::{Mat4, Vec3};
use rayon::prelude::*;

use super::anim::Pose;
use super::asset::{Asset, Part};

/// World positions of all vertices of `asset` in `pose`, `[V]`.
pub fn pose_vertices(asset: &Asset, pose: &Pose) -> Vec<Vec3> {
    let mut out = vec![Vec3::ZERO; asset.num_vertices()];
    let mut slices = Vec::with_capacity(asset.parts.len());
    let mut rest: &mut [Vec3] = &mut out;
    for p in &asset.parts {
        let (head, tail) = rest.split_at_mut(p.positions.len());
        slices.push((p, head));
        rest = tail;
    }
    slices.into_par_iter().for_each(|(part, dst)| pose_part(asset, pose, part, dst));
    out
}

fn pose_part(asset: &Asset, pose: &Pose, part: &Part, dst: &mut [Vec3]) {
    let weights = &pose.weights[part.node];
    let joints: Option<Vec<Mat4>> = part.skin.map(|s| {
        let skin = &asset.skins[s];
        skin.joints.iter().zip(&skin.inverse_bind).map(|(&j, ibm)| pose.world[j] * *ibm).collect()
    });
    let node = pose.world[part.node];
    for (i, d) in dst.iter_mut().enumerate() {
        let mut p = part.positions[i];
        for (t, w) in part.targets.iter().zip(weights) {
            p += *w * t[i];
        }
        *d = match &joints {
            Some(j) => skin_point(j, &part.influences[i], p, node),
            None => node.transform_point3(p),
        };
    }
}

/// Linear blend skinning of one point; weights are renormalised, and a vertex without any
/// weight falls back to the node transform `fallback`.
pub fn skin_point(
    joints: &[Mat4],
    (idx, w): &([u16; 8], [f32; 8]),
    p: Vec3,
    fallback: Mat4,
) -> Vec3 {
    let mut acc = Vec3::ZERO;
    let mut total = 0.0;
    for k in 0..8 {
        if w[k] != 0.0 {
            acc += w[k] * joints[idx[k] as usize].transform_point3(p);
            total += w[k];
        }
    }
    if total > 0.0 { acc / total } else { fallback.transform_point3(p) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Quat;

    #[test]
    fn hand_made_joint_blend() {
        // Joint 0 at rest (identity), joint 1 rotated 90° about z around the point (1, 0, 0),
        // with its inverse bind moving that point to the origin.
        let bind1 = Mat4::from_translation(Vec3::new(1.0, 0.0, 0.0));
        let world1 = bind1 * Mat4::from_quat(Quat::from_rotation_z(std::f32::consts::FRAC_PI_2));
        let joints = [Mat4::IDENTITY, world1 * bind1.inverse()];
        let p = Vec3::new(2.0, 0.0, 0.0);
        let only1 = ([1, 0, 0, 0, 0, 0, 0, 0], [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(
            skin_point(&joints, &only1, p, Mat4::IDENTITY)
                .abs_diff_eq(Vec3::new(1.0, 1.0, 0.0), 1e-6)
        );
        let half = ([0, 1, 0, 0, 0, 0, 0, 0], [0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(
            skin_point(&joints, &half, p, Mat4::IDENTITY)
                .abs_diff_eq(Vec3::new(1.5, 0.5, 0.0), 1e-6)
        );
        // Unnormalised weights are renormalised; no weight falls back to the node matrix.
        let double = ([0, 1, 0, 0, 0, 0, 0, 0], [1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!(
            skin_point(&joints, &double, p, Mat4::IDENTITY)
                .abs_diff_eq(Vec3::new(1.5, 0.5, 0.0), 1e-6)
        );
        let none = ([0; 8], [0.0; 8]);
        let t = Mat4::from_translation(Vec3::Y);
        assert_eq!(skin_point(&joints, &none, p, t), Vec3::new(2.0, 1.0, 0.0));
    }
}
