//! The 4D Gaussian model: static attributes per Gaussian plus a position and rotation per
//! Gaussian per frame, stored in a model directory.
//!
//! Layout of `MODEL_DIR`: `gaussians.parquet` (N rows, canonical order) and
//! `trajectories.parquet` (T row groups of N rows). Static Gaussians repeat their pose in
//! every frame. Frames are read one at a time ([`Model::frame`]) so that memory stays
//! O(N), not O(N·T).

use std::path::{Path, PathBuf};

use crate::tables::trajectories::{TrajectoriesTable, TrajectoryReader, TrajectoryWriter};
use crate::tables::{self, Provenance, Table, gaussians::GaussiansTable};

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

    /// Open a model directory (reads the Gaussians, validates the trajectory layout).
    pub fn load(dir: &Path) -> tables::Result<Model> {
        let gaussians = tables::gaussians::read(&Self::gaussians_path(dir))?;
        let trajectories = TrajectoryReader::open(&Self::trajectories_path(dir), &gaussians.id)?;
        Ok(Model { dir: dir.to_path_buf(), gaussians, trajectories })
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
