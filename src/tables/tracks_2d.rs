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
use arrow::datatypes::{DataType, Float32Type, SchemaRef};

use super::io::{Columns, Table, batch, field};
use super::tracks_3d::{TrackReader, TrackTable, TrackWriter, track_schema};
use super::{Result, validate};

/// Marker type of the `tracks_2d` table.
pub struct Tracks2dTable;

impl Table for Tracks2dTable {
    const NAME: &'static str = "tracks_2d";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        track_schema(field("visible", DataType::Boolean))
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

impl TrackTable for Tracks2dTable {
    type Frame = Tracks2dFrame;
    type Read = Tracks2dFrame;

    fn frame_batch(frame: u32, f: &Tracks2dFrame) -> RecordBatch {
        assert_eq!(f.visible.len(), f.xy.len(), "one visibility per track");
        let m = f.xy.len();
        batch::<Tracks2dTable>(vec![
            Arc::new(UInt32Array::from(vec![frame; m])),
            Arc::new(UInt32Array::from_iter_values(0..m as u32)),
            Arc::new(Float32Array::from_iter_values(f.xy.iter().map(|p| p[0]))),
            Arc::new(Float32Array::from_iter_values(f.xy.iter().map(|p| p[1]))),
            Arc::new(BooleanArray::from(f.visible.clone())),
        ])
    }

    fn read_frame(path: &Path, c: &Columns, row0: u64) -> Result<Tracks2dFrame> {
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

/// Streams [`Tracks2dFrame`]s into a `tracks_2d` file, atomically on finish.
pub type Tracks2dWriter = TrackWriter<Tracks2dTable>;

/// Reads a `tracks_2d` file frame by frame ([`Tracks2dFrame`]s), validating each frame.
pub type Tracks2dReader = TrackReader<Tracks2dTable>;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tables::Provenance;

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
            [Tracks2dTable::frame_batch(0, &f0), Tracks2dTable::frame_batch(1, &short)],
        )
        .unwrap();
        let err = Tracks2dReader::open(&p).err().unwrap().to_string();
        assert_eq!(
            err,
            format!("{}: frame 1: 1 rows, expected 2 (one per track, as in frame 0)", p.display())
        );
    }
}
