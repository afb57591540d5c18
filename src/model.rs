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

use crate::render::ShFrame;
use crate::scene::Camera;
use crate::tables::model_cameras::{self, ModelCamera, ModelCamerasTable, Similarity};
use crate::tables::trajectories::{TrajectoriesTable, TrajectoryReader, TrajectoryWriter};
use crate::tables::{self, Provenance, Table, gaussians::GaussiansTable};

/// Key of the gaussians table's metadata that holds the model's [`ShFrame`] (`world` or
/// `local`).
pub const SH_FRAME_KEY: &str = "usplat4d.sh_frame";

/// File name of the scene-to-model similarity inside a model directory.
pub const SIMILARITY_FILE: &str = "scene_to_model.json";

/// Static per-Gaussian attributes, `[N]` each, indexed by canonical position (not id).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gaussians {
    /// Stable `gaussian_id` of each Gaussian.
    pub id: Vec<u32>,
    /// Whether the Gaussian moves (dynamic) or is part of the static background.
    pub dynamic: Vec<bool>,
    /// Linear scales along the Gaussian's local axes, world units.
    pub scale: Vec<[f32; 3]>,
    /// Opacity in [0, 1].
    pub opacity: Vec<f32>,
    /// RGB colour of the SH degree-0 term, nominally [0, 1].
    pub color: Vec<[f32; 3]>,
    /// SH degree (0..=3) shared by all Gaussians.
    pub sh_degree: u8,
    /// Higher-order SH coefficients `[N, K, 3]` flattened, K = (degree+1)^2 - 1.
    pub sh_rest: Vec<f32>,
}

impl Gaussians {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.id.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.id.is_empty()
    }

    /// Number of `sh_rest` floats per Gaussian (3·K).
    pub fn sh_rest_len(&self) -> usize {
        3 * ((self.sh_degree as usize + 1).pow(2) - 1)
    }
}

/// Pose of every Gaussian at one frame, `[N]` each, canonical order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameState {
    /// Frame index t.
    pub frame: u32,
    /// World positions.
    pub position: Vec<[f32; 3]>,
    /// Rotations as unit quaternions `w, x, y, z` (local-to-world).
    pub rotation: Vec<[f32; 4]>,
}

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

    /// The camera to render training frame `scene_cam.frame` with: the model's own camera
    /// (intrinsics rescaled to the scene image's size) when the model carries cameras, else
    /// `scene_cam` itself. Image paths stay those of the scene.
    pub fn training_camera(&self, scene_cam: &Camera) -> Camera {
        let Some(mc) = self.cameras.as_ref().and_then(|c| c.get(scene_cam.frame as usize)) else {
            return scene_cam.clone();
        };
        let sx = scene_cam.width as f64 / mc.width as f64;
        let sy = scene_cam.height as f64 / mc.height as f64;
        Camera {
            fx: mc.fx * sx,
            fy: mc.fy * sy,
            cx: mc.cx * sx,
            cy: mc.cy * sy,
            w2c: mc.w2c,
            distortion: None,
            ..scene_cam.clone()
        }
    }

    /// A scene camera (e.g. an evaluation view) expressed in the model's world frame
    /// through the scene-to-model similarity (unchanged when the model has none).
    pub fn camera_in_model_frame(&self, cam: &Camera) -> Camera {
        match &self.scene_to_model {
            Some(sim) => Camera { w2c: sim.w2c_to_model(&cam.w2c), ..cam.clone() },
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
