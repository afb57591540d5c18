//! The `segments` table: a motion-group label per Gaussian (paper Sec. 5.3, "Further
//! analysis": spectral clustering of the key graph, non-keys inheriting through their
//! edges), written by `usplat4d segment`.
//!
//! One row group, one row per Gaussian of the edges table, sorted by `gaussian_id`.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, UInt32Array};
use arrow::datatypes::{DataType, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, write_table};
use super::{Provenance, Result, validate};

/// Marker type of the `segments` table.
pub struct SegmentsTable;

impl Table for SegmentsTable {
    const NAME: &'static str = "segments";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("gaussian_id", DataType::UInt32),
            field("segment", DataType::UInt32),
            field("is_key", DataType::Boolean),
        ]))
    }
}

/// Segment labels, `[N]` each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Segments {
    /// `gaussian_id` of each Gaussian.
    pub id: Vec<u32>,
    /// Motion group 0..K-1.
    pub segment: Vec<u32>,
    /// Whether the Gaussian is a key node.
    pub is_key: Vec<bool>,
}

/// Write `s` to `path` atomically.
pub fn write(path: &Path, s: &Segments, provenance: &Provenance) -> Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(s.id.clone())),
        Arc::new(UInt32Array::from(s.segment.clone())),
        Arc::new(BooleanArray::from(s.is_key.clone())),
    ];
    write_table::<SegmentsTable>(path, provenance, [batch::<SegmentsTable>(cols)])
}

/// Read and validate `path` (unique ids).
pub fn read(path: &Path) -> Result<Segments> {
    let reader = TableReader::open::<SegmentsTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let id = c.values::<UInt32Type>("gaussian_id")?;
    validate::unique_ids(path, "gaussian_id", 0, id)?;
    Ok(Segments {
        id: id.to_vec(),
        segment: c.values::<UInt32Type>("segment")?.to_vec(),
        is_key: c.bools("is_key")?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_duplicate_id() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("segments.parquet");
        let s = Segments {
            id: vec![0, 1, 2],
            segment: vec![1, 0, 1],
            is_key: vec![true, false, false],
        };
        write(&path, &s, &Provenance::default()).unwrap();
        assert_eq!(read(&path).unwrap(), s);
        write(&path, &Segments { id: vec![0, 0, 2], ..s }, &Provenance::default()).unwrap();
        let err = read(&path).unwrap_err().to_string();
        assert_eq!(
            err,
            format!(
                "{}: column 'gaussian_id', row 1: duplicate id 0 (first at row 0)",
                path.display()
            )
        );
    }
}
