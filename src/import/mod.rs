//! Importers of base reconstructions: Shape of Motion checkpoints ([`som`]) and MoSca log
//! directories ([`mosca`]) into model directories.
//!
//! Each importer decodes its checkpoints ([`crate::formats::torch`]) into a [`BaseModel`]:
//! static attributes with the activations the method applies, and a function that evaluates
//! every Gaussian's pose at frame t exactly as the method does (in f64). [`write_model`] then
//! streams frames 0..T-1 into `trajectories.parquet` (memory O(N), not O(N·T)) and writes the
//! gaussians table, the model's own cameras and the scene-to-model similarity. With a scene
//! ([`align_to_scene`]), the frame count must match (an error otherwise) and the cameras are
//! compared after fitting the similarity; their differences are reported as warnings, since a
//! base model's solved or refined cameras differ from the dataset's by design.

pub mod mosca;
pub mod som;

use std::path::Path;

use rayon::prelude::*;

use crate::context::Context;
use crate::math::quat64::{self as q4, M3};
use crate::model::{FrameState, Gaussians, Model, SH_FRAME_KEY};
use crate::render::ShFrame;
use crate::scene::{Camera, Scene};
use crate::tables::Provenance;
use crate::tables::model_cameras::{ModelCamera, Similarity};

/// The poses of every Gaussian at one frame, canonical order, f64.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Poses {
    /// World positions `[N]`.
    pub position: Vec<[f64; 3]>,
    /// Unit rotations `w, x, y, z` `[N]`, in the method's own sign convention.
    pub rotation: Vec<[f64; 4]>,
}

/// A base reconstruction decoded from its checkpoints.
pub trait BaseModel: Sync {
    /// Number of frames T.
    fn num_frames(&self) -> usize;
    /// Static attributes (ids 0..N-1; dynamic Gaussians first).
    fn gaussians(&self) -> Gaussians;
    /// Poses of every Gaussian at frame `t`.
    fn poses(&self, t: usize) -> Poses;
    /// The model's camera of every frame; `size` is the scene's image `(width, height)` when
    /// known (intrinsics are given for that size).
    fn cameras(&self, size: Option<(u32, u32)>) -> Vec<ModelCamera>;
    /// Frame of the SH view direction.
    fn sh_frame(&self) -> ShFrame;
}

/// Write `model` into `out`: gaussians (with the SH frame in its metadata), trajectories
/// streamed frame by frame, the model's cameras and the similarity.
pub fn write_model(
    out: &Path,
    model: &dyn BaseModel,
    cameras: &[ModelCamera],
    sim: &Similarity,
    provenance: &Provenance,
    ctx: &Context,
) -> anyhow::Result<()> {
    let gaussians = model.gaussians();
    let sh = model.sh_frame().name();
    let t_count = model.num_frames();
    let bar = ctx.progress(t_count as u64, "frames");
    let frames = (0..t_count).map(|t| {
        let p = model.poses(t);
        bar.inc(1);
        Ok(FrameState {
            frame: t as u32,
            position: p.position.iter().map(|x| x.map(|v| v as f32)).collect(),
            rotation: p.rotation.iter().map(|q| q.map(|v| v as f32)).collect(),
        })
    });
    let g_prov = provenance.clone().with_metadata(SH_FRAME_KEY, sh);
    Model::save(out, &gaussians, frames, &g_prov)?;
    bar.finish_and_clear();
    Model::save_cameras(out, cameras, sim, provenance)?;
    Ok(())
}

/// The scene's training cameras checked against the model's: T must agree (an error
/// otherwise); returns the similarity fitted to the cameras and warns about differences.
pub fn align_to_scene(
    scene_dir: &Path,
    model: &dyn BaseModel,
    what: &str,
    ctx: &Context,
) -> anyhow::Result<(Vec<ModelCamera>, Similarity)> {
    let scene = Scene::load(scene_dir)?;
    let train = scene.train_by_frame();
    let t_model = model.num_frames();
    if train.len() != t_model {
        anyhow::bail!(
            "{what} has {t_model} frames but the scene {} has {} training frames",
            scene_dir.display(),
            train.len()
        );
    }
    let size = (train[0].pinhole.width, train[0].pinhole.height);
    if let Some(c) = train.iter().find(|c| (c.pinhole.width, c.pinhole.height) != size) {
        anyhow::bail!(
            "{}: training frame {} is {}x{}, frame 0 is {}x{}: one image size is expected",
            Scene::cameras_path(scene_dir).display(),
            c.frame,
            c.pinhole.width,
            c.pinhole.height,
            size.0,
            size.1
        );
    }
    let cams = model.cameras(Some(size));
    let (sim, report) = fit_similarity(&train, &cams);
    for line in report.lines() {
        ctx.warn(format!("{what} vs scene {}: {line}", scene_dir.display()));
    }
    Ok((cams, sim))
}

fn rot_of(w2c: &[f64; 16]) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| w2c[i * 4 + j]))
}

fn center_of(w2c: &[f64; 16]) -> [f64; 3] {
    let r = rot_of(w2c);
    std::array::from_fn(|j| -(0..3).map(|i| r[i][j] * w2c[i * 4 + 3]).sum::<f64>())
}

/// Fit `x_model = s·R·x_scene + t` to paired training cameras: R is the sign-aligned
/// quaternion mean of `R_model_cwᵀ·R_scene_cw`, then s and t by least squares on the camera
/// centres (s = 1 when the scene's camera does not move). Returns the similarity and a report
/// of the residual differences (empty when they are negligible).
pub fn fit_similarity(scene: &[&Camera], model: &[ModelCamera]) -> (Similarity, String) {
    let n = scene.len().min(model.len());
    let mut qsum = [0.0; 4];
    let mut first: Option<[f64; 4]> = None;
    for i in 0..n {
        let r = q4::matmul(transpose(rot_of(&model[i].pinhole.w2c)), rot_of(&scene[i].pinhole.w2c));
        let mut q = q4::from_rotmat(&r);
        let f = *first.get_or_insert(q);
        if (0..4).map(|k| q[k] * f[k]).sum::<f64>() < 0.0 {
            q = q.map(|x| -x);
        }
        (0..4).for_each(|k| qsum[k] += q[k]);
    }
    let rot = q4::quat_to_mat(q4::normalize4(if n == 0 { [1.0, 0.0, 0.0, 0.0] } else { qsum }));
    let a: Vec<[f64; 3]> =
        (0..n).map(|i| q4::mat_vec(&rot, center_of(&scene[i].pinhole.w2c))).collect();
    let b: Vec<[f64; 3]> = (0..n).map(|i| center_of(&model[i].pinhole.w2c)).collect();
    let mean = |v: &[[f64; 3]]| -> [f64; 3] {
        std::array::from_fn(|k| v.iter().map(|x| x[k]).sum::<f64>() / v.len().max(1) as f64)
    };
    let (ma, mb) = (mean(&a), mean(&b));
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..n {
        for k in 0..3 {
            num += (a[i][k] - ma[k]) * (b[i][k] - mb[k]);
            den += (a[i][k] - ma[k]).powi(2);
        }
    }
    let spread = (den / n.max(1) as f64).sqrt();
    let mut report = Vec::new();
    let scale = if spread > 1e-9 && num > 0.0 {
        num / den
    } else {
        report.push("the scene's training camera does not move: scale set to 1".to_string());
        1.0
    };
    let translation = std::array::from_fn(|k| mb[k] - scale * ma[k]);
    let sim = Similarity {
        scale,
        rotation: rot,
        translation,
        source: "fit to the scene's training cameras".into(),
    };
    // Residuals: rotation angle, centre distance relative to the model's camera path, focal.
    let (mut max_deg, mut max_centre, mut max_focal) = (0.0f64, 0.0f64, 0.0f64);
    let path = (b.iter().map(|x| (0..3).map(|k| (x[k] - mb[k]).powi(2)).sum::<f64>()).sum::<f64>()
        / n.max(1) as f64)
        .sqrt()
        .max(1e-12);
    for i in 0..n {
        let mapped = sim.w2c_to_model(&scene[i].pinhole.w2c);
        let r = q4::matmul(transpose(rot_of(&mapped)), rot_of(&model[i].pinhole.w2c));
        let cos = ((r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0).clamp(-1.0, 1.0);
        max_deg = max_deg.max(cos.acos().to_degrees());
        let c = center_of(&mapped);
        let d = (0..3).map(|k| (c[k] - b[i][k]).powi(2)).sum::<f64>().sqrt();
        max_centre = max_centre.max(d / path);
        let sx = scene[i].pinhole.width as f64 / model[i].pinhole.width as f64;
        max_focal = max_focal.max((model[i].pinhole.fx * sx / scene[i].pinhole.fx - 1.0).abs());
    }
    if max_deg > 0.5 {
        report.push(format!("camera orientations differ by up to {max_deg:.2}° after alignment"));
    }
    if max_centre > 0.05 {
        report.push(format!(
            "camera centres differ by up to {:.1}% of the camera path after alignment",
            100.0 * max_centre
        ));
    }
    if max_focal > 0.02 {
        report.push(format!("focal lengths differ by up to {:.1}%", 100.0 * max_focal));
    }
    (sim, report.join("\n"))
}

fn transpose(m: M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
}

/// Evaluate `f` for every index in parallel, in order.
pub(crate) fn par_map<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync + Send) -> Vec<T> {
    (0..n).into_par_iter().map(f).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Pinhole, Split};

    fn cam(frame: u32, w2c: [f64; 16]) -> Camera {
        Camera::new(frame, "0", Split::Train, Pinhole::centred(50.0, 64, 48, w2c))
    }

    #[test]
    fn similarity_is_recovered_from_cameras() {
        let truth = Similarity {
            scale: 0.4,
            rotation: q4::quat_to_mat(q4::normalize4([0.9, 0.1, -0.3, 0.2])),
            translation: [1.0, -2.0, 0.5],
            source: String::new(),
        };
        let scene: Vec<Camera> = (0..5)
            .map(|t| {
                let r = q4::quat_to_mat(q4::normalize4([1.0, 0.05 * t as f64, 0.1, 0.0]));
                let mut w = [0.0; 16];
                for i in 0..3 {
                    for j in 0..3 {
                        w[i * 4 + j] = r[i][j];
                    }
                    w[i * 4 + 3] = [0.3 * t as f64, -0.1, 2.0 + 0.2 * t as f64][i];
                }
                w[15] = 1.0;
                cam(t, w)
            })
            .collect();
        let model: Vec<ModelCamera> = scene.iter().map(|c| truth.camera_to_model(c)).collect();
        let refs: Vec<&Camera> = scene.iter().collect();
        let (sim, report) = fit_similarity(&refs, &model);
        assert!(report.is_empty(), "{report}");
        assert!((sim.scale - truth.scale).abs() < 1e-9, "{sim:?}");
        for i in 0..3 {
            assert!((sim.translation[i] - truth.translation[i]).abs() < 1e-9, "{sim:?}");
            for j in 0..3 {
                assert!((sim.rotation[i][j] - truth.rotation[i][j]).abs() < 1e-9);
            }
        }
    }
}
