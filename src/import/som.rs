//! `usplat4d import som`: a Shape of Motion checkpoint (`last.ckpt` or the initial one) into
//! a model directory (formats-and-protocols.md §1.1-1.2).
//!
//! Foreground Gaussian g at frame t (`flow3d/scene_model.py::compute_poses_fg`):
//! `w = softmax(motion_coefs_g)`, `R = cont_6d_to_rmat(Σ_k w_k rots[k,t])`,
//! `tr = Σ_k w_k transls[k,t]`, `μ_t = R μ_g + tr`, `q_t = normalize(quat(R) ⊗ normalize(q_g))`
//! with roma's Markley `quat(R)` (its sign convention is reproduced, so quaternions equal
//! SoM's exactly). The background is static (`dynamic = false`, normalised quats). Scales
//! are `exp`, opacities and colours `sigmoid` (plain RGB, SH degree 0, world SH frame).
//! Cameras are `Ks` and `w2cs` (already scene-normalised by SoM). Everything is computed in
//! f64 from the stored values.

use std::path::PathBuf;

use crate::context::Context;
use crate::formats::torch::{Checkpoint, Dim, Dims, Error as CkptError};
use crate::math::{quat64 as q4, rot6d};
use crate::model::Gaussians;
use crate::render::ShFrame;
use crate::tables::Provenance;
use crate::tables::cameras::Pinhole;
use crate::tables::model_cameras::{ModelCamera, Similarity};

use super::{BaseModel, Poses, par_map};

/// Parameters of `usplat4d import som`.
#[derive(Debug, Clone, clap::Args, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct ImportSomParams {
    /// SoM checkpoint: `<work_dir>/checkpoints/last.ckpt` (or the initial checkpoint).
    #[arg(long, value_name = "FILE")]
    pub ckpt: PathBuf,
    /// Model directory to write.
    #[arg(long, value_name = "MODEL_DIR")]
    pub out: PathBuf,
    /// Scene the model was trained on: checks the frame count, takes the image size from
    /// it and fits the scene-to-model similarity to its training cameras.
    #[arg(long, value_name = "SCENE_DIR")]
    #[serde(default)]
    pub scene: Option<PathBuf>,
}

/// Gaussian parameters of one SoM `GaussianParams` (fg or bg), activated, f64.
#[derive(Debug, Clone, Default)]
pub struct Params {
    /// Canonical means `[N, 3]`.
    pub means: Vec<[f64; 3]>,
    /// `F.normalize(quats)`, `w, x, y, z` `[N]`.
    pub quats: Vec<[f64; 4]>,
    /// `exp(scales)` `[N, 3]`.
    pub scales: Vec<[f64; 3]>,
    /// `sigmoid(colors)` `[N, 3]`.
    pub colors: Vec<[f64; 3]>,
    /// `sigmoid(opacities)` `[N]`.
    pub opacities: Vec<f64>,
}

/// A decoded SoM scene model.
#[derive(Debug, Clone)]
pub struct Som {
    /// Foreground Gaussians (G).
    pub fg: Params,
    /// `softmax(motion_coefs)` `[G, K]`, row-major.
    pub coefs: Vec<f64>,
    /// Background Gaussians (B, possibly 0).
    pub bg: Params,
    /// Number of motion bases K.
    pub k: usize,
    /// Number of frames T.
    pub t: usize,
    /// Raw 6D rotations of the bases `[K, T, 6]`.
    pub rots: Vec<f64>,
    /// Translations of the bases `[K, T, 3]`.
    pub transls: Vec<f64>,
    /// Pixel intrinsics `[T, 3, 3]`.
    pub ks: Vec<f64>,
    /// World-to-camera `[T, 4, 4]`.
    pub w2cs: Vec<f64>,
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

fn rows<const W: usize>(v: &[f64]) -> Vec<[f64; W]> {
    v.chunks_exact(W).map(|c| std::array::from_fn(|i| c[i])).collect()
}

/// Reject non-finite values, naming the key and the row.
fn finite(ck: &Checkpoint, key: &[&str], v: &[f64], width: usize) -> Result<(), CkptError> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(i) => Err(CkptError::Key {
            path: ck.path.clone(),
            key: key.join("/"),
            msg: format!("row {} holds a non-finite value ({})", i / width.max(1), v[i]),
        }),
    }
}

fn params(
    ck: &Checkpoint,
    prefix: &str,
    n: &'static str,
    dims: &mut Dims,
) -> Result<Params, CkptError> {
    let key = |name: &str| format!("{prefix}.params.{name}");
    let mut read = |name: &str, shape: &[Dim]| -> Result<Vec<f64>, CkptError> {
        let k = key(name);
        let v = ck.floats(&["model", &k], shape, dims)?;
        finite(
            ck,
            &["model", &k],
            &v,
            shape.iter().skip(1).map(|d| if let Dim::Is(w) = d { *w } else { 1 }).product(),
        )?;
        Ok(v)
    };
    let means = read("means", &[Dim::Named(n), Dim::Is(3)])?;
    let quats = read("quats", &[Dim::Named(n), Dim::Is(4)])?;
    let scales = read("scales", &[Dim::Named(n), Dim::Is(3)])?;
    let colors = read("colors", &[Dim::Named(n), Dim::Is(3)])?;
    let opacities = read("opacities", &[Dim::Named(n)])?;
    Ok(Params {
        means: rows(&means),
        quats: rows::<4>(&quats).into_iter().map(q4::normalize4).collect(),
        scales: rows::<3>(&scales).into_iter().map(|s| s.map(f64::exp)).collect(),
        colors: rows::<3>(&colors).into_iter().map(|c| c.map(sigmoid)).collect(),
        opacities: opacities.into_iter().map(sigmoid).collect(),
    })
}

impl Som {
    /// Decode `ckpt["model"]` (keys and shapes of formats-and-protocols.md §1.1).
    pub fn from_checkpoint(ck: &Checkpoint) -> Result<Som, CkptError> {
        let mut dims = Dims::default();
        let fg = params(ck, "fg", "G", &mut dims)?;
        let logits = ck.floats(
            &["model", "fg.params.motion_coefs"],
            &[Dim::Named("G"), Dim::Named("K")],
            &mut dims,
        )?;
        let k = dims.get("K").unwrap_or(0);
        finite(ck, &["model", "fg.params.motion_coefs"], &logits, k)?;
        let rots = ck.floats(
            &["model", "motion_bases.params.rots"],
            &[Dim::Named("K"), Dim::Named("T"), Dim::Is(6)],
            &mut dims,
        )?;
        finite(ck, &["model", "motion_bases.params.rots"], &rots, 6)?;
        let transls = ck.floats(
            &["model", "motion_bases.params.transls"],
            &[Dim::Named("K"), Dim::Named("T"), Dim::Is(3)],
            &mut dims,
        )?;
        finite(ck, &["model", "motion_bases.params.transls"], &transls, 3)?;
        let t = dims.get("T").unwrap_or(0);
        let has_bg = ck.get(&["model"])?.keys().iter().any(|k| k.contains("bg."));
        let bg = if has_bg { params(ck, "bg", "B", &mut dims)? } else { Params::default() };
        let ks =
            ck.floats(&["model", "Ks"], &[Dim::Named("T"), Dim::Is(3), Dim::Is(3)], &mut dims)?;
        finite(ck, &["model", "Ks"], &ks, 9)?;
        let w2cs =
            ck.floats(&["model", "w2cs"], &[Dim::Named("T"), Dim::Is(4), Dim::Is(4)], &mut dims)?;
        finite(ck, &["model", "w2cs"], &w2cs, 16)?;
        if let Some(i) = (0..t).find(|i| ks[i * 9] <= 0.0 || ks[i * 9 + 4] <= 0.0) {
            return Err(CkptError::Key {
                path: ck.path.clone(),
                key: "model/Ks".into(),
                msg: format!(
                    "frame {i}: focal lengths must be positive, got {} {}",
                    ks[i * 9],
                    ks[i * 9 + 4]
                ),
            });
        }
        let coefs = logits
            .chunks_exact(k.max(1))
            .flat_map(|row| {
                let m = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let e: Vec<f64> = row.iter().map(|x| (x - m).exp()).collect();
                let s: f64 = e.iter().sum();
                e.into_iter().map(move |x| x / s)
            })
            .collect();
        Ok(Som { fg, coefs, bg, k, t, rots, transls, ks, w2cs })
    }

    /// `[R | t]` of foreground Gaussian `g` at frame `t` (`compute_transforms`).
    pub fn transform(&self, g: usize, t: usize) -> (q4::M3, [f64; 3]) {
        let mut r6 = [0.0; 6];
        let mut tr = [0.0; 3];
        for k in 0..self.k {
            let w = self.coefs[g * self.k + k];
            let base = k * self.t + t;
            (0..6).for_each(|i| r6[i] += w * self.rots[base * 6 + i]);
            (0..3).for_each(|i| tr[i] += w * self.transls[base * 3 + i]);
        }
        (rot6d::to_rotmat(r6), tr)
    }

    /// Foreground means and quaternions at frame `t` (`compute_poses_fg`).
    pub fn fg_poses(&self, t: usize) -> Poses {
        let per: Vec<([f64; 3], [f64; 4])> = par_map(self.fg.means.len(), |g| {
            let (r, tr) = self.transform(g, t);
            let m = q4::mat_vec(&r, self.fg.means[g]);
            let mu = [m[0] + tr[0], m[1] + tr[1], m[2] + tr[2]];
            let q = q4::normalize4(q4::mul(q4::mat_to_quat_roma(r), self.fg.quats[g]));
            (mu, q)
        });
        Poses {
            position: per.iter().map(|p| p.0).collect(),
            rotation: per.iter().map(|p| p.1).collect(),
        }
    }
}

impl BaseModel for Som {
    fn num_frames(&self) -> usize {
        self.t
    }

    fn gaussians(&self) -> Gaussians {
        let (g, b) = (self.fg.means.len(), self.bg.means.len());
        let f32x3 = |v: &[f64; 3]| v.map(|x| x as f32);
        let both = |f: fn(&Params) -> &Vec<[f64; 3]>| -> Vec<[f32; 3]> {
            f(&self.fg).iter().chain(f(&self.bg)).map(f32x3).collect()
        };
        Gaussians {
            id: (0..(g + b) as u32).collect(),
            dynamic: (0..g + b).map(|i| i < g).collect(),
            scale: both(|p| &p.scales),
            opacity: self
                .fg
                .opacities
                .iter()
                .chain(&self.bg.opacities)
                .map(|o| *o as f32)
                .collect(),
            color: both(|p| &p.colors),
            sh_degree: 0,
            sh_rest: Vec::new(),
        }
    }

    fn poses(&self, t: usize) -> Poses {
        let mut p = self.fg_poses(t);
        p.position.extend(&self.bg.means);
        p.rotation.extend(&self.bg.quats);
        p
    }

    fn cameras(&self, size: Option<(u32, u32)>) -> Vec<ModelCamera> {
        (0..self.t)
            .map(|t| {
                let k = &self.ks[t * 9..t * 9 + 9];
                // SoM does not store the image size; without a scene it is taken as twice
                // the principal point.
                let (width, height) = size.unwrap_or((
                    (2.0 * k[2]).round().max(1.0) as u32,
                    (2.0 * k[5]).round().max(1.0) as u32,
                ));
                let mut w2c = [0.0; 16];
                w2c.copy_from_slice(&self.w2cs[t * 16..t * 16 + 16]);
                ModelCamera {
                    frame: t as u32,
                    pinhole: Pinhole { fx: k[0], fy: k[4], cx: k[2], cy: k[5], width, height, w2c },
                }
            })
            .collect()
    }

    fn sh_frame(&self) -> ShFrame {
        ShFrame::World
    }
}

/// Run `usplat4d import som`.
pub fn run(p: &ImportSomParams, ctx: &Context) -> anyhow::Result<()> {
    let ck = Checkpoint::open(&p.ckpt)?;
    let som = Som::from_checkpoint(&ck)?;
    let what = p.ckpt.display().to_string();
    let (cams, sim) = match &p.scene {
        Some(scene) => super::align_to_scene(scene, &som, &what, ctx)?,
        None => {
            ctx.info(
                "no --scene: image size taken as twice the principal point, similarity = identity",
            );
            (som.cameras(None), Similarity::identity("identity: no scene given"))
        }
    };
    super::write_model(&p.out, &som, &cams, &sim, &Provenance::new("import som", p), ctx)?;
    ctx.info(format!(
        "imported {} foreground and {} background Gaussians, {} frames, into {}",
        som.fg.means.len(),
        som.bg.means.len(),
        som.t,
        p.out.display()
    ));
    Ok(())
}
