//! The `uncertainty` table: per-Gaussian, per-frame rendering statistics and the scalar
//! uncertainty u_{i,t} of the paper's Eqs. 3-5 (written by `usplat4d uncertainty`, read by
//! `keynodes` and `edges`).
//!
//! One row group per frame (row group t holds frame t); every frame lists the same Gaussians
//! in the same order (the graph's node set: all Gaussians, or only the dynamic ones under the
//! release scope), so readers can stream frame by frame.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, Float32Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, FrameWriter, Table, TableReader, batch, field, read_frame_group};
use super::{Error, Provenance, Result, validate};

/// Marker type of the `uncertainty` table.
pub struct UncertaintyTable;

impl Table for UncertaintyTable {
    const NAME: &'static str = "uncertainty";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("frame", DataType::UInt32),
            field("gaussian_id", DataType::UInt32),
            field("sum_w2", DataType::Float32),
            field("sum_w", DataType::Float32),
            field("n_pixels", DataType::UInt32),
            field("converged", DataType::Boolean),
            field("u", DataType::Float32),
        ]))
    }
}

/// One frame of the table, `[N]` each in the table's Gaussian order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UncertaintyFrame {
    /// Frame index t.
    pub frame: u32,
    /// Σ_h (T·α)² over the pixels the Gaussian touched (1/σ² of Eq. 3); 0 when unseen.
    pub sum_w2: Vec<f32>,
    /// Σ_h T·α (total blending weight).
    pub sum_w: Vec<f32>,
    /// Number of pixels the Gaussian contributed to.
    pub n_pixels: Vec<u32>,
    /// The convergence indicator 𝟙_{i,t} of Eq. 5 (with the release gates when enabled).
    pub converged: Vec<bool>,
    /// Scalar uncertainty u_{i,t} > 0 (φ when unconverged or unseen).
    pub u: Vec<f32>,
}

fn frame_batch(ids: &[u32], f: &UncertaintyFrame) -> RecordBatch {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(vec![f.frame; ids.len()])),
        Arc::new(UInt32Array::from(ids.to_vec())),
        Arc::new(Float32Array::from(f.sum_w2.clone())),
        Arc::new(Float32Array::from(f.sum_w.clone())),
        Arc::new(UInt32Array::from(f.n_pixels.clone())),
        Arc::new(BooleanArray::from(f.converged.clone())),
        Arc::new(Float32Array::from(f.u.clone())),
    ];
    batch::<UncertaintyTable>(cols)
}

/// Streams frames into an `uncertainty` file, one row group each, atomically on finish.
pub struct UncertaintyWriter {
    inner: FrameWriter,
    ids: Vec<u32>,
}

impl UncertaintyWriter {
    /// Start writing to `path` for Gaussians `ids` (the order of every frame).
    pub fn create(path: &Path, ids: &[u32], provenance: &Provenance) -> Result<Self> {
        let inner = FrameWriter::create::<UncertaintyTable>(path, ids.len(), provenance)?;
        Ok(UncertaintyWriter { inner, ids: ids.to_vec() })
    }

    /// Append the next frame (frames come as 0, 1, 2, ...; `[N]` arrays of `ids` length).
    pub fn write(&mut self, f: &UncertaintyFrame) -> Result<()> {
        assert_eq!(f.frame, self.inner.next_frame(), "frames are written in order");
        let n = self.ids.len();
        assert!(
            [f.sum_w2.len(), f.sum_w.len(), f.n_pixels.len(), f.converged.len(), f.u.len()]
                .iter()
                .all(|l| *l == n),
            "one value per Gaussian"
        );
        self.inner.write(&frame_batch(&self.ids, f))
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.inner.finish()
    }
}

/// Reads an `uncertainty` file frame by frame, validating each frame as it is read.
pub struct UncertaintyReader {
    inner: TableReader,
    ids: Vec<u32>,
}

impl UncertaintyReader {
    /// Open `path`: reads the Gaussian order of frame 0 and checks every frame's row count.
    pub fn open(path: &Path) -> Result<Self> {
        let inner = TableReader::open::<UncertaintyTable>(path)?;
        Self::from_reader(inner)
    }

    /// Wrap an opened reader (a file or bytes in memory).
    fn from_reader(inner: TableReader) -> Result<Self> {
        let path = inner.path().to_path_buf();
        if inner.num_row_groups() == 0 {
            return Err(Error::Frame { path, frame: 0, msg: "the table has no frames".into() });
        }
        let first = inner.read_group(0)?;
        let ids = Columns::new(&path, &first).values::<UInt32Type>("gaussian_id")?.to_vec();
        validate::unique_ids(&path, "gaussian_id", 0, &ids)?;
        validate::rows_per_frame(&inner, ids.len(), &format!("{} (as in frame 0)", ids.len()))?;
        Ok(UncertaintyReader { inner, ids })
    }

    /// The Gaussians of every frame, in row order `[N]`.
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }

    /// Number of frames T.
    pub fn num_frames(&self) -> usize {
        self.inner.num_row_groups()
    }

    /// A key-value metadata entry (e.g. the resolved settings in the provenance).
    pub fn metadata_value(&self, key: &str) -> Option<String> {
        self.inner.metadata_value(key)
    }

    /// Read and validate frame `t`: frame column, id order, finite values, u > 0.
    pub fn frame(&self, t: usize) -> Result<UncertaintyFrame> {
        let path = self.inner.path();
        let (b, row0) = read_frame_group(
            &self.inner,
            t,
            "gaussian_id",
            |i| self.ids[i],
            "every frame lists the Gaussians in the order of frame 0",
        )?;
        let c = Columns::new(path, &b);
        let sum_w2 = c.values::<Float32Type>("sum_w2")?;
        let sum_w = c.values::<Float32Type>("sum_w")?;
        let u = c.values::<Float32Type>("u")?;
        for (name, v) in [("sum_w2", sum_w2), ("sum_w", sum_w), ("u", u)] {
            validate::finite(path, name, row0, v)?;
        }
        validate::in_range(path, "sum_w2", row0, sum_w2, 0.0, f32::MAX)?;
        validate::in_range(path, "sum_w", row0, sum_w, 0.0, f32::MAX)?;
        if let Some(i) = u.iter().position(|v| *v <= 0.0) {
            return Err(Error::Value {
                path: path.into(),
                column: "u".into(),
                row: row0 + i as u64,
                msg: format!("uncertainty {} is not positive", u[i]),
            });
        }
        Ok(UncertaintyFrame {
            frame: t as u32,
            sum_w2: sum_w2.to_vec(),
            sum_w: sum_w.to_vec(),
            n_pixels: c.values::<UInt32Type>("n_pixels")?.to_vec(),
            converged: c.bools("converged")?,
            u: u.to_vec(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(t: u32, u: Vec<f32>) -> UncertaintyFrame {
        let n = u.len();
        UncertaintyFrame {
            frame: t,
            sum_w2: u.iter().map(|v| 1.0 / v.max(1e-3)).collect(),
            sum_w: vec![1.0; n],
            n_pixels: vec![3; n],
            converged: vec![true; n],
            u,
        }
    }

    #[test]
    fn round_trip_and_value_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("uncertainty.parquet");
        let ids = [7, 3, 9];
        let mut w = UncertaintyWriter::create(&path, &ids, &Provenance::default()).unwrap();
        let frames = [frame(0, vec![0.5, 2.0, 1e8]), frame(1, vec![1.0, 0.25, 4.0])];
        for f in &frames {
            w.write(f).unwrap();
        }
        w.finish().unwrap();
        let r = UncertaintyReader::open(&path).unwrap();
        assert_eq!(r.ids(), &ids);
        assert_eq!(r.num_frames(), 2);
        assert_eq!(r.frame(1).unwrap(), frames[1]);

        let mut w = UncertaintyWriter::create(&path, &ids, &Provenance::default()).unwrap();
        w.write(&frame(0, vec![0.5, 2.0, 1.0])).unwrap();
        w.write(&frame(1, vec![0.5, 0.0, 1.0])).unwrap();
        w.finish().unwrap();
        let err = UncertaintyReader::open(&path).unwrap().frame(1).unwrap_err().to_string();
        assert_eq!(
            err,
            format!("{}: column 'u', row 4: uncertainty 0 is not positive", path.display())
        );
    }

    #[test]
    fn wrong_table_names_the_missing_columns() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.parquet");
        crate::tables::key_nodes::write(
            &path,
            &crate::tables::key_nodes::KeyNodes::default(),
            &Provenance::default(),
        )
        .unwrap();
        let err = UncertaintyReader::open(&path).err().unwrap().to_string();
        assert!(err.contains("it is a 'key_nodes' table"), "{err}");
        assert!(err.contains("missing column 'sum_w2' (f32)"), "{err}");
    }
}
