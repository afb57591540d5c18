//! The 4D Gaussian model: static attributes per Gaussian plus a position and rotation per
//! Gaussian per frame, stored in a model directory.
//!
//! Layout of `MODEL_DIR`: `gaussians.parquet` (N rows, canonical order) and
//! `trajectories.parquet` (T row groups of N rows). Static Gaussians repeat their pose in
//! every frame. Frames are read one at a time ([`Model::frame`]) so that memory stays
//! O(N), not O(N·T).
//!
//! An imported base model also carries its own training cameras (`model_cameras.parquet`)
//! and the similarity from the scene's world frame to its own (`scene_to_model.json`);
//! [`Model::training_camera`] is the camera a stage renders training frame t with. The frame
//! the SH view direction is taken in ([`ShFrame`]: world for 3DGS and SoM, the Gaussian's
//! local frame for MoSca) is a model property stored in the gaussians table's metadata under
//! [`SH_FRAME_KEY`] (absent: world).

use std::path::{Path, PathBuf};

use crate::render::{ColorSource, ShFrame, SplatInputs};
use crate::scene::{Camera, Pinhole};
pub use crate::tables::gaussians::Gaussians;
use crate::tables::model_cameras::{self, ModelCamera, ModelCamerasTable, Similarity};
pub use crate::tables::trajectories::FrameState;
use crate::tables::trajectories::{TrajectoriesTable, TrajectoryReader, TrajectoryWriter};
use crate::tables::{self, Provenance, Table, gaussians::GaussiansTable};

/// File name of the scene-to-model similarity inside a model directory.
pub const SIMILARITY_FILE: &str = "scene_to_model.json";

/// A model directory opened for frame-by-frame reading.
pub struct Model {
    /// The model directory.
    pub dir: PathBuf,
    /// Static attributes.
    pub gaussians: Gaussians,
    /// The frame SH colours are evaluated in.
    pub sh_frame: ShFrame,
    /// The base model's own camera of each training frame, if it carries them.
    pub cameras: Option<Vec<ModelCamera>>,
    /// The similarity from the scene's world frame to the model's, if known.
    pub scene_to_model: Option<Similarity>,
    trajectories: TrajectoryReader,
}

/// Key of the gaussians table's metadata that holds the model's [`ShFrame`] (`world` or
/// `local`): a model with local-frame SH is saved with
/// `Model::save(dir, &g, frames, &provenance.with_metadata(SH_FRAME_KEY, "local"))`.
pub const SH_FRAME_KEY: &str = "usplat4d.sh_frame";

/// The colour source of Gaussians `g` with SH evaluated in `frame` (plain RGB at degree 0).
pub fn colors(g: &Gaussians, frame: ShFrame) -> ColorSource<'_> {
    if g.sh_degree == 0 {
        ColorSource::Rgb(&g.color)
    } else {
        ColorSource::Sh { degree: g.sh_degree, dc: &g.color, rest: &g.sh_rest, frame }
    }
}

impl Model {
    /// Path of the gaussians table in a model directory.
    pub fn gaussians_path(dir: &Path) -> PathBuf {
        dir.join(GaussiansTable::file_name())
    }

    /// Path of the trajectories table in a model directory.
    pub fn trajectories_path(dir: &Path) -> PathBuf {
        dir.join(TrajectoriesTable::file_name())
    }

    /// Path of the model's own training cameras in a model directory.
    pub fn cameras_path(dir: &Path) -> PathBuf {
        dir.join(ModelCamerasTable::file_name())
    }

    /// Open a model directory (reads the Gaussians, validates the trajectory layout, reads
    /// the model's cameras and similarity when present).
    pub fn load(dir: &Path) -> tables::Result<Model> {
        let path = Self::gaussians_path(dir);
        let gaussians = tables::gaussians::read(&path)?;
        let sh_frame = match tables::TableReader::open::<GaussiansTable>(&path)?
            .metadata_value(SH_FRAME_KEY)
            .as_deref()
        {
            None | Some("world") => ShFrame::World,
            Some("local") => ShFrame::Local,
            Some(other) => {
                return Err(tables::Error::Mismatch {
                    path,
                    msg: format!("metadata {SH_FRAME_KEY} is '{other}', expected world or local"),
                });
            }
        };
        let trajectories = TrajectoryReader::open(&Self::trajectories_path(dir), &gaussians.id)?;
        let cams_path = Self::cameras_path(dir);
        let cameras = if cams_path.exists() {
            let cams = model_cameras::read(&cams_path)?;
            if cams.len() != trajectories.num_frames() {
                return Err(tables::Error::Mismatch {
                    path: cams_path,
                    msg: format!(
                        "{} cameras for a model of {} frames",
                        cams.len(),
                        trajectories.num_frames()
                    ),
                });
            }
            Some(cams)
        } else {
            None
        };
        let sim_path = dir.join(SIMILARITY_FILE);
        let scene_to_model =
            if sim_path.exists() { Some(model_cameras::read_similarity(&sim_path)?) } else { None };
        Ok(Model {
            dir: dir.to_path_buf(),
            gaussians,
            sh_frame,
            cameras,
            scene_to_model,
            trajectories,
        })
    }

    /// The renderer inputs of frame `state`: its poses, the static attributes and the
    /// model's colours (SH in [`Model::sh_frame`]); no feature channels.
    pub fn splat_inputs<'a>(&'a self, state: &'a FrameState) -> SplatInputs<'a> {
        let g = &self.gaussians;
        SplatInputs {
            means: &state.position,
            quats: &state.rotation,
            scales: &g.scale,
            opacities: &g.opacity,
            colors: colors(g, self.sh_frame),
            features: &[],
            num_features: 0,
        }
    }

    /// The camera to render training frame `scene_cam.frame` with: the model's own camera
    /// (intrinsics rescaled to the scene image's size) when the model carries cameras, else
    /// `scene_cam` mapped through the scene-to-model similarity
    /// ([`Model::camera_in_model_frame`]). Image paths stay those of the scene.
    pub fn training_camera(&self, scene_cam: &Camera) -> Camera {
        let Some(mc) = self.cameras.as_ref().and_then(|c| c.get(scene_cam.frame as usize)) else {
            return self.camera_in_model_frame(scene_cam);
        };
        let (mc, sc) = (&mc.pinhole, &scene_cam.pinhole);
        let sx = sc.width as f64 / mc.width as f64;
        let sy = sc.height as f64 / mc.height as f64;
        Camera {
            pinhole: Pinhole {
                fx: mc.fx * sx,
                fy: mc.fy * sy,
                cx: mc.cx * sx,
                cy: mc.cy * sy,
                w2c: mc.w2c,
                ..*sc
            },
            distortion: None,
            ..scene_cam.clone()
        }
    }

    /// The camera that renders scene camera `cam` in this model: [`Model::training_camera`]
    /// for a training camera, [`Model::camera_in_model_frame`] for an evaluation view (the
    /// similarity fitted to the training cameras, the Sim(3) alignment step of MoSca's
    /// evaluation, without its test-time pose optimisation).
    pub fn render_camera(&self, cam: &Camera) -> Camera {
        match cam.split {
            crate::scene::Split::Train => self.training_camera(cam),
            crate::scene::Split::Eval => self.camera_in_model_frame(cam),
        }
    }

    /// A scene camera (e.g. an evaluation view) expressed in the model's world frame
    /// through the scene-to-model similarity (unchanged when the model has none).
    pub fn camera_in_model_frame(&self, cam: &Camera) -> Camera {
        match &self.scene_to_model {
            Some(sim) => {
                let pinhole = Pinhole { w2c: sim.w2c_to_model(&cam.pinhole.w2c), ..cam.pinhole };
                Camera { pinhole, ..cam.clone() }
            }
            None => cam.clone(),
        }
    }

    /// Write a model's own cameras and scene-to-model similarity into model directory `dir`.
    pub fn save_cameras(
        dir: &Path,
        cameras: &[ModelCamera],
        scene_to_model: &Similarity,
        provenance: &Provenance,
    ) -> tables::Result<()> {
        model_cameras::write(&Self::cameras_path(dir), cameras, provenance)?;
        model_cameras::write_similarity(&dir.join(SIMILARITY_FILE), scene_to_model)
    }

    /// Number of frames T.
    pub fn num_frames(&self) -> usize {
        self.trajectories.num_frames()
    }

    /// Read frame `t` (validated: finite, normalised quaternions, ids in canonical order).
    pub fn frame(&self, t: usize) -> tables::Result<FrameState> {
        self.trajectories.frame(t)
    }

    /// Write a model directory: the Gaussians, then frames 0..T-1 streamed from `frames`.
    pub fn save(
        dir: &Path,
        gaussians: &Gaussians,
        frames: impl IntoIterator<Item = tables::Result<FrameState>>,
        provenance: &Provenance,
    ) -> tables::Result<()> {
        tables::gaussians::write(&Self::gaussians_path(dir), gaussians, provenance)?;
        let mut w =
            TrajectoryWriter::create(&Self::trajectories_path(dir), &gaussians.id, provenance)?;
        for f in frames {
            w.write(&f?)?;
        }
        w.finish()
    }
}

/// A three-Gaussian, two-frame model with SH degree 1, for tests.
#[cfg(test)]
pub(crate) fn sample_model() -> (Gaussians, Vec<FrameState>) {
    let g = Gaussians {
        id: vec![7, 3, 11],
        dynamic: vec![true, false, true],
        scale: vec![[0.1, 0.2, 0.3]; 3],
        opacity: vec![0.5, 1.0, 0.0],
        color: vec![[1.0, 0.5, 0.0]; 3],
        sh_degree: 1,
        sh_rest: (0..27).map(|i| i as f32 * 0.01).collect(),
    };
    let frames = (0..2)
        .map(|t| FrameState {
            frame: t,
            position: vec![[t as f32, 1.0, 2.0]; 3],
            rotation: vec![[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5]],
        })
        .collect();
    (g, frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The SH frame is read from the gaussians table (absent: world), and is what
    /// [`Model::splat_inputs`] hands the renderer.
    #[test]
    fn sh_frame_is_a_model_property() {
        let (mut g, frames) = sample_model();
        g.sh_degree = 1;
        g.sh_rest = vec![0.1; g.len() * 9];
        for (name, prov, want) in [
            ("world", Provenance::default(), ShFrame::World),
            ("local", Provenance::default().with_metadata(SH_FRAME_KEY, "local"), ShFrame::Local),
        ] {
            let dir = tempfile::tempdir().unwrap();
            Model::save(dir.path(), &g, frames.clone().into_iter().map(Ok), &prov).unwrap();
            let m = Model::load(dir.path()).unwrap();
            assert_eq!(m.sh_frame, want, "{name}");
            let state = m.frame(0).unwrap();
            match m.splat_inputs(&state).colors {
                ColorSource::Sh { frame, .. } => assert_eq!(frame, want),
                ColorSource::Rgb(_) => panic!("degree 1 must render SH"),
            }
        }
    }
}
