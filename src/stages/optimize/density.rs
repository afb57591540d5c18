//! Density control (3DGS's adaptive density control as MoSca runs it; paper App. B,
//! official-release.md Sec. 5.3 and rows 59-60): Gaussians whose mean screen-space position
//! gradient (NDC units, over the views they were visible in since the last pass) exceeds a
//! threshold are cloned when small (max scale ≤ `percent-dense` × extent) or split in two
//! when large (children sampled from the parent's Gaussian, scales / 1.6); Gaussians whose
//! opacity fell below `prune-opacity` are removed; opacities are periodically reset to at
//! most 0.01. Key nodes (the `protected` mask) are never densified or pruned. New Gaussians
//! take fresh ids above every id in use, zero Adam moments, and their parent's per-frame
//! trajectory (a split child is offset rigidly in the parent's local frame), so they are
//! non-keys that inherit the parent's most reliable frame and edges ([`TrainState::origin`]).

use super::adam::Adam;
use super::params::DensitySettings;
use super::state::{TrainState, gather_frames, logit, sigmoid};
use crate::util::rng::{Rng, mix};

/// Split children's scale factor (3DGS).
const SPLIT_SHRINK: f32 = 1.6;
/// Opacity after a reset (upper bound).
const RESET_OPACITY: f32 = 0.01;

/// Screen-gradient accumulators since the last density pass, `[N]` each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DensityStats {
    /// Σ of per-view NDC gradient norms.
    pub grad: Vec<f32>,
    /// Number of views the Gaussian was visible in.
    pub count: Vec<u32>,
}

impl DensityStats {
    /// Zeros for N Gaussians.
    pub fn new(n: usize) -> Self {
        DensityStats { grad: vec![0.0; n], count: vec![0; n] }
    }

    /// Add one step's sums.
    pub fn add(&mut self, grad: &[f32], count: &[u32]) {
        for i in 0..self.grad.len() {
            self.grad[i] += grad[i];
            self.count[i] += count[i];
        }
    }
}

/// What one density pass did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DensityReport {
    /// Gaussians cloned.
    pub cloned: usize,
    /// Gaussians split (each replaced by two).
    pub split: usize,
    /// Gaussians pruned.
    pub pruned: usize,
}

/// Layout of Adam group `g` over the Gaussians: (frames, floats per Gaussian per frame),
/// for the groups [`super::run`] creates in this order: position, rotation, log-scale,
/// opacity, colour, SH rest.
pub fn group_layouts(state: &TrainState) -> [(usize, usize); 6] {
    let t = state.frames();
    let k3 = state.sh_rest.len() / state.n().max(1);
    [(t, 3), (t, 4), (1, 3), (1, 1), (1, 3), (1, k3)]
}

/// Densify and prune once (module doc). `protected` `[N]` marks key nodes; `extent` is the
/// scene extent in world units; `next_id` is the next unused `gaussian_id`.
pub fn densify_and_prune(
    state: &mut TrainState,
    adam: &mut Adam,
    stats: &DensityStats,
    protected: &[bool],
    s: &DensitySettings,
    extent: f32,
    seed: u64,
    step: u32,
    next_id: &mut u32,
) -> DensityReport {
    let n = state.n();
    let layouts = group_layouts(state);
    let opac = state.opacities();
    let mut keep = Vec::with_capacity(n);
    let (mut clones, mut splits) = (Vec::new(), Vec::new());
    let mut report = DensityReport::default();
    for i in 0..n {
        if protected[i] {
            keep.push(i);
            continue;
        }
        let avg = if stats.count[i] > 0 { stats.grad[i] / stats.count[i] as f32 } else { 0.0 };
        let max_scale = state.log_scale[i].iter().copied().fold(f32::MIN, f32::max).exp();
        let grow = avg >= s.densify_grad;
        if grow && max_scale > s.percent_dense * extent {
            splits.push(i);
            continue;
        }
        if grow {
            clones.push(i);
        }
        if opac[i] < s.prune_opacity {
            report.pruned += 1;
        } else {
            keep.push(i);
        }
    }
    report.cloned = clones.len();
    report.split = splits.len();
    let mut rows = keep.clone();
    rows.extend(&clones);
    for &i in &splits {
        rows.extend([i, i]);
    }
    let mut ids: Vec<u32> = keep.iter().map(|&i| state.ids[i]).collect();
    for _ in 0..clones.len() + 2 * splits.len() {
        ids.push(*next_id);
        *next_id += 1;
    }
    state.gather(&rows, ids);
    // Split children: sampled from the parent's Gaussian (ε ~ N(0, I) in its local frame,
    // the same for every frame so the child moves rigidly with the parent), shrunk.
    let mut rng = Rng::new(mix(seed ^ mix(step as u64 ^ 0x5eed_0000_0000)));
    let (n2, nt) = (state.n(), state.frames());
    let first_child = keep.len() + clones.len();
    for j in first_child..n2 {
        let s3 = state.log_scale[j].map(f32::exp);
        let e = [rng.normal() as f32, rng.normal() as f32, rng.normal() as f32];
        let local = [s3[0] * e[0], s3[1] * e[1], s3[2] * e[2]];
        for t in 0..nt {
            let q = super::state::normalized(state.poses.rotation[t * n2 + j]);
            let d = rotate(q, local);
            for k in 0..3 {
                state.poses.position[t * n2 + j][k] += d[k];
            }
        }
        for v in state.log_scale[j].iter_mut() {
            *v -= SPLIT_SHRINK.ln();
        }
    }
    // Adam moments follow their Gaussians; new ones start at zero.
    for (g, &(frames, stride)) in adam.groups.iter_mut().zip(&layouts) {
        gather_frames(&mut g.m, frames, n, stride, &rows, keep.len());
        gather_frames(&mut g.v, frames, n, stride, &rows, keep.len());
    }
    report
}

/// Reset opacities to at most 0.01 and clear the opacity group's moments (3DGS).
pub fn reset_opacity(state: &mut TrainState, adam: &mut Adam) {
    let cap = logit(RESET_OPACITY);
    for l in state.logit_opacity.iter_mut() {
        if sigmoid(*l) > RESET_OPACITY {
            *l = cap;
        }
    }
    let g = &mut adam.groups[3];
    g.m.fill(0.0);
    g.v.fill(0.0);
}

/// `q ⊗ v ⊗ q*` for a unit quaternion `w, x, y, z`.
fn rotate(q: [f32; 4], v: [f32; 3]) -> [f32; 3] {
    let [w, x, y, z] = q;
    let u = [x, y, z];
    let cross = |a: [f32; 3], b: [f32; 3]| {
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    };
    let t = cross(u, v).map(|c| 2.0 * c);
    let c = cross(u, t);
    [v[0] + w * t[0] + c[0], v[1] + w * t[1] + c[1], v[2] + w * t[2] + c[2]]
}

#[cfg(test)]
mod tests {
    use super::super::poses::Poses;
    use super::*;

    fn state(n: usize) -> TrainState {
        TrainState {
            ids: (0..n as u32).collect(),
            dynamic: vec![true; n],
            origin: (0..n as u32).collect(),
            poses: Poses {
                frames: 2,
                n,
                position: (0..2 * n).map(|k| [k as f32, 0.0, 0.0]).collect(),
                rotation: vec![[1.0, 0.0, 0.0, 0.0]; 2 * n],
            },
            log_scale: vec![[0.001f32.ln(); 3]; n],
            logit_opacity: vec![logit(0.5); n],
            color: vec![[0.5; 3]; n],
            sh_degree: 0,
            sh_rest: vec![],
        }
    }

    #[test]
    fn clone_split_prune_and_protect() {
        let mut s = state(4);
        s.log_scale[1] = [0.5f32.ln(); 3]; // large: split
        s.logit_opacity[2] = logit(0.001); // faint: pruned
        let layouts = group_layouts(&s);
        let groups: Vec<(String, usize)> = ["p", "q", "s", "o", "c", "sh"]
            .iter()
            .zip(layouts)
            .map(|(k, (f, st))| (k.to_string(), f * 4 * st))
            .collect();
        let spec: Vec<(&str, f32, usize)> =
            groups.iter().map(|(k, l)| (k.as_str(), 0.1, *l)).collect();
        let mut adam = Adam::new(&spec);
        adam.groups[0].m = (0..24).map(|k| k as f32).collect();
        let stats = DensityStats { grad: vec![1.0, 1.0, 0.0, 1.0], count: vec![1; 4] };
        let settings = DensitySettings {
            density_start: 0.0,
            density_end: 1.0,
            densify_every: 1,
            opacity_reset_every: None,
            densify_grad: 0.5,
            percent_dense: 0.01,
            prune_opacity: 0.01,
        };
        let mut next_id = 10;
        let protected = [false, false, false, true];
        let r = densify_and_prune(
            &mut s,
            &mut adam,
            &stats,
            &protected,
            &settings,
            1.0,
            0,
            1,
            &mut next_id,
        );
        assert_eq!(r, DensityReport { cloned: 1, split: 1, pruned: 1 });
        // kept 0 and 3 (protected, never cloned), clone of 0, two children of 1
        assert_eq!(s.ids, vec![0, 3, 10, 11, 12]);
        assert_eq!(s.origin, vec![0, 3, 0, 1, 1]);
        assert_eq!(next_id, 13);
        assert_eq!(s.positions(1)[2], [4.0, 0.0, 0.0], "a clone keeps its parent's trajectory");
        let child = s.positions(1)[3];
        let d = (child[0] - 5.0, s.positions(0)[3][0] - 1.0);
        assert!((d.0 - d.1).abs() < 1e-6 && d.0 != 0.0, "rigid offset {d:?}");
        assert!((s.log_scale[4][0].exp() - 0.5 / 1.6).abs() < 1e-6);
        // moments of kept rows follow them, new rows are zero: frame 1 of Gaussian 3 = 7·3..
        assert_eq!(&adam.groups[0].m[..6], &[0.0, 1.0, 2.0, 9.0, 10.0, 11.0]);
        assert_eq!(&adam.groups[0].m[6..15], &[0.0; 9]);
        assert_eq!(&adam.groups[0].m[15..21], &[12.0, 13.0, 14.0, 21.0, 22.0, 23.0]);
    }
}
