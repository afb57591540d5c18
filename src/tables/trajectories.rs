//! The `trajectories` table: each Gaussian's position and rotation at every frame.
//!
//! One row group per frame (row group t holds frame t), rows within a frame in the model's
//! canonical Gaussian order, so a stage can stream the model frame by frame. Quaternions
//! are `w, x, y, z`, normalised.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef};

use super::io::{Columns, FrameWriter, Table, TableReader, batch, field, read_frame_group};
use super::{Provenance, Result, validate};

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

/// Marker type of the `trajectories` table.
pub struct TrajectoriesTable;

impl Table for TrajectoriesTable {
    const NAME: &'static str = "trajectories";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("frame", DataType::UInt32),
            field("gaussian_id", DataType::UInt32),
            field("x", DataType::Float32),
            field("y", DataType::Float32),
            field("z", DataType::Float32),
            field("qw", DataType::Float32),
            field("qx", DataType::Float32),
            field("qy", DataType::Float32),
            field("qz", DataType::Float32),
        ]))
    }
}

/// The row group of one frame; `ids` is the canonical Gaussian order.
pub fn frame_batch(ids: &[u32], s: &FrameState) -> RecordBatch {
    let n = ids.len();
    let p = |k: usize| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(s.position.iter().map(|v| v[k])))
    };
    let q = |k: usize| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(s.rotation.iter().map(|v| v[k])))
    };
    batch::<TrajectoriesTable>(vec![
        Arc::new(UInt32Array::from(vec![s.frame; n])),
        Arc::new(UInt32Array::from(ids.to_vec())),
        p(0),
        p(1),
        p(2),
        q(0),
        q(1),
        q(2),
        q(3),
    ])
}

/// Streams frames into a `trajectories` file, one row group each, atomically on finish.
pub struct TrajectoryWriter {
    inner: FrameWriter,
    ids: Vec<u32>,
}

impl TrajectoryWriter {
    /// Start writing to `path` for Gaussians `ids` (canonical order).
    pub fn create(path: &Path, ids: &[u32], provenance: &Provenance) -> Result<Self> {
        let inner = FrameWriter::create::<TrajectoriesTable>(path, ids.len(), provenance)?;
        Ok(TrajectoryWriter { inner, ids: ids.to_vec() })
    }

    /// Append the next frame (frames must come as 0, 1, 2, ...).
    pub fn write(&mut self, s: &FrameState) -> Result<()> {
        assert_eq!(s.frame, self.inner.next_frame(), "frames are written in order");
        assert_eq!(s.rotation.len(), s.position.len(), "one rotation per Gaussian");
        self.inner.write(&frame_batch(&self.ids, s))
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.inner.finish()
    }
}

/// Reads a `trajectories` file frame by frame, validating each frame as it is read.
pub struct TrajectoryReader {
    inner: TableReader,
    ids: Vec<u32>,
}

impl TrajectoryReader {
    /// Open `path`, checking that every frame has one row per Gaussian of `ids`.
    pub fn open(path: &Path, ids: &[u32]) -> Result<Self> {
        let inner = TableReader::open::<TrajectoriesTable>(path)?;
        validate::rows_per_frame(&inner, ids.len(), &format!("one per Gaussian ({})", ids.len()))?;
        Ok(TrajectoryReader { inner, ids: ids.to_vec() })
    }

    /// Number of frames T.
    pub fn num_frames(&self) -> usize {
        self.inner.num_row_groups()
    }

    /// Read and validate frame `t`.
    pub fn frame(&self, t: usize) -> Result<FrameState> {
        let path = self.inner.path();
        let (b, row0) = read_frame_group(
            &self.inner,
            t,
            "gaussian_id",
            |i| self.ids[i],
            "rows of each frame follow the gaussians order",
        )?;
        let c = Columns::new(path, &b);
        let mut f = Vec::with_capacity(7);
        for name in ["x", "y", "z", "qw", "qx", "qy", "qz"] {
            let v = c.values::<Float32Type>(name)?;
            validate::finite(path, name, row0, v)?;
            f.push(v);
        }
        validate::unit_quaternions(path, row0, f[3], f[4], f[5], f[6])?;
        let n = b.num_rows();
        Ok(FrameState {
            frame: t as u32,
            position: (0..n).map(|i| [f[0][i], f[1][i], f[2][i]]).collect(),
            rotation: (0..n).map(|i| [f[3][i], f[4][i], f[5][i], f[6][i]]).collect(),
        })
    }
}
