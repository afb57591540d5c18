//! The `tracks_2d` table: pixel positions of the M ground-truth surface points in the
//! training camera at every frame, with visibility.
//!
//! One row group per frame (row group t holds frame t), M rows each with `track_id`
//! 0..M-1 in order (the same ids as `tracks_3d`). Written by `synth`; `visible` comes from
//! a depth test against the rendered z-buffer. Points behind the camera have x = y = -1 and
//! are not visible.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{BooleanArray, Float32Array, RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef};

use super::io::{Columns, FrameWriter, Table, batch, field};
use super::tracks_3d::TrackFrames;
use super::{Provenance, Result, validate};

/// Marker type of the `tracks_2d` table.
pub struct Tracks2dTable;

impl Table for Tracks2dTable {
    const NAME: &'static str = "tracks_2d";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("frame", DataType::UInt32),
            field("track_id", DataType::UInt32),
            field("x", DataType::Float32),
            field("y", DataType::Float32),
            field("visible", DataType::Boolean),
        ]))
    }
}

/// The tracks of one frame, `[M]` each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tracks2dFrame {
    /// Pixel positions (pixel centres at +0.5).
    pub xy: Vec<[f32; 2]>,
    /// Visible in the training camera (inside the image and passing the depth test).
    pub visible: Vec<bool>,
}

/// The row group of frame `frame`.
pub fn frame_batch(frame: u32, f: &Tracks2dFrame) -> RecordBatch {
    let m = f.xy.len();
    batch::<Tracks2dTable>(vec![
        Arc::new(UInt32Array::from(vec![frame; m])),
        Arc::new(UInt32Array::from_iter_values(0..m as u32)),
        Arc::new(Float32Array::from_iter_values(f.xy.iter().map(|p| p[0]))),
        Arc::new(Float32Array::from_iter_values(f.xy.iter().map(|p| p[1]))),
        Arc::new(BooleanArray::from(f.visible.clone())),
    ])
}

/// Streams frames into a `tracks_2d` file, atomically on finish.
pub struct Tracks2dWriter(FrameWriter);

impl Tracks2dWriter {
    /// Start writing `num_tracks` tracks to `path`.
    pub fn create(path: &Path, num_tracks: usize, provenance: &Provenance) -> Result<Self> {
        Ok(Tracks2dWriter(FrameWriter::create::<Tracks2dTable>(path, num_tracks, provenance)?))
    }

    /// Append the next frame (frames come as 0, 1, 2, ...).
    pub fn write(&mut self, f: &Tracks2dFrame) -> Result<()> {
        assert_eq!(f.visible.len(), f.xy.len(), "one visibility per track");
        self.0.write(&frame_batch(self.0.next_frame(), f))
    }

    /// Close and rename into place.
    pub fn finish(self) -> Result<()> {
        self.0.finish()
    }
}

/// Reads a `tracks_2d` file frame by frame, validating each frame.
pub struct Tracks2dReader(TrackFrames);

impl std::ops::Deref for Tracks2dReader {
    type Target = TrackFrames;
    fn deref(&self) -> &TrackFrames {
        &self.0
    }
}

impl Tracks2dReader {
    /// Open `path`; every frame must hold the same number of tracks.
    pub fn open(path: &Path) -> Result<Self> {
        Ok(Tracks2dReader(TrackFrames::open::<Tracks2dTable>(path)?))
    }

    /// The tracks of frame `t`, validated.
    pub fn frame(&self, t: usize) -> Result<Tracks2dFrame> {
        let (b, row0) = self.0.group(t)?;
        let path = self.0.path();
        let c = Columns::new(path, &b);
        let x = c.values::<Float32Type>("x")?;
        let y = c.values::<Float32Type>("y")?;
        validate::finite(path, "x", row0, x)?;
        validate::finite(path, "y", row0, y)?;
        Ok(Tracks2dFrame {
            xy: x.iter().zip(y).map(|(x, y)| [*x, *y]).collect(),
            visible: c.bools("visible")?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_row_count_check() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tracks_2d.parquet");
        let f0 = Tracks2dFrame { xy: vec![[1.5, 2.5], [-1.0, -1.0]], visible: vec![true, false] };
        let f1 = Tracks2dFrame { xy: vec![[3.0, 2.0], [4.0, 4.0]], visible: vec![false, true] };
        let mut w = Tracks2dWriter::create(&p, 2, &Provenance::default()).unwrap();
        w.write(&f0).unwrap();
        w.write(&f1).unwrap();
        w.finish().unwrap();
        let r = Tracks2dReader::open(&p).unwrap();
        assert_eq!((r.num_frames(), r.num_tracks()), (2, 2));
        assert_eq!(r.frame(0).unwrap(), f0);
        assert_eq!(r.frame(1).unwrap(), f1);

        let short = Tracks2dFrame { xy: vec![[0.0, 0.0]], visible: vec![true] };
        super::super::io::write_table::<Tracks2dTable>(
            &p,
            &Provenance::default(),
            [frame_batch(0, &f0), frame_batch(1, &short)],
        )
        .unwrap();
        let err = Tracks2dReader::open(&p).err().unwrap().to_string();
        assert_eq!(
            err,
            format!("{}: frame 1: 1 rows, expected 2 (one per track, as in frame 0)", p.display())
        );
    }
}
