//! The 4D Gaussian model: static attributes per Gaussian plus a position and rotation per
//! Gaussian per frame, stored in a model directory.
//!
//! Layout of `MODEL_DIR`: `gaussians.parquet` (N rows, canonical order) and
//! `trajectories.parquet` (T row groups of N rows). Static Gaussians repeat their pose in
//! every frame. Frames are read one at a time ([`Model::frame`]) so that memory stays
//! O(N), not O(N·T).
//!
//! The model is also the one place that turns a frame into renderer inputs
//! ([`Model::splat_inputs`]): the frame the SH view direction is taken in ([`ShFrame`]) is a
//! property of the model (3DGS and SoM: world, MoSca: the Gaussian's local frame), stored
//! in the gaussians table's metadata under [`SH_FRAME_KEY`] (absent: world).

use std::path::{Path, PathBuf};

use crate::tables::trajectories::{TrajectoriesTable, TrajectoryReader, TrajectoryWriter};
use crate::tables::{self, Provenance, Table, gaussians::GaussiansTable};

use crate::render::{ColorSource, ShFrame, SplatInputs};
pub use crate::tables::gaussians::Gaussians;
pub use crate::tables::trajectories::FrameState;

/// A model directory opened for frame-by-frame reading.
pub struct Model {
    /// The model directory.
    pub dir: PathBuf,
    /// Static attributes.
    pub gaussians: Gaussians,
    /// The frame SH colours are evaluated in.
    pub sh_frame: ShFrame,
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

    /// Open a model directory (reads the Gaussians, validates the trajectory layout).
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
        Ok(Model { dir: dir.to_path_buf(), gaussians, sh_frame, trajectories })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The SH frame is read from the gaussians table (absent: world), and is what
    /// [`Model::splat_inputs`] hands the renderer.
    #[test]
    fn sh_frame_is_a_model_property() {
        let (mut g, frames) = crate::tables::tests::sample_model();
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
