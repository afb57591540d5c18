//! The `key_nodes` table: the key / non-key partition of the graph's Gaussians (paper Sec.
//! 4.2, "Key node selection"), written by `usplat4d keynodes`, read by `edges`.
//!
//! One row group, one row per Gaussian of the uncertainty table, in its order.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, BooleanArray, UInt32Array};
use arrow::datatypes::{DataType, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, write_table};
use super::{Provenance, Result, validate};

/// Marker type of the `key_nodes` table.
pub struct KeyNodesTable;

impl Table for KeyNodesTable {
    const NAME: &'static str = "key_nodes";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("gaussian_id", DataType::UInt32),
            field("is_key", DataType::Boolean),
            field("t_hat", DataType::UInt32),
            field("significant_period", DataType::UInt32),
        ]))
    }
}

/// The key-node selection, `[N]` each, in the uncertainty table's Gaussian order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeyNodes {
    /// `gaussian_id` of each Gaussian.
    pub id: Vec<u32>,
    /// Whether the Gaussian is a key node.
    pub is_key: Vec<bool>,
    /// Most reliable frame t̂ = argmin_t u_{i,t} (first on ties).
    pub t_hat: Vec<u32>,
    /// Significant period: frames with uncertainty below the per-frame threshold (longest
    /// consecutive run or total count, per the `spt-counting` setting).
    pub significant_period: Vec<u32>,
}

impl KeyNodes {
    /// Number of key nodes.
    pub fn num_keys(&self) -> usize {
        self.is_key.iter().filter(|k| **k).count()
    }
}

/// Write `k` to `path` atomically.
pub fn write(path: &Path, k: &KeyNodes, provenance: &Provenance) -> Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(k.id.clone())),
        Arc::new(BooleanArray::from(k.is_key.clone())),
        Arc::new(UInt32Array::from(k.t_hat.clone())),
        Arc::new(UInt32Array::from(k.significant_period.clone())),
    ];
    write_table::<KeyNodesTable>(path, provenance, [batch::<KeyNodesTable>(cols)])
}

/// Read and validate `path` (unique ids).
pub fn read(path: &Path) -> Result<KeyNodes> {
    let reader = TableReader::open::<KeyNodesTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let id = c.values::<UInt32Type>("gaussian_id")?;
    validate::unique_ids(path, "gaussian_id", 0, id)?;
    Ok(KeyNodes {
        id: id.to_vec(),
        is_key: c.bools("is_key")?,
        t_hat: c.values::<UInt32Type>("t_hat")?.to_vec(),
        significant_period: c.values::<UInt32Type>("significant_period")?.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_duplicate_id() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("key_nodes.parquet");
        let k = KeyNodes {
            id: vec![4, 1, 2],
            is_key: vec![true, false, true],
            t_hat: vec![0, 3, 1],
            significant_period: vec![5, 0, 9],
        };
        write(&path, &k, &Provenance::default()).unwrap();
        assert_eq!(read(&path).unwrap(), k);
        assert_eq!(k.num_keys(), 2);
        let bad = KeyNodes { id: vec![4, 1, 4], ..k };
        write(&path, &bad, &Provenance::default()).unwrap();
        let err = read(&path).unwrap_err().to_string();
        assert_eq!(
            err,
            format!(
                "{}: column 'gaussian_id', row 2: duplicate id 4 (first at row 0)",
                path.display()
            )
        );
    }
}
