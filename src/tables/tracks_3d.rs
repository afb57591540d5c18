//! The `tracks_3d` table: ground-truth 3D positions of M surface points at every frame.
//!
//! One row group per frame (row group t holds frame t), M rows each with `track_id`
//! 0..M-1 in order, so readers stream frame by frame. Written by `synth` (points sampled
//! uniformly by area on the animated mesh, world units of the scene's cameras).

use std::marker::PhantomData;
use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Field, Float32Type, Schema, SchemaRef};

use super::io::{Columns, FrameWriter, Table, TableReader, batch, field, read_frame_group};
use super::{Provenance, Result, validate};

/// Marker type of the `tracks_3d` table.
pub struct Tracks3dTable;

impl Table for Tracks3dTable {
    const NAME: &'static str = "tracks_3d";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        track_schema(field("z", DataType::Float32))
    }
}

impl TrackTable for Tracks3dTable {
    type Frame = [[f32; 3]];
    type Read = Vec<[f32; 3]>;

    /// Positions `[M, 3]` of tracks 0..M-1.
    fn frame_batch(frame: u32, positions: &[[f32; 3]]) -> RecordBatch {
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

    /// Positions `[M, 3]`, finite.
    fn read_frame(path: &Path, c: &Columns, row0: u64) -> Result<Vec<[f32; 3]>> {
        let mut cols = Vec::with_capacity(3);
        for name in ["x", "y", "z"] {
            let v = c.values::<Float32Type>(name)?;
            validate::finite(path, name, row0, v)?;
            cols.push(v);
        }
        Ok((0..cols[0].len()).map(|i| [cols[0][i], cols[1][i], cols[2][i]]).collect())
    }
}

/// Streams frames (positions `[M, 3]`) into a `tracks_3d` file, atomically on finish.
pub type Tracks3dWriter = TrackWriter<Tracks3dTable>;

/// Reads a `tracks_3d` file frame by frame (positions `[M, 3]`), validating each frame.
pub type Tracks3dReader = TrackReader<Tracks3dTable>;

/// A table of M tracks in every frame, one row group per frame (`tracks_2d`, `tracks_3d`):
/// how a frame becomes a row group and back.
pub trait TrackTable: Table {
    /// A frame as written.
    type Frame: ?Sized;
    /// A frame as read.
    type Read;
    /// The row group of frame `frame` (`track_id` 0..M-1 in order).
    fn frame_batch(frame: u32, f: &Self::Frame) -> RecordBatch;
    /// The frame held by columns `c` of `path` (first row at file row `row0`), validated.
    fn read_frame(path: &Path, c: &Columns, row0: u64) -> Result<Self::Read>;
}

/// The columns of a track table: `frame`, `track_id`, `x`, `y` (f32) and the table's `last`.
pub(super) fn track_schema(last: Field) -> SchemaRef {
    Arc::new(Schema::new(vec![
        field("frame", DataType::UInt32),
        field("track_id", DataType::UInt32),
        field("x", DataType::Float32),
        field("y", DataType::Float32),
        last,
    ]))
}

/// Streams frames into a track table's file, atomically on finish.
pub struct TrackWriter<T>(FrameWriter, PhantomData<T>);

impl<T: TrackTable> TrackWriter<T> {
    /// Start writing `num_tracks` tracks to `path`.
    pub fn create(path: &Path, num_tracks: usize, provenance: &Provenance) -> Result<Self> {
        Ok(TrackWriter(FrameWriter::create::<T>(path, num_tracks, provenance)?, PhantomData))
    }

    /// Append the next frame (frames come as 0, 1, 2, ...).
    pub fn write(&mut self, f: &T::Frame) -> Result<()> {
        self.0.write(&T::frame_batch(self.0.next_frame(), f))
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.0.finish()
    }
}

/// Reads a track table's file frame by frame, validating each frame; dereferences to
/// [`TrackFrames`] for the frame and track counts.
pub struct TrackReader<T>(TrackFrames, PhantomData<T>);

impl<T> std::ops::Deref for TrackReader<T> {
    type Target = TrackFrames;
    fn deref(&self) -> &TrackFrames {
        &self.0
    }
}

impl<T: TrackTable> TrackReader<T> {
    /// Open `path`; every frame must hold the same number of tracks.
    pub fn open(path: &Path) -> Result<Self> {
        Ok(TrackReader(TrackFrames::open::<T>(path)?, PhantomData))
    }

    /// The tracks of frame `t`, validated.
    pub fn frame(&self, t: usize) -> Result<T::Read> {
        let (b, row0) = self.0.group(t)?;
        let path = self.0.path();
        T::read_frame(path, &Columns::new(path, &b), row0)
    }
}

/// The frame-by-frame reading shared by the track tables: M rows in every frame, the
/// frame column and track ids 0..M-1 checked on each read.
pub struct TrackFrames {
    inner: TableReader,
    num_tracks: usize,
}

impl TrackFrames {
    /// Open `path` as table `T`; every frame must hold the rows of frame 0.
    pub(crate) fn open<T: Table>(path: &Path) -> Result<Self> {
        let inner = TableReader::open::<T>(path)?;
        let num_tracks =
            if inner.num_row_groups() > 0 { inner.row_group_rows(0) as usize } else { 0 };
        validate::rows_per_frame(
            &inner,
            num_tracks,
            &format!("{num_tracks} (one per track, as in frame 0)"),
        )?;
        Ok(TrackFrames { inner, num_tracks })
    }

    /// Number of frames T.
    pub fn num_frames(&self) -> usize {
        self.inner.num_row_groups()
    }

    /// The file read.
    pub fn path(&self) -> &Path {
        self.inner.path()
    }

    /// Number of tracks M.
    pub fn num_tracks(&self) -> usize {
        self.num_tracks
    }

    /// Row group `t` with its frame column and ids checked, and its first file row.
    pub(crate) fn group(&self, t: usize) -> Result<(RecordBatch, u64)> {
        read_frame_group(&self.inner, t, "track_id", |i| i as u32, "ids run 0..M-1 in every frame")
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

        let mut b = Tracks3dTable::frame_batch(0, &frames[0]);
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
