//! The training state: what `optimize` trains (issue 11, "What is trained"). Per-frame
//! poses of every Gaussian ([`Poses`]; static Gaussians keep one pose, tied across frames by
//! summing their gradients over frames), log-scales, opacity logits and colour/SH. Tables
//! stay linear: [`TrainState::to_gaussians`] and [`TrainState::frame_state`] convert back.

use super::poses::{PoseGrads, Poses};
use crate::model::{FrameState, Gaussians, Model};

/// Smallest opacity and scale kept when going to logit/log space.
const OPACITY_EPS: f32 = 1e-6;
const SCALE_MIN: f32 = 1e-12;

/// Logistic function.
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Inverse of [`sigmoid`] on [ε, 1 − ε].
pub fn logit(p: f32) -> f32 {
    let p = p.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
    (p / (1.0 - p)).ln()
}

/// Everything optimised, `[N]` arrays in model order (and the poses `[T, N]`).
#[derive(Debug, Clone, PartialEq)]
pub struct TrainState {
    /// `gaussian_id` of each Gaussian.
    pub ids: Vec<u32>,
    /// Dynamic (true) or static background (false, pose tied across frames).
    pub dynamic: Vec<bool>,
    /// `gaussian_id` of the input Gaussian each one descends from (itself, or the parent
    /// that density control cloned or split).
    pub origin: Vec<u32>,
    /// Per-frame poses `[T, N]`.
    pub poses: Poses,
    /// Log of the linear scales `[N, 3]`.
    pub log_scale: Vec<[f32; 3]>,
    /// Opacity logits `[N]`.
    pub logit_opacity: Vec<f32>,
    /// Degree-0 colour `[N, 3]`.
    pub color: Vec<[f32; 3]>,
    /// SH degree.
    pub sh_degree: u8,
    /// Higher SH coefficients `[N, K, 3]` flattened.
    pub sh_rest: Vec<f32>,
}

/// Gradients w.r.t. a [`TrainState`], same layout except the poses, which hold only some
/// frames (the image step's: one row per batch frame).
#[derive(Debug, Clone, PartialEq)]
pub struct StateGrads {
    /// Pose gradients `[rows, N]`.
    pub poses: PoseGrads,
    /// dL/d log-scale `[N, 3]`.
    pub log_scale: Vec<[f32; 3]>,
    /// dL/d opacity logit `[N]`.
    pub logit_opacity: Vec<f32>,
    /// dL/d colour `[N, 3]`.
    pub color: Vec<[f32; 3]>,
    /// dL/d SH rest `[N, K, 3]`.
    pub sh_rest: Vec<f32>,
}

impl StateGrads {
    /// Zero gradients for `s`, with `pose_rows` rows of pose gradients.
    pub fn zeros(s: &TrainState, pose_rows: usize) -> Self {
        StateGrads {
            poses: PoseGrads::zeros(pose_rows, s.n()),
            log_scale: vec![[0.0; 3]; s.n()],
            logit_opacity: vec![0.0; s.n()],
            color: vec![[0.0; 3]; s.n()],
            sh_rest: vec![0.0; s.sh_rest.len()],
        }
    }

    /// Zero gradients for `s` with `pose_rows` rows of pose gradients, reusing these
    /// buffers.
    pub fn reset(&mut self, s: &TrainState, pose_rows: usize) {
        let n = s.n();
        self.poses.reset(pose_rows, n);
        for v in [&mut self.log_scale, &mut self.color] {
            v.clear();
            v.resize(n, [0.0; 3]);
        }
        self.logit_opacity.clear();
        self.logit_opacity.resize(n, 0.0);
        self.sh_rest.clear();
        self.sh_rest.resize(s.sh_rest.len(), 0.0);
    }
}

impl TrainState {
    /// Number of Gaussians N.
    pub fn n(&self) -> usize {
        self.ids.len()
    }

    /// Number of frames T.
    pub fn frames(&self) -> usize {
        self.poses.frames
    }

    /// Read every frame of `model`, keeping the Gaussians with `keep[i]` (all when `None`).
    pub fn from_model(model: &Model, keep: Option<&[bool]>) -> crate::tables::Result<Self> {
        let g = &model.gaussians;
        let rows: Vec<usize> = (0..g.len()).filter(|&i| keep.is_none_or(|k| k[i])).collect();
        let t_count = model.num_frames();
        let n = rows.len();
        let mut poses = Poses::with_capacity(t_count, n);
        for t in 0..t_count {
            let f = model.frame(t)?;
            poses.position.extend(rows.iter().map(|&i| f.position[i]));
            poses.rotation.extend(rows.iter().map(|&i| f.rotation[i]));
        }
        let k3 = g.sh_rest_len();
        Ok(TrainState {
            ids: rows.iter().map(|&i| g.id[i]).collect(),
            origin: rows.iter().map(|&i| g.id[i]).collect(),
            dynamic: rows.iter().map(|&i| g.dynamic[i]).collect(),
            poses,
            log_scale: rows.iter().map(|&i| g.scale[i].map(|s| s.max(SCALE_MIN).ln())).collect(),
            logit_opacity: rows.iter().map(|&i| logit(g.opacity[i])).collect(),
            color: rows.iter().map(|&i| g.color[i]).collect(),
            sh_degree: g.sh_degree,
            sh_rest: rows
                .iter()
                .flat_map(|&i| g.sh_rest[i * k3..(i + 1) * k3].iter().copied())
                .collect(),
        })
    }

    /// Linear scales `[N, 3]`.
    pub fn scales(&self) -> Vec<[f32; 3]> {
        self.log_scale.iter().map(|s| s.map(f32::exp)).collect()
    }

    /// Opacities `[N]` in (0, 1).
    pub fn opacities(&self) -> Vec<f32> {
        self.logit_opacity.iter().map(|&l| sigmoid(l)).collect()
    }

    /// Positions of frame `t` `[N, 3]`.
    pub fn positions(&self, t: usize) -> &[[f32; 3]] {
        &self.poses.position[t * self.n()..(t + 1) * self.n()]
    }

    /// Rotations of frame `t` `[N, 4]` (unnormalised).
    pub fn rotations(&self, t: usize) -> &[[f32; 4]] {
        &self.poses.rotation[t * self.n()..(t + 1) * self.n()]
    }

    /// The static attributes in table form (linear scale, opacity in [0, 1]).
    pub fn to_gaussians(&self) -> Gaussians {
        Gaussians {
            id: self.ids.clone(),
            dynamic: self.dynamic.clone(),
            scale: self.scales(),
            opacity: self.opacities(),
            color: self.color.clone(),
            sh_degree: self.sh_degree,
            sh_rest: self.sh_rest.clone(),
        }
    }

    /// Frame `t` in table form (normalised quaternions; a zero quaternion becomes identity).
    pub fn frame_state(&self, t: usize) -> FrameState {
        FrameState {
            frame: t as u32,
            position: self.positions(t).to_vec(),
            rotation: self.rotations(t).iter().map(|q| normalized(*q)).collect(),
        }
    }

    /// Tie static Gaussians: replace each static Gaussian's per-frame pose gradient by its
    /// sum over frames, so every frame's copy takes the same Adam step and stays equal.
    pub fn tie_static(&self, g: &mut PoseGrads) {
        let (n, nt) = (self.n(), self.frames());
        for i in (0..n).filter(|&i| !self.dynamic[i]) {
            let mut p = [0.0f32; 3];
            let mut q = [0.0f32; 4];
            for t in 0..nt {
                for k in 0..3 {
                    p[k] += g.position[t * n + i][k];
                }
                for k in 0..4 {
                    q[k] += g.rotation[t * n + i][k];
                }
            }
            for t in 0..nt {
                g.position[t * n + i] = p;
                g.rotation[t * n + i] = q;
            }
        }
    }

    /// Keep rows `rows` (indices into this state, repeats allowed), the Gaussian at
    /// position j taking id `ids[j]`: pruning and densification. The poses are rearranged
    /// in place ([`gather_frames`]).
    pub fn gather(&mut self, rows: &[usize], ids: Vec<u32>) {
        let (n, nt) = (self.n(), self.frames());
        let k3 = self.sh_rest.len() / n.max(1);
        let all = rows.len();
        gather_frames(&mut self.poses.position, nt, n, 1, rows, all);
        gather_frames(&mut self.poses.rotation, nt, n, 1, rows, all);
        self.poses.n = all;
        self.ids = ids;
        self.dynamic = rows.iter().map(|&i| self.dynamic[i]).collect();
        self.origin = rows.iter().map(|&i| self.origin[i]).collect();
        self.log_scale = rows.iter().map(|&i| self.log_scale[i]).collect();
        self.logit_opacity = rows.iter().map(|&i| self.logit_opacity[i]).collect();
        self.color = rows.iter().map(|&i| self.color[i]).collect();
        self.sh_rest =
            rows.iter().flat_map(|&i| self.sh_rest[i * k3..(i + 1) * k3].iter().copied()).collect();
    }
}

/// Replace the `[frames, n, stride]` tensor `v` by its rows `rows` (indices below n,
/// repeats allowed), `[frames, rows.len(), stride]`, rows at positions ≥ `first_new` being
/// zero (`T::default()`). In place, a frame at a time through one frame's copy, so that a
/// density pass at T = 475, N = 200,000 does not hold the whole state twice: a growing
/// tensor is moved from its last frame down (frame t's new place starts at or after its
/// old one), a shrinking one from its first frame up.
pub fn gather_frames<T: Copy + Default>(
    v: &mut Vec<T>,
    frames: usize,
    n: usize,
    stride: usize,
    rows: &[usize],
    first_new: usize,
) {
    let (old, new) = (n * stride, rows.len() * stride);
    assert_eq!(v.len(), frames * old, "gather_frames: tensor size");
    if new > old {
        v.reserve_exact(frames * (new - old));
        v.resize(frames * new, T::default());
    }
    let mut frame = Vec::with_capacity(old);
    let mut place = |v: &mut Vec<T>, t: usize| {
        frame.clear();
        frame.extend_from_slice(&v[t * old..(t + 1) * old]);
        let out = &mut v[t * new..(t + 1) * new];
        for (j, (dst, &i)) in out.chunks_exact_mut(stride.max(1)).zip(rows).enumerate() {
            if j < first_new {
                dst.copy_from_slice(&frame[i * stride..(i + 1) * stride]);
            } else {
                dst.fill(T::default());
            }
        }
    };
    if new > old {
        (0..frames).rev().for_each(|t| place(v, t));
    } else {
        (0..frames).for_each(|t| place(v, t));
        v.truncate(frames * new);
        v.shrink_to_fit();
    }
}

/// `q / |q|`, identity for a zero or non-finite quaternion.
pub fn normalized(q: [f32; 4]) -> [f32; 4] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    if n > 0.0 && n.is_finite() { q.map(|v| v / n) } else { [1.0, 0.0, 0.0, 0.0] }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> TrainState {
        TrainState {
            ids: vec![5, 7],
            dynamic: vec![true, false],
            origin: vec![5, 7],
            poses: Poses {
                frames: 2,
                n: 2,
                position: vec![[0.0; 3], [1.0; 3], [0.5; 3], [1.0; 3]],
                rotation: vec![[1.0, 0.0, 0.0, 0.0]; 4],
            },
            log_scale: vec![[0.1f32.ln(); 3]; 2],
            logit_opacity: vec![logit(0.3), logit(0.9)],
            color: vec![[0.2; 3], [0.4; 3]],
            sh_degree: 0,
            sh_rest: vec![],
        }
    }

    #[test]
    fn linear_tables_and_tied_statics() {
        let s = state();
        let g = s.to_gaussians();
        assert!((g.opacity[0] - 0.3).abs() < 1e-6 && (g.scale[1][2] - 0.1).abs() < 1e-7);
        let mut pg = PoseGrads {
            position: vec![[1.0; 3], [2.0; 3], [3.0; 3], [4.0; 3]],
            rotation: vec![[0.0; 4]; 4],
        };
        s.tie_static(&mut pg);
        assert_eq!(pg.position, vec![[1.0; 3], [6.0; 3], [3.0; 3], [6.0; 3]]);
        let mut d = s.clone();
        d.gather(&[1, 0, 0], vec![7, 5, 8]);
        assert_eq!(d.positions(1), &[[1.0; 3], [0.5; 3], [0.5; 3]]);
        assert_eq!(d.dynamic, vec![false, true, true]);
    }

    /// In-place gathering equals building the tensor anew, growing and shrinking, with
    /// repeats and zero rows.
    #[test]
    fn gather_frames_equals_a_fresh_gather() {
        let (frames, n, stride) = (5, 7, 3);
        let src: Vec<f32> = (0..frames * n * stride).map(|x| x as f32).collect();
        for (rows, first_new) in [
            (vec![0, 2, 3, 6, 6, 1, 4, 4, 5, 0], 8),
            (vec![6, 1, 3], 3),
            (vec![0, 1, 2, 3, 4, 5, 6], 7),
            (vec![2, 5, 5, 1], 2),
            (vec![], 0),
        ] {
            let mut fresh = Vec::new();
            for t in 0..frames {
                for (j, &i) in rows.iter().enumerate() {
                    let at = (t * n + i) * stride;
                    if j < first_new {
                        fresh.extend_from_slice(&src[at..at + stride]);
                    } else {
                        fresh.extend([0.0; 3]);
                    }
                }
            }
            let mut v = src.clone();
            gather_frames(&mut v, frames, n, stride, &rows, first_new);
            assert_eq!(v, fresh, "rows {rows:?}");
        }
    }
}
