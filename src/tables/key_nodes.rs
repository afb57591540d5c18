//! The `key_nodes` table: the role of each of the graph's Gaussians (paper Sec. 4.2, "Key
//! node selection"; official-release.md Sec. 4.2 and profile rows 33-35 for the non-keys
//! left out of the graph), written by `usplat4d keynodes`, read by `edges`.
//!
//! One row group, one row per Gaussian of the uncertainty table, in its order.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, StringArray, UInt32Array};
use arrow::datatypes::{DataType, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, write_table};
use super::{Error, Provenance, Result, validate};

/// Marker type of the `key_nodes` table.
pub struct KeyNodesTable;

impl Table for KeyNodesTable {
    const NAME: &'static str = "key_nodes";
    /// 2: the `role` column replaces `is_key` (non-keys left out of the graph).
    const VERSION: u32 = 2;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("gaussian_id", DataType::UInt32),
            field("role", DataType::Utf8),
            field("t_hat", DataType::UInt32),
            field("significant_period", DataType::UInt32),
        ]))
    }
}

/// What a Gaussian is in the graph (column `role`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Role {
    /// A key node: edges to its k nearest keys (Eq. 7).
    Key,
    /// A non-key in the graph: edges to keys (Eq. 8).
    Nonkey,
    /// A non-key left out of the graph (release rows 33-34) but kept in the model: no edges.
    Unlinked,
    /// A non-key left out of the graph and deleted from the model at the start of training
    /// (release row 35, "Cull in initialization"): no edges.
    Culled,
}

impl Role {
    /// Every role, in the order of the table's documentation.
    pub const ALL: [Role; 4] = [Role::Key, Role::Nonkey, Role::Unlinked, Role::Culled];

    /// The value stored in the `role` column.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Key => "key",
            Role::Nonkey => "nonkey",
            Role::Unlinked => "unlinked",
            Role::Culled => "culled",
        }
    }

    /// The role of a `role` column value, if it is one.
    pub fn parse(s: &str) -> Option<Role> {
        Role::ALL.into_iter().find(|r| r.as_str() == s)
    }
}

/// The key-node selection, `[N]` each, in the uncertainty table's Gaussian order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KeyNodes {
    /// `gaussian_id` of each Gaussian.
    pub id: Vec<u32>,
    /// The Gaussian's role in the graph.
    pub role: Vec<Role>,
    /// Most reliable frame t̂ = argmin_t u_{i,t} (first on ties).
    pub t_hat: Vec<u32>,
    /// Significant period: frames with uncertainty below the per-frame threshold (longest
    /// consecutive run or total count, per the `spt-counting` setting).
    pub significant_period: Vec<u32>,
}

impl KeyNodes {
    /// Number of Gaussians with `role`.
    pub fn count(&self, role: Role) -> usize {
        self.role.iter().filter(|r| **r == role).count()
    }

    /// Number of key nodes.
    pub fn num_keys(&self) -> usize {
        self.count(Role::Key)
    }

    /// Rows (indices into the `[N]` arrays) with `role`, ascending.
    pub fn rows(&self, role: Role) -> Vec<usize> {
        (0..self.role.len()).filter(|&i| self.role[i] == role).collect()
    }
}

/// Write `k` to `path` atomically.
pub fn write(path: &Path, k: &KeyNodes, provenance: &Provenance) -> Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(k.id.clone())),
        Arc::new(StringArray::from_iter_values(k.role.iter().map(|r| r.as_str()))),
        Arc::new(UInt32Array::from(k.t_hat.clone())),
        Arc::new(UInt32Array::from(k.significant_period.clone())),
    ];
    write_table::<KeyNodesTable>(path, provenance, [batch::<KeyNodesTable>(cols)])
}

/// Read and validate `path` (unique ids, known roles).
pub fn read(path: &Path) -> Result<KeyNodes> {
    let reader = TableReader::open::<KeyNodesTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let id = c.values::<UInt32Type>("gaussian_id")?;
    validate::unique_ids(path, "gaussian_id", 0, id)?;
    let role = c
        .strings("role")?
        .iter()
        .enumerate()
        .map(|(row, s)| {
            Role::parse(s).ok_or_else(|| Error::Value {
                path: path.to_path_buf(),
                column: "role".into(),
                row: row as u64,
                msg: format!("unknown role '{s}' (key, nonkey, unlinked or culled)"),
            })
        })
        .collect::<Result<_>>()?;
    Ok(KeyNodes {
        id: id.to_vec(),
        role,
        t_hat: c.values::<UInt32Type>("t_hat")?.to_vec(),
        significant_period: c.values::<UInt32Type>("significant_period")?.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_bad_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("key_nodes.parquet");
        let k = KeyNodes {
            id: vec![4, 1, 2, 7],
            role: vec![Role::Key, Role::Nonkey, Role::Key, Role::Culled],
            t_hat: vec![0, 3, 1, 2],
            significant_period: vec![5, 0, 9, 1],
        };
        write(&path, &k, &Provenance::default()).unwrap();
        assert_eq!(read(&path).unwrap(), k);
        assert_eq!((k.num_keys(), k.count(Role::Culled), k.rows(Role::Key)), (2, 1, vec![0, 2]));
        let bad = KeyNodes { id: vec![4, 1, 4, 7], ..k.clone() };
        write(&path, &bad, &Provenance::default()).unwrap();
        let err = read(&path).unwrap_err().to_string();
        assert_eq!(
            err,
            format!(
                "{}: column 'gaussian_id', row 2: duplicate id 4 (first at row 0)",
                path.display()
            )
        );
        let cols: Vec<ArrayRef> = vec![
            Arc::new(UInt32Array::from(vec![1, 2])),
            Arc::new(StringArray::from(vec!["key", "anchor"])),
            Arc::new(UInt32Array::from(vec![0, 0])),
            Arc::new(UInt32Array::from(vec![0, 0])),
        ];
        write_table::<KeyNodesTable>(&path, &Provenance::default(), [batch::<KeyNodesTable>(cols)])
            .unwrap();
        assert_eq!(
            read(&path).unwrap_err().to_string(),
            format!(
                "{}: column 'role', row 1: unknown role 'anchor' (key, nonkey, unlinked or culled)",
                path.display()
            )
        );
        assert!(Role::ALL.iter().all(|r| Role::parse(r.as_str()) == Some(*r)));
    }
}
