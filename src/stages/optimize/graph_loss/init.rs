//! Graph initialisation before fine-tuning. The paper (App. B) "sequentially initialize[s]
//! the key and non-key graphs"; the release does it in its prep (official-release.md §5.1,
//! §11 rows 37-38), in this order:
//!
//! 1. Non-keys: fit each non-key's DQB source pose so that DQB (Eq. 10) of its keys' prior
//!    motions reproduces its prior trajectory: the DQB terms of Eq. 11 on seeded batches of
//!    frames, the poses fixed.
//! 2. Keys: fit the key trajectories and the learned key-edge tensors to the key anchor
//!    (Eq. 9) and the key edge terms (a seeded share of the edges per iteration), both with
//!    weight 1 in every profile, and the acceleration over the keys.
//! 3. Every linked non-key's trajectory becomes the DQB of the fitted keys, at every frame
//!    (the release's "final non-key trajectories").
//!
//! Each fit is Adam with PyTorch's `ReduceLROnPlateau(factor 0.5, patience 10, threshold
//! 1e-3, min_lr 1e-6)`, stopped once the rate falls below 2e-6 or at the iteration cap.

use rayon::prelude::*;

use super::super::adam::Adam;
use super::super::motion;
use super::super::poses::{PoseGrads, Poses};
use super::super::smoothness;
use super::super::train::batch_frames;
use super::{GraphObjective, Reduction};
use crate::math::dqb;
use crate::math::quat64 as q4;
use crate::util::rng::mix;

/// Settings of the graph initialisation (rows 37-38; where the paper gives no value the
/// paper profile takes the release's).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub struct GraphInit {
    /// Iteration cap of each fit; 0 turns the initialisation off.
    pub max_iters: u32,
    /// Adam's starting learning rate (release 0.1).
    pub lr: f32,
    /// Share of the key edges kept per key iteration (release 0.7).
    pub edge_keep_ratio: f64,
    /// Frames per non-key iteration (release 30).
    pub batch_frames: usize,
    /// Weight of the keys' acceleration term (release 0.1).
    pub acceleration: f64,
}

/// What the initialisation did: iterations and final loss of each fit.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct InitReport {
    /// Iterations of the non-key fit.
    pub nonkey_iters: u32,
    /// Its last loss.
    pub nonkey_loss: f64,
    /// Iterations of the key fit.
    pub key_iters: u32,
    /// Its last loss.
    pub key_loss: f64,
}

/// PyTorch's `ReduceLROnPlateau` in `min` mode with a relative threshold.
struct Plateau {
    lr: f32,
    best: f64,
    bad: u32,
}

impl Plateau {
    const FACTOR: f32 = 0.5;
    const PATIENCE: u32 = 10;
    const THRESHOLD: f64 = 1e-3;
    const MIN_LR: f32 = 1e-6;
    const STOP_LR: f32 = 2e-6;

    fn new(lr: f32) -> Self {
        Plateau { lr, best: f64::INFINITY, bad: 0 }
    }

    /// Record a loss; true once the rate has fallen below the stopping rate.
    fn observe(&mut self, loss: f64) -> bool {
        if loss < self.best * (1.0 - Self::THRESHOLD) {
            self.best = loss;
            self.bad = 0;
        } else {
            self.bad += 1;
            if self.bad > Self::PATIENCE {
                self.lr = (self.lr * Self::FACTOR).max(Self::MIN_LR);
                self.bad = 0;
            }
        }
        self.lr < Self::STOP_LR
    }
}

impl GraphObjective {
    /// Run the three steps of the module docs on `poses` (the model's poses before
    /// fine-tuning); `progress` is told the iteration count of each fit as it goes.
    pub fn initialise(
        &mut self,
        poses: &mut Poses,
        init: &GraphInit,
        seed: u64,
        progress: &dyn Fn(&str, u32),
    ) -> InitReport {
        let mut report = InitReport::default();
        if init.max_iters == 0 || self.keys.is_empty() {
            return report;
        }
        (report.nonkey_iters, report.nonkey_loss) = self.fit_sources(poses, init, seed, progress);
        (report.key_iters, report.key_loss) = self.fit_keys(poses, init, seed, progress);
        self.propagate(poses);
        report
    }

    /// Step 1: Adam on the source poses against the DQB terms, poses fixed.
    fn fit_sources(
        &mut self,
        poses: &Poses,
        init: &GraphInit,
        seed: u64,
        progress: &dyn Fn(&str, u32),
    ) -> (u32, f64) {
        let s = self.s.clone();
        if self.nonkeys.is_empty() || (s.dqb == 0.0 && s.dqb_rotation == 0.0) {
            return (0, 0.0);
        }
        let mut adam = Adam::new(&[
            ("src_p", init.lr, self.src_p.len()),
            ("src_q", init.lr, self.src_q.len()),
        ]);
        let mut plateau = Plateau::new(init.lr);
        // The pose gradients of the DQB terms are not used here.
        let mut unused = PoseGrads::zeros(self.frames, self.n);
        let batch = init.batch_frames.clamp(1, self.frames);
        let (mut iters, mut loss) = (0, 0.0);
        while iters < init.max_iters {
            let frames = batch_frames(mix(seed ^ 0x6e6f_6e6b), iters, self.frames, batch);
            self.g_src_p.fill(0.0);
            self.g_src_q.fill(0.0);
            let [p, q] = self.dqb_terms(poses, &frames, &mut unused);
            loss = s.dqb * p + s.dqb_rotation * q;
            adam.begin_step();
            adam.update(0, &mut self.src_p, &self.g_src_p);
            adam.update(1, &mut self.src_q, &self.g_src_q);
            iters += 1;
            progress("graph init: non-keys", iters);
            if plateau.observe(loss) {
                break;
            }
            adam.groups.iter_mut().for_each(|g| g.lr = plateau.lr);
        }
        (iters, loss)
    }

    /// Step 2: Adam on the key trajectories, W and (release form) D.
    fn fit_keys(
        &mut self,
        poses: &mut Poses,
        init: &GraphInit,
        seed: u64,
        progress: &dyn Fn(&str, u32),
    ) -> (u32, f64) {
        let n = self.n;
        let keys = self.keys.clone();
        let rows: Vec<usize> =
            (0..self.frames).flat_map(|t| keys.iter().map(move |&k| t * n + k as usize)).collect();
        let mut kp: Vec<f32> = rows.iter().flat_map(|&o| poses.position[o]).collect();
        let mut kq: Vec<f32> = rows.iter().flat_map(|&o| poses.rotation[o]).collect();
        let mut groups = vec![
            ("position", init.lr, kp.len()),
            ("rotation", init.lr, kq.len()),
            ("weight", init.lr, self.w_raw.len()),
        ];
        let learn_rest = self.s.motion == motion::MotionForm::Release;
        if learn_rest {
            groups.push(("rest", init.lr, self.rest.len()));
        }
        let mut adam = Adam::new(&groups);
        let mut plateau = Plateau::new(init.lr);
        let mut grads = PoseGrads::zeros(self.frames, n);
        let (mut gp, mut gq) = (vec![0.0f32; kp.len()], vec![0.0f32; kq.len()]);
        let form = self.s.motion;
        let nacc = match (form, self.s.reduction) {
            (motion::MotionForm::Paper, Reduction::Sum) => 1.0,
            _ => smoothness::smoothness_means(self.frames, keys.len()).1,
        };
        // The prep weighs the key edge terms 1 (release: `L_rigid_extra` unscaled; paper:
        // L^motion,key of Eq. 9), not fine-tuning's λ_graph·λ_key.
        let keep = std::mem::replace(&mut self.s.edge_keep_ratio, init.edge_keep_ratio);
        let weight = std::mem::replace(&mut self.s.key_motion, 1.0);
        let (mut iters, mut loss) = (0, 0.0);
        while iters < init.max_iters {
            self.g_w_raw.fill(0.0);
            self.g_rest.fill(0.0);
            let [anchor, _] = self.anchors(poses, [1.0, 0.0], &mut grads);
            let edges: f64 = self
                .key_motion(poses, mix(seed ^ 0x6b65_7973 ^ iters as u64), &mut grads)
                .iter()
                .map(|(_, v)| v)
                .sum();
            let accel = (nacc, init.acceleration);
            let [_, acc] =
                smoothness::smoothness(poses, &keys, form, (nacc, 0.0), accel, &mut grads);
            loss = anchor + edges + init.acceleration * acc;
            for (k, &o) in rows.iter().enumerate() {
                gp[3 * k..3 * k + 3].copy_from_slice(&grads.position[o]);
                gq[4 * k..4 * k + 4].copy_from_slice(&grads.rotation[o]);
                grads.position[o] = [0.0; 3];
                grads.rotation[o] = [0.0; 4];
            }
            adam.begin_step();
            adam.update(0, &mut kp, &gp);
            adam.update(1, &mut kq, &gq);
            adam.update(2, &mut self.w_raw, &self.g_w_raw);
            if learn_rest {
                adam.update(3, &mut self.rest, &self.g_rest);
            }
            for (k, &o) in rows.iter().enumerate() {
                poses.position[o].copy_from_slice(&kp[3 * k..3 * k + 3]);
                poses.rotation[o].copy_from_slice(&kq[4 * k..4 * k + 4]);
            }
            iters += 1;
            progress("graph init: keys", iters);
            if plateau.observe(loss) {
                break;
            }
            adam.groups.iter_mut().for_each(|g| g.lr = plateau.lr);
        }
        self.s.edge_keep_ratio = keep;
        self.s.key_motion = weight;
        self.g_w_raw.fill(0.0);
        self.g_rest.fill(0.0);
        (iters, loss)
    }

    /// Step 3: each linked non-key's pose at every frame becomes the DQB of its keys'
    /// current motions from t̂ applied to its source pose (Eq. 10), with the blend weights
    /// and pose offsets of the DQB term.
    fn propagate(&mut self, poses: &mut Poses) {
        self.blend_weights_of(&poses.position);
        let (n, nk) = (self.n, self.keys.len());
        let dq_key: Vec<dqb::Dq> = (0..self.frames * nk)
            .into_par_iter()
            .map(|x| {
                let o = (x / nk) * n + self.keys[x % nk] as usize;
                dqb::from_pose(q4::q64(poses.rotation[o]), q4::v64(poses.position[o])).0
            })
            .collect();
        let this = &*self;
        let (position, rotation) = (&mut poses.position, &mut poses.rotation);
        position.par_chunks_mut(n).zip(rotation.par_chunks_mut(n)).enumerate().for_each(
            |(t, (pos, rot))| {
                for (u, &node) in this.nonkeys.iter().enumerate() {
                    let (a, b) = (this.nk_off[u], this.nk_off[u + 1]);
                    if a == b {
                        continue;
                    }
                    let th = this.t_hat[u] as usize;
                    let mut blend = [0.0; 8];
                    for e in a..b {
                        let k = this.nk_key[e] as usize;
                        let r = dqb::relative(&dq_key[t * nk + k], &dq_key[th * nk + k]).0;
                        for c in 0..8 {
                            blend[c] += this.nk_w_eff[e] * r[c];
                        }
                    }
                    let sp = [0, 1, 2].map(|c| this.src_p[3 * u + c] as f64);
                    let sq = [0, 1, 2, 3].map(|c| this.src_q[4 * u + c] as f64);
                    let out = dqb::Warp::new(&blend, sp, sq).out;
                    let off = this.offsets.get(7 * u..7 * u + 7).unwrap_or(&[0.0; 7]);
                    pos[node as usize] = [0, 1, 2].map(|c| (out.p[c] + off[c] as f64) as f32);
                    rot[node as usize] =
                        [0, 1, 2, 3].map(|c| (out.q[c] + off[3 + c] as f64) as f32);
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use glam::DMat3;

    use super::super::{Anchors, GraphInputs, GraphSettings};
    use super::*;
    use crate::stages::params::Profile;

    /// One rigid body turning about z and translating: 3 keys and 4 non-keys (wxyz
    /// rotations), T = 9; non-key 4 is displaced at frame 6.
    fn rigid_case(s: GraphSettings) -> (GraphObjective, Poses, Poses) {
        let (t, n) = (9, 7);
        let local: [[f64; 3]; 7] = [
            [0.0, 0.0, 0.0],
            [1.0, 0.2, 0.1],
            [0.1, 1.1, -0.3],
            [0.5, 0.5, 0.2],
            [0.3, 0.8, 0.0],
            [0.9, 0.6, -0.1],
            [0.2, 0.1, 0.4],
        ];
        let mut truth = Poses::identity(t, n);
        for f in 0..t {
            let a = 0.15 * f as f64;
            let q = [(a / 2.0).cos(), 0.0, 0.0, (a / 2.0).sin()];
            let c = [0.1 * f as f64, -0.05 * f as f64, 0.02 * f as f64];
            for (i, x) in local.iter().enumerate() {
                let r = q4::rotate(q, *x);
                truth.position[f * n + i] = [0, 1, 2].map(|k| (r[k] + c[k]) as f32);
                truth.rotation[f * n + i] = q.map(|v| v as f32);
            }
        }
        let mut prior = truth.clone();
        prior.position[6 * n + 4][0] += 0.5;
        let keys = [0u32, 1, 2];
        let key_edges: Vec<(u32, u32, f32)> = keys
            .iter()
            .flat_map(|&a| keys.iter().filter(move |&&b| b != a).map(move |&b| (a, b, 1.0)))
            .collect();
        let nonkey_edges: Vec<Vec<(u32, f32)>> = vec![vec![(0, 0.5), (1, 0.3), (2, 0.2)]; 4];
        let u = vec![0.1f32; t * n];
        let rot = vec![DMat3::IDENTITY; t];
        let ids: Vec<u32> = (0..n as u32).collect();
        let (nonkeys, t_hat) = ([3, 4, 5, 6], [0, 2, 8, 4]);
        let inp = GraphInputs {
            anchors: Anchors::of_poses(&prior, u, &nonkeys, &t_hat),
            ids: &ids,
            keys: &keys,
            nonkeys: &nonkeys,
            t_hat: &t_hat,
            nonkey_edges: &nonkey_edges,
            key_edges: &key_edges,
            rot_cw: &rot,
            nonkey_lambda: 1.0,
        };
        (GraphObjective::new(inp, s).unwrap(), prior, truth)
    }

    fn max_error(a: &Poses, b: &Poses) -> f64 {
        let p = a.position.iter().flatten().zip(b.position.iter().flatten());
        let q = a.rotation.iter().flatten().zip(b.rotation.iter().flatten());
        p.chain(q).map(|(x, y)| (x - y).abs() as f64).fold(0.0, f64::max)
    }

    /// The prior is the rigid motion except non-key 4 at frame 6, 0.5 off; the fits start at
    /// the optimum, where Adam's first steps (about `lr` each) push them off before the
    /// plateau schedule shrinks the rate: with lr 1e-3 they stay within 0.03.
    #[test]
    fn a_displaced_nonkey_returns_to_its_keys_rigid_motion() {
        let release = GraphSettings::defaults(Profile::Release);
        let init = GraphInit { acceleration: 0.0, lr: 1e-3, ..release.init };
        let (mut obj, mut poses, truth) = rigid_case(release.clone());
        assert!(max_error(&poses, &truth) >= 0.5);
        let iters = std::cell::Cell::new(0);
        let r = obj.initialise(&mut poses, &init, 3, &|_, k| iters.set(k));
        assert!(r.nonkey_iters > 0 && r.key_iters > 0 && iters.get() > 0, "{r:?}");
        let err = max_error(&poses, &truth);
        assert!(err < 0.03, "largest deviation from the rigid motion {err}; {r:?}");
        // Off: nothing changes.
        let (mut obj, mut poses, _) = rigid_case(release);
        let before = poses.clone();
        let off = GraphInit { max_iters: 0, ..init };
        assert_eq!(obj.initialise(&mut poses, &off, 3, &|_, _| {}), InitReport::default());
        assert_eq!(poses, before);
    }

    #[test]
    fn the_initialisation_does_not_depend_on_the_thread_count() {
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (mut obj, mut poses, _) = rigid_case(GraphSettings::defaults(Profile::Paper));
                let init =
                    GraphInit { max_iters: 500, ..GraphSettings::defaults(Profile::Release).init };
                obj.initialise(&mut poses, &init, 5, &|_, _| {});
                (poses, obj.src_p.clone(), obj.w_raw.clone())
            })
        };
        assert!(run(1) == run(3));
    }

    #[test]
    fn plateau_halves_after_patience_and_stops_below_the_floor() {
        let mut p = Plateau::new(0.1);
        assert!(!p.observe(1.0));
        // 10 non-improving losses keep the rate; the 11th halves it.
        for _ in 0..10 {
            assert!(!p.observe(0.9995));
        }
        assert_eq!(p.lr, 0.1);
        p.observe(0.9995);
        assert_eq!(p.lr, 0.05);
        // An improvement beyond 0.1 % resets the count.
        p.observe(0.5);
        assert_eq!((p.best, p.bad), (0.5, 0));
        let mut steps = 0;
        while !p.observe(0.5) {
            steps += 1;
        }
        // 0.05 · 0.5^15 ≈ 1.5e-6 < 2e-6: 15 halvings of 11 iterations each.
        assert_eq!(steps + 1, 15 * 11);
    }
}
