//! The `tracks_3d` table: ground-truth 3D positions of M surface points at every frame.
//!
//! One row group per frame (row group t holds frame t), M rows each with `track_id`
//! 0..M-1 in order, so readers stream frame by frame. Written by `synth` (points sampled
//! uniformly by area on the animated mesh, world units of the scene's cameras).

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, TableWriter, batch, field};
use super::{Error, Provenance, Result, validate};

/// Marker type of the `tracks_3d` table.
pub struct Tracks3dTable;

impl Table for Tracks3dTable {
    const NAME: &'static str = "tracks_3d";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("frame", DataType::UInt32),
            field("track_id", DataType::UInt32),
            field("x", DataType::Float32),
            field("y", DataType::Float32),
            field("z", DataType::Float32),
        ]))
    }
}

/// The row group of frame `frame`: positions `[M, 3]` of tracks 0..M-1.
pub fn frame_batch(frame: u32, positions: &[[f32; 3]]) -> RecordBatch {
    let m = positions.len();
    let col = |k: usize| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(positions.iter().map(|p| p[k])))
    };
    batch::<Tracks3dTable>(vec![
        Arc::new(UInt32Array::from(vec![frame; m])),
        Arc::new(UInt32Array::from_iter_values(0..m as u32)),
        col(0),
        col(1),
        col(2),
    ])
}

/// Streams frames into a `tracks_3d` file, atomically on finish.
pub struct Tracks3dWriter {
    inner: TableWriter,
    num_tracks: usize,
    next: u32,
}

impl Tracks3dWriter {
    /// Start writing `num_tracks` tracks to `path`.
    pub fn create(path: &Path, num_tracks: usize, provenance: &Provenance) -> Result<Self> {
        Ok(Tracks3dWriter {
            inner: TableWriter::create::<Tracks3dTable>(path, provenance)?,
            num_tracks,
            next: 0,
        })
    }

    /// Append the next frame's positions `[M, 3]` (frames come as 0, 1, 2, ...).
    pub fn write(&mut self, positions: &[[f32; 3]]) -> Result<()> {
        assert_eq!(positions.len(), self.num_tracks, "one position per track");
        self.inner.write_group(&frame_batch(self.next, positions))?;
        self.next += 1;
        Ok(())
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.inner.finish()
    }
}

/// Reads a `tracks_3d` file frame by frame, validating each frame.
pub struct Tracks3dReader {
    inner: TableReader,
    num_tracks: usize,
}

impl Tracks3dReader {
    /// Open `path`; every frame must hold the same number of tracks.
    pub fn open(path: &Path) -> Result<Self> {
        let inner = TableReader::open::<Tracks3dTable>(path)?;
        let num_tracks =
            if inner.num_row_groups() > 0 { inner.row_group_rows(0) as usize } else { 0 };
        same_rows_per_frame(&inner, num_tracks)?;
        Ok(Tracks3dReader { inner, num_tracks })
    }

    /// Number of frames T.
    pub fn num_frames(&self) -> usize {
        self.inner.num_row_groups()
    }

    /// Number of tracks M.
    pub fn num_tracks(&self) -> usize {
        self.num_tracks
    }

    /// Positions `[M, 3]` at frame `t`, validated.
    pub fn frame(&self, t: usize) -> Result<Vec<[f32; 3]>> {
        let path = self.inner.path();
        let b = self.inner.read_group(t)?;
        let row0 = self.inner.row_group_offset(t);
        let c = Columns::new(path, &b);
        validate::frame_column(path, t, row0, c.values::<UInt32Type>("frame")?)?;
        track_ids_in_order(path, row0, c.values::<UInt32Type>("track_id")?)?;
        let mut cols = Vec::with_capacity(3);
        for name in ["x", "y", "z"] {
            let v = c.values::<Float32Type>(name)?;
            validate::finite(path, name, row0, v)?;
            cols.push(v);
        }
        Ok((0..b.num_rows()).map(|i| [cols[0][i], cols[1][i], cols[2][i]]).collect())
    }
}

/// Every row group of a per-frame track table holds `m` rows.
pub(crate) fn same_rows_per_frame(r: &TableReader, m: usize) -> Result<()> {
    for g in 0..r.num_row_groups() {
        if r.row_group_rows(g) != m as u64 {
            return Err(Error::Frame {
                path: r.path().into(),
                frame: g as u64,
                msg: format!(
                    "{} rows, expected {m} (one per track, as in frame 0)",
                    r.row_group_rows(g)
                ),
            });
        }
    }
    Ok(())
}

/// Track ids of one frame run 0..M-1 in order.
pub(crate) fn track_ids_in_order(path: &Path, row0: u64, ids: &[u32]) -> Result<()> {
    match ids.iter().enumerate().find(|(i, id)| **id as usize != *i) {
        Some((i, id)) => Err(Error::Value {
            path: path.into(),
            column: "track_id".into(),
            row: row0 + i as u64,
            msg: format!("id {id} where {i} was expected (ids run 0..M-1 in every frame)"),
        }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_bad_ids() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tracks_3d.parquet");
        let frames =
            [vec![[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], vec![[1.0, 1.0, 2.0], [3.0, 5.0, 5.0]]];
        let mut w = Tracks3dWriter::create(&p, 2, &Provenance::default()).unwrap();
        for f in &frames {
            w.write(f).unwrap();
        }
        w.finish().unwrap();
        let r = Tracks3dReader::open(&p).unwrap();
        assert_eq!((r.num_frames(), r.num_tracks()), (2, 2));
        assert_eq!(r.frame(1).unwrap(), frames[1]);

        let mut b = frame_batch(0, &frames[0]);
        let cols: Vec<ArrayRef> = b
            .columns()
            .iter()
            .enumerate()
            .map(|(i, c)| {
                if i == 1 { Arc::new(UInt32Array::from(vec![0, 0])) as ArrayRef } else { c.clone() }
            })
            .collect();
        b = batch::<Tracks3dTable>(cols);
        super::super::io::write_table::<Tracks3dTable>(&p, &Provenance::default(), [b]).unwrap();
        let err = Tracks3dReader::open(&p).unwrap().frame(0).unwrap_err().to_string();
        assert_eq!(
            err,
            format!(
                "{}: column 'track_id', row 1: id 0 where 1 was expected (ids run 0..M-1 in every frame)",
                p.display()
            )
        );
    }
}
