//! `usplat4d import mosca`: a MoSca log directory into a model directory
//! (formats-and-protocols.md §2).
//!
//! Reads `photometric_d_model_<backend>.pth` (`DynSCFGaussian` with its scaffold under
//! `scf.`), `photometric_s_model_<backend>.pth` (`StaticGaussian`) and `photometric_cam.pth`
//! (`MonocularCameras`). Each dynamic leaf n is evaluated as `DynSCFGaussian.forward(t)` →
//! `MoSca.warp` does (§2.4): its reference pose from node `attach_ind` at `ref_time` (leaf-local
//! storage), skinning weights `w_k = (exp(−‖μ−x_k‖²/2σ_k²) + 1e-6)·mask_k`, corrected to
//! `|w_k + _skinning_weight|` after `set_surface_deform` (rescaled to the old sum when
//! `w_corr_maintain_sum_flag`), `dyn_o = clamp(Σw, 0, 1)` (or `1 − DQ_EPS`), then dual-quaternion
//! blending of the nodes' relative motions ref→t with pytorch3d's w ≥ 0 quaternions and no
//! antipodal fix (or LBS when `blending_method = 1`). Rotations are returned as pytorch3d
//! quaternions (w ≥ 0), so they equal MoSca's exactly. Scales are
//! `min + sigmoid·(max − min)`, opacities `sigmoid`, SH kept raw (degree-0 colour `0.5 + C0·dc`)
//! and evaluated in the Gaussian's local frame (`ShFrame::Local`). The static model follows
//! with `dynamic = false`. Cameras: `T_cw = T_wc⁻¹` and `K(H, W)` at the scene's image size
//! (MoSca's `default_H × default_W` without a scene). All in f64 from the stored values.
//!
//! The DQB forward is `math::dqb` (`lib_mosca/scaffold_utils/dualquat_helper.py`), the one
//! the optimiser differentiates.

use std::path::{Path, PathBuf};

use crate::context::Context;
use crate::formats::torch::{Checkpoint, Dim, Dims, Error as CkptError};
use crate::math::dqb;
use crate::math::quat64::{self as q4, M3};
use crate::model::Gaussians;
use crate::render::ShFrame;
use crate::tables::Provenance;
use crate::tables::cameras::Pinhole;
use crate::tables::model_cameras::{ModelCamera, Similarity};

use super::{BaseModel, Poses, par_map};
use crate::render::sh::C0;

/// `lib_mosca/mosca.py::DQ_EPS`.
pub const DQ_EPS: f64 = 0.001;

/// Parameters of `usplat4d import mosca`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImportMoscaParams {
    /// MoSca log directory (`<ws>/logs/<exp>_<backend>_<date>/`) holding
    /// `photometric_{d,s}_model_<backend>.pth` and `photometric_cam.pth`.
    #[arg(long, value_name = "LOG_DIR")]
    pub dir: PathBuf,
    /// Model directory to write.
    #[arg(long, value_name = "MODEL_DIR")]
    pub out: PathBuf,
    /// Scene the model was trained on: checks the frame count, sets the image size of the
    /// intrinsics and fits the scene-to-model similarity to its training cameras.
    #[arg(long, value_name = "SCENE_DIR")]
    #[serde(default)]
    pub scene: Option<PathBuf>,
    /// Gaussian backend suffix of the model files (MoSca's `GS_BACKEND`); default: the only
    /// one present.
    #[arg(long, value_name = "NAME")]
    #[serde(default)]
    pub backend: Option<String>,
}

/// Static attributes of one MoSca Gaussian set, activated, f64.
#[derive(Debug, Clone, Default)]
pub struct Attributes {
    /// `min + sigmoid(_scaling)·(max − min)` `[N, 3]`.
    pub scales: Vec<[f64; 3]>,
    /// `sigmoid(_opacity)` `[N]`.
    pub opacities: Vec<f64>,
    /// SH degree of the set (`max_sph_order`).
    pub sh_degree: usize,
    /// Raw `cat(_features_dc, _features_rest)` `[N, (d+1)², 3]` flattened.
    pub sph: Vec<f64>,
}

/// One dynamic leaf, prepared once: reference pose and skinning.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leaf {
    /// Reference frame r.
    pub ref_time: usize,
    /// World position at r, `[3]`.
    pub xyz_ref: [f64; 3],
    /// World rotation at r.
    pub r_ref: M3,
    /// Skinning nodes (`topo_knn_ind[attach_ind]`) `[K]`, up to 32.
    pub sk_ind: [usize; 32],
    /// Normalised skinning weights `[K]`.
    pub sk_w: [f64; 32],
    /// Sum of the (corrected) unnormalised weights.
    pub sk_w_sum: f64,
    /// Blend factor toward the identity motion.
    pub dyn_o: f64,
}

/// A decoded MoSca reconstruction.
#[derive(Debug, Clone)]
pub struct Mosca {
    /// Frames T.
    pub t: usize,
    /// Nodes M.
    pub m: usize,
    /// Skinning neighbours K.
    pub k: usize,
    /// `scf._node_xyz` `[T, M, 3]`.
    pub node_xyz: Vec<[f64; 3]>,
    /// `q2R(scf._node_rotation)` `[T, M]`.
    pub node_r: Vec<M3>,
    /// `max_sigma·sigmoid(_node_sigma_logit)` `[M]`.
    pub node_sigma: Vec<f64>,
    /// 0 = DQB, 1 = LBS.
    pub blending: i64,
    /// Dynamic leaves `[N]`.
    pub leaves: Vec<Leaf>,
    /// Dynamic attributes.
    pub dynamic: Attributes,
    /// Static positions `[B, 3]`.
    pub st_xyz: Vec<[f64; 3]>,
    /// Static rotations, normalised `w, x, y, z` `[B]`.
    pub st_quat: Vec<[f64; 4]>,
    /// Static attributes.
    pub st: Attributes,
    /// Camera-to-world of each frame (MoSca's `T_wc_list`, rounded to f32 as it returns).
    pub t_wc: Vec<[f64; 16]>,
    /// `_rel_focal` (both entries equal `_rel_focal[0]` with `iso_focal`).
    pub rel_focal: [f64; 2],
    /// `cxcy_ratio`.
    pub cxcy_ratio: [f64; 2],
    /// `(default_W, default_H)`.
    pub default_size: (u32, u32),
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn q2r(q: [f64; 4]) -> M3 {
    q4::quat_to_mat(q4::normalize4(q))
}

fn rows<const W: usize>(v: &[f64]) -> Vec<[f64; W]> {
    v.chunks_exact(W).map(|c| std::array::from_fn(|i| c[i])).collect()
}

fn key_err(ck: &Checkpoint, key: &str, msg: String) -> CkptError {
    CkptError::Key { path: ck.path.clone(), key: key.into(), msg }
}

fn finite(ck: &Checkpoint, key: &str, v: &[f64], width: usize) -> Result<(), CkptError> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(i) => Err(key_err(
            ck,
            key,
            format!("row {} holds a non-finite value ({})", i / width.max(1), v[i]),
        )),
    }
}

/// Floats of `key` with `shape`, checked finite.
fn floats(
    ck: &Checkpoint,
    key: &str,
    shape: &[Dim],
    dims: &mut Dims,
) -> Result<Vec<f64>, CkptError> {
    let v = ck.floats(&[key], shape, dims)?;
    let width =
        shape.iter().skip(1).map(|d| if let Dim::Is(w) = d { *w } else { 1 }).product::<usize>();
    finite(ck, key, &v, width.max(1))?;
    Ok(v)
}

fn flag(ck: &Checkpoint, key: &str) -> Result<bool, CkptError> {
    Ok(ck.scalar(&[key])? != 0.0)
}

/// Scales, opacities and SH of a Gaussian set with `n` its count's name.
fn attributes(ck: &Checkpoint, n: &'static str, dims: &mut Dims) -> Result<Attributes, CkptError> {
    let max_s = ck.scalar(&["max_scale"])?;
    let min_s = ck.scalar(&["min_scale"])?;
    let deg = ck.scalar(&["max_sph_order"])?;
    if !(0.0..=3.0).contains(&deg) || deg.fract() != 0.0 {
        return Err(key_err(ck, "max_sph_order", format!("SH degree {deg} (0..=3 supported)")));
    }
    let deg = deg as usize;
    let scaling = floats(ck, "_scaling", &[Dim::Named(n), Dim::Is(3)], dims)?;
    let opacity = floats(ck, "_opacity", &[Dim::Named(n), Dim::Is(1)], dims)?;
    let dc = floats(ck, "_features_dc", &[Dim::Named(n), Dim::Is(3)], dims)?;
    let rest_w = 3 * ((deg + 1).pow(2) - 1);
    let rest = floats(ck, "_features_rest", &[Dim::Named(n), Dim::Is(rest_w)], dims)?;
    let count = opacity.len();
    let mut sph = Vec::with_capacity(count * (3 + rest_w));
    for i in 0..count {
        sph.extend_from_slice(&dc[i * 3..i * 3 + 3]);
        sph.extend_from_slice(&rest[i * rest_w..(i + 1) * rest_w]);
    }
    Ok(Attributes {
        scales: rows::<3>(&scaling)
            .into_iter()
            .map(|s| s.map(|x| min_s + sigmoid(x) * (max_s - min_s)))
            .collect(),
        opacities: opacity.into_iter().map(sigmoid).collect(),
        sh_degree: deg,
        sph,
    })
}

/// The files of a MoSca log directory: (dynamic model, static model, cameras).
pub fn log_files(dir: &Path, backend: Option<&str>) -> anyhow::Result<(PathBuf, PathBuf, PathBuf)> {
    let backend = match backend {
        Some(b) => b.to_string(),
        None => {
            let rd =
                std::fs::read_dir(dir).map_err(|e| anyhow::anyhow!("{}: {e}", dir.display()))?;
            let mut found: Vec<String> = rd
                .filter_map(|e| e.ok())
                .filter_map(|e| {
                    let name = e.file_name().to_string_lossy().into_owned();
                    name.strip_prefix("photometric_d_model_")?
                        .strip_suffix(".pth")
                        .map(str::to_string)
                })
                .collect();
            found.sort();
            match found.len() {
                1 => found.remove(0),
                0 => anyhow::bail!(
                    "{}: no photometric_d_model_<backend>.pth (is it a MoSca log directory? \
                     the files are written at the end of the photometric phase)",
                    dir.display()
                ),
                _ => anyhow::bail!(
                    "{}: several backends ({}): choose one with --backend",
                    dir.display(),
                    found.join(", ")
                ),
            }
        }
    };
    let files = (
        dir.join(format!("photometric_d_model_{backend}.pth")),
        dir.join(format!("photometric_s_model_{backend}.pth")),
        dir.join("photometric_cam.pth"),
    );
    for f in [&files.0, &files.1, &files.2] {
        if !f.is_file() {
            anyhow::bail!("{}: missing (expected in a MoSca log directory)", f.display());
        }
    }
    Ok(files)
}

impl Mosca {
    /// Decode the three checkpoints.
    pub fn from_checkpoints(
        d: &Checkpoint,
        s: &Checkpoint,
        cam: &Checkpoint,
    ) -> Result<Mosca, CkptError> {
        let mut dims = Dims::default();
        // Scaffold.
        let node_xyz =
            floats(d, "scf._node_xyz", &[Dim::Named("T"), Dim::Named("M"), Dim::Is(3)], &mut dims)?;
        let node_rot = floats(
            d,
            "scf._node_rotation",
            &[Dim::Named("T"), Dim::Named("M"), Dim::Is(4)],
            &mut dims,
        )?;
        let logit = floats(d, "scf._node_sigma_logit", &[Dim::Named("M"), Dim::Is(1)], &mut dims)?;
        let knn = d.ints(&["scf.topo_knn_ind"], &[Dim::Named("M"), Dim::Named("K")], &mut dims)?;
        let mask =
            d.bools(&["scf.topo_knn_mask"], &[Dim::Named("M"), Dim::Named("K")], &mut dims)?;
        let (t, m, k) =
            (dims.get("T").unwrap_or(0), dims.get("M").unwrap_or(0), dims.get("K").unwrap_or(0));
        if k > 32 {
            return Err(key_err(
                d,
                "scf.topo_knn_ind",
                format!("{k} skinning neighbours (at most 32 supported)"),
            ));
        }
        if let Some(i) = knn.iter().position(|x| *x < 0 || *x as usize >= m) {
            return Err(key_err(
                d,
                "scf.topo_knn_ind",
                format!("row {}: node {} is not in 0..{m}", i / k.max(1), knn[i]),
            ));
        }
        let max_sigma = d.scalar(&["scf.max_sigma"])?;
        let blending = match d.find(&["scf.blending_method"]) {
            Some(_) => d.ints(&["scf.blending_method"], &[Dim::Is(1)], &mut dims)?[0],
            None => 0,
        };
        if blending != 0 && blending != 1 {
            return Err(key_err(
                d,
                "scf.blending_method",
                format!("{blending} (0 = DQB, 1 = LBS)"),
            ));
        }
        let maintain_sum =
            d.has(&["scf.w_corr_maintain_sum_flag"]) && flag(d, "scf.w_corr_maintain_sum_flag")?;
        let nn_fusion = if d.has(&["nn_fusion"]) { d.scalar(&["nn_fusion"])? } else { -1.0 };
        if nn_fusion > 0.0 {
            return Err(key_err(
                d,
                "nn_fusion",
                format!(
                    "{nn_fusion}: per-frame opacity masking is not representable in a model directory"
                ),
            ));
        }
        let node_xyz = rows::<3>(&node_xyz);
        let node_r: Vec<M3> = rows::<4>(&node_rot).into_iter().map(q2r).collect();
        let node_sigma: Vec<f64> = logit.iter().map(|l| max_sigma * sigmoid(*l)).collect();
        // Leaves.
        let xyz = floats(d, "_xyz", &[Dim::Named("N"), Dim::Is(3)], &mut dims)?;
        let rot = floats(d, "_rotation", &[Dim::Named("N"), Dim::Is(4)], &mut dims)?;
        let corr = floats(d, "_skinning_weight", &[Dim::Named("N"), Dim::Named("K")], &mut dims)?;
        let attach = d.ints(&["attach_ind"], &[Dim::Named("N")], &mut dims)?;
        let ref_time = d.ints(&["ref_time"], &[Dim::Named("N")], &mut dims)?;
        if let Some(i) = attach.iter().position(|a| *a < 0 || *a as usize >= m) {
            return Err(key_err(
                d,
                "attach_ind",
                format!("row {i}: node {} is not in 0..{m}", attach[i]),
            ));
        }
        if let Some(i) = ref_time.iter().position(|r| *r < 0 || *r as usize >= t) {
            return Err(key_err(
                d,
                "ref_time",
                format!("row {i}: frame {} is not in 0..{t}", ref_time[i]),
            ));
        }
        let local = flag(d, "leaf_local_flag")?;
        let w_corr = flag(d, "w_correction_flag")?;
        let dyn_o_flag = flag(d, "dyn_o_flag")?;
        let leaves = (0..attach.len())
            .map(|n| {
                let (a, r) = (attach[n] as usize, ref_time[n] as usize);
                let x = [xyz[n * 3], xyz[n * 3 + 1], xyz[n * 3 + 2]];
                let rl = q2r([rot[n * 4], rot[n * 4 + 1], rot[n * 4 + 2], rot[n * 4 + 3]]);
                let (xyz_ref, r_ref) = if local {
                    let rn = node_r[r * m + a];
                    let p = q4::mat_vec(&rn, x);
                    let o = node_xyz[r * m + a];
                    ([p[0] + o[0], p[1] + o[1], p[2] + o[2]], q4::matmul(rn, rl))
                } else {
                    (x, rl)
                };
                let mut sk_ind = [0usize; 32];
                let mut w = [0.0; 32];
                for j in 0..k {
                    let node = knn[a * k + j] as usize;
                    sk_ind[j] = node;
                    let p = node_xyz[r * m + node];
                    let d2: f64 = (0..3).map(|i| (xyz_ref[i] - p[i]).powi(2)).sum();
                    let s = node_sigma[node];
                    let on = if mask[a * k + j] { 1.0 } else { 0.0 };
                    w[j] = ((-d2 / (2.0 * s * s)).exp() + 1e-6) * on;
                }
                if w_corr {
                    let old: f64 = w[..k].iter().map(|x| x.abs()).sum();
                    (0..k).for_each(|j| w[j] = (w[j] + corr[n * k + j]).abs());
                    if maintain_sum {
                        let new = w[..k].iter().map(|x| x.abs()).sum::<f64>().max(1e-6);
                        (0..k).for_each(|j| w[j] *= old / new);
                    }
                }
                let sum: f64 = w[..k].iter().sum();
                let mut sk_w = [0.0; 32];
                (0..k).for_each(|j| sk_w[j] = w[j] / sum.max(1e-6));
                let dyn_o = if dyn_o_flag { sum.clamp(0.0, 1.0) } else { 1.0 - DQ_EPS };
                Leaf { ref_time: r, xyz_ref, r_ref, sk_ind, sk_w, sk_w_sum: sum, dyn_o }
            })
            .collect();
        let dynamic = attributes(d, "N", &mut dims)?;
        // Static model.
        let mut sdims = Dims::default();
        let st_xyz = rows::<3>(&floats(s, "_xyz", &[Dim::Named("B"), Dim::Is(3)], &mut sdims)?);
        let st_rot = floats(s, "_rotation", &[Dim::Named("B"), Dim::Is(4)], &mut sdims)?;
        if let Some(i) = rows::<4>(&st_rot).iter().position(|q| q.iter().all(|x| *x == 0.0)) {
            return Err(key_err(s, "_rotation", format!("row {i} is a zero quaternion")));
        }
        let st_quat = rows::<4>(&st_rot).into_iter().map(q4::normalize4).collect();
        let st = attributes(s, "B", &mut sdims)?;
        // Cameras.
        let mut cdims = Dims::default();
        cdims.bind("T", t, "scf._node_xyz");
        let q_wc = floats(cam, "q_wc", &[Dim::Named("T"), Dim::Is(4)], &mut cdims).map_err(
            |e| match e {
                CkptError::Key { path, key, msg } => CkptError::Key {
                    path,
                    key,
                    msg: format!("{msg} (the dynamic model's scaffold has T = {t})"),
                },
                e => e,
            },
        )?;
        let t_wc = floats(cam, "t_wc", &[Dim::Named("T"), Dim::Is(3)], &mut cdims)?;
        let rel = floats(cam, "_rel_focal", &[Dim::Is(2)], &mut cdims)?;
        let cxcy = floats(cam, "cxcy_ratio", &[Dim::Is(2)], &mut cdims)?;
        let iso = flag(cam, "iso_focal")?;
        let delta = flag(cam, "delta_flag")?;
        let (h, w) = (cam.scalar(&["default_H"])?, cam.scalar(&["default_W"])?);
        if !(h >= 1.0 && w >= 1.0) {
            return Err(key_err(cam, "default_H", format!("image size {w}x{h} is empty")));
        }
        let rel_focal = if iso { [rel[0], rel[0]] } else { [rel[0], rel[1]] };
        if rel_focal.iter().any(|f| *f <= 0.0) {
            return Err(key_err(
                cam,
                "_rel_focal",
                format!("focal lengths must be positive, got {rel_focal:?}"),
            ));
        }
        let mut t_wc_list = Vec::with_capacity(t);
        let mut prev: Option<[f64; 16]> = None;
        for i in 0..t {
            let r = q2r([q_wc[i * 4], q_wc[i * 4 + 1], q_wc[i * 4 + 2], q_wc[i * 4 + 3]]);
            let mut m4 = [0.0; 16];
            for a in 0..3 {
                for b in 0..3 {
                    m4[a * 4 + b] = r[a][b];
                }
                m4[a * 4 + 3] = t_wc[i * 3 + a];
            }
            m4[15] = 1.0;
            let cur = match (delta, prev) {
                (true, Some(p)) => mul4(&p, &m4),
                _ => m4,
            };
            prev = Some(cur);
            t_wc_list.push(cur);
        }
        // MoSca returns T_wc as float32.
        let t_wc = t_wc_list.into_iter().map(|m4| m4.map(|x| x as f32 as f64)).collect();
        Ok(Mosca {
            t,
            m,
            k,
            node_xyz,
            node_r,
            node_sigma,
            blending,
            leaves,
            dynamic,
            st_xyz,
            st_quat,
            st,
            t_wc,
            rel_focal,
            cxcy_ratio: [cxcy[0], cxcy[1]],
            default_size: (w as u32, h as u32),
        })
    }

    /// Position and rotation matrix of leaf `n` at frame `t` (`MoSca.warp`).
    pub fn warp(&self, n: usize, t: usize) -> ([f64; 3], M3) {
        let leaf = &self.leaves[n];
        let r = leaf.ref_time;
        let o = leaf.dyn_o;
        let (rot, tr) = if self.blending == 0 {
            let mut dq = [0.0; 8];
            for j in 0..self.k {
                let node = leaf.sk_ind[j];
                let (rj, tj) = self.relative(node, r, t);
                let d = dqb::from_rt(q4::from_rotmat(&rj), tj);
                (0..8).for_each(|i| dq[i] += leaf.sk_w[j] * d[i]);
            }
            let unit = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
            let dq: [f64; 8] = std::array::from_fn(|i| dq[i] * o + unit[i] * (1.0 - o));
            dqb::to_rt(&dqb::unit(&dq))
        } else {
            let (mut q, mut tt) = ([0.0; 4], [0.0; 3]);
            for j in 0..self.k {
                let (rj, tj) = self.relative(leaf.sk_ind[j], r, t);
                let qj = q4::from_rotmat(&rj);
                (0..4).for_each(|i| q[i] += leaf.sk_w[j] * qj[i]);
                (0..3).for_each(|i| tt[i] += leaf.sk_w[j] * tj[i]);
            }
            let q = std::array::from_fn(|i| q[i] * o + (1.0 - o) * f64::from(u8::from(i == 0)));
            (q2r(q), tt.map(|x| x * o))
        };
        let p = q4::mat_vec(&rot, leaf.xyz_ref);
        ([p[0] + tr[0], p[1] + tr[1], p[2] + tr[2]], q4::matmul(rot, leaf.r_ref))
    }

    /// Motion of node `node` from frame `i` to frame `j`: `R_ji = R_wj·R_wiᵀ`, `t_ji = t_wj − R_ji·t_wi`.
    fn relative(&self, node: usize, i: usize, j: usize) -> (M3, [f64; 3]) {
        let (ri, ti) = (self.node_r[i * self.m + node], self.node_xyz[i * self.m + node]);
        let (rj, tj) = (self.node_r[j * self.m + node], self.node_xyz[j * self.m + node]);
        let r = q4::matmul_bt(rj, ri);
        let p = q4::mat_vec(&r, ti);
        (r, [tj[0] - p[0], tj[1] - p[1], tj[2] - p[2]])
    }

    /// Dynamic means and rotation matrices at frame `t` (`DynSCFGaussian.forward(t)`).
    pub fn dynamic_at(&self, t: usize) -> Vec<([f64; 3], M3)> {
        par_map(self.leaves.len(), |n| self.warp(n, t))
    }

    /// MoSca's `K(H, W)` as `(fx, fy, cx, cy)`.
    pub fn intrinsics(&self, width: u32, height: u32) -> [f64; 4] {
        let l = width.min(height) as f64;
        [
            self.rel_focal[0] * l / 2.0,
            self.rel_focal[1] * l / 2.0,
            width as f64 * self.cxcy_ratio[0],
            height as f64 * self.cxcy_ratio[1],
        ]
    }
}

/// `a · b` of row-major 4x4 matrices.
fn mul4(a: &[f64; 16], b: &[f64; 16]) -> [f64; 16] {
    std::array::from_fn(|x| (0..4).map(|k| a[(x / 4) * 4 + k] * b[k * 4 + x % 4]).sum())
}

/// Inverse of a rigid row-major 4x4 `[R | t]`: `[Rᵀ | −Rᵀt]`.
fn rigid_inverse(m: &[f64; 16]) -> [f64; 16] {
    let mut out = [0.0; 16];
    for i in 0..3 {
        for j in 0..3 {
            out[i * 4 + j] = m[j * 4 + i];
        }
        out[i * 4 + 3] = -(0..3).map(|k| m[k * 4 + i] * m[k * 4 + 3]).sum::<f64>();
    }
    out[15] = 1.0;
    out
}

/// The SH-degree-`deg` colour columns of a set: degree-0 RGB and the rest, padded with
/// zeros up to degree `to`.
fn sh_columns(a: &Attributes, to: usize) -> (Vec<[f32; 3]>, Vec<f32>) {
    let per = 3 * (a.sh_degree + 1).pow(2);
    let rest_to = 3 * ((to + 1).pow(2) - 1);
    let mut color = Vec::with_capacity(a.opacities.len());
    let mut rest = Vec::with_capacity(a.opacities.len() * rest_to);
    for s in a.sph.chunks_exact(per) {
        color.push(std::array::from_fn(|c| (0.5 + C0 * s[c]) as f32));
        rest.extend(s[3..].iter().map(|x| *x as f32));
        rest.extend(std::iter::repeat_n(0.0f32, rest_to - (per - 3)));
    }
    (color, rest)
}

impl BaseModel for Mosca {
    fn num_frames(&self) -> usize {
        self.t
    }

    fn gaussians(&self) -> Gaussians {
        let (n, b) = (self.leaves.len(), self.st_xyz.len());
        let deg = self.dynamic.sh_degree.max(self.st.sh_degree);
        let (mut color, mut sh_rest) = sh_columns(&self.dynamic, deg);
        let (sc, sr) = sh_columns(&self.st, deg);
        color.extend(sc);
        sh_rest.extend(sr);
        let f32x3 = |v: &[f64; 3]| v.map(|x| x as f32);
        Gaussians {
            id: (0..(n + b) as u32).collect(),
            dynamic: (0..n + b).map(|i| i < n).collect(),
            scale: self.dynamic.scales.iter().chain(&self.st.scales).map(f32x3).collect(),
            opacity: self
                .dynamic
                .opacities
                .iter()
                .chain(&self.st.opacities)
                .map(|o| *o as f32)
                .collect(),
            color,
            sh_degree: deg as u8,
            sh_rest,
        }
    }

    fn poses(&self, t: usize) -> Poses {
        let dynamic = self.dynamic_at(t);
        let mut position: Vec<[f64; 3]> = dynamic.iter().map(|d| d.0).collect();
        let mut rotation: Vec<[f64; 4]> = dynamic.iter().map(|d| q4::from_rotmat(&d.1)).collect();
        position.extend(&self.st_xyz);
        rotation.extend(&self.st_quat);
        Poses { position, rotation }
    }

    fn cameras(&self, size: Option<(u32, u32)>) -> Vec<ModelCamera> {
        let (width, height) = size.unwrap_or(self.default_size);
        let [fx, fy, cx, cy] = self.intrinsics(width, height);
        self.t_wc
            .iter()
            .enumerate()
            .map(|(t, m)| ModelCamera {
                frame: t as u32,
                pinhole: Pinhole { fx, fy, cx, cy, width, height, w2c: rigid_inverse(m) },
            })
            .collect()
    }

    fn sh_frame(&self) -> ShFrame {
        ShFrame::Local
    }
}

/// Run `usplat4d import mosca`.
pub fn run(p: &ImportMoscaParams, ctx: &Context) -> anyhow::Result<()> {
    let (d, s, c) = log_files(&p.dir, p.backend.as_deref())?;
    let mosca = Mosca::from_checkpoints(
        &Checkpoint::open(&d)?,
        &Checkpoint::open(&s)?,
        &Checkpoint::open(&c)?,
    )?;
    let what = p.dir.display().to_string();
    let (cams, sim) = match &p.scene {
        Some(scene) => super::align_to_scene(scene, &mosca, &what, ctx)?,
        None => (mosca.cameras(None), Similarity::identity("identity: no scene given")),
    };
    super::write_model(&p.out, &mosca, &cams, &sim, &Provenance::new("import mosca", p), ctx)?;
    ctx.info(format!(
        "imported {} dynamic and {} static Gaussians ({} nodes), {} frames, into {}",
        mosca.leaves.len(),
        mosca.st_xyz.len(),
        mosca.m,
        mosca.t,
        p.out.display()
    ));
    Ok(())
}
