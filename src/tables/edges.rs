//! The `edges` table: the directed USplat4D graph (paper Sec. 4.2, "Edge construction"),
//! written by `usplat4d edges`, read by `segment` and the optimiser.
//!
//! One row group. Rows are the key-key edges (grouped by source key, neighbours nearest
//! first) followed by the nonkey-key edges (grouped by source non-key). Weights are
//! normalised per source: the edges leaving one Gaussian sum to 1. A graph trained by
//! `optimize` also carries each key-key edge's learned canonical length.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array, StringArray, UInt32Array};
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, nullable, write_table};
use super::{Error, Provenance, Result, validate};

/// Marker type of the `edges` table.
pub struct EdgesTable;

impl Table for EdgesTable {
    const NAME: &'static str = "edges";
    /// 2: `rest_length`, the learned canonical lengths of a trained graph.
    const VERSION: u32 = 2;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("src", DataType::UInt32),
            field("dst", DataType::UInt32),
            field("kind", DataType::Utf8),
            field("weight", DataType::Float32),
            nullable("rest_length", DataType::Float32),
        ]))
    }
}

/// Which part of the graph an edge belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum EdgeKind {
    /// Between two key nodes (UA-kNN, Eq. 7).
    KeyKey,
    /// From a non-key Gaussian to a key node (Eq. 8).
    NonkeyKey,
}

impl EdgeKind {
    /// The name stored in the `kind` column.
    pub fn as_str(self) -> &'static str {
        match self {
            EdgeKind::KeyKey => "key-key",
            EdgeKind::NonkeyKey => "nonkey-key",
        }
    }

    /// Parse a stored kind.
    pub fn parse(s: &str) -> Option<EdgeKind> {
        match s {
            "key-key" => Some(EdgeKind::KeyKey),
            "nonkey-key" => Some(EdgeKind::NonkeyKey),
            _ => None,
        }
    }
}

/// The edges, `[E]` each (E edges), ids are `gaussian_id`s.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Edges {
    /// Source Gaussian.
    pub src: Vec<u32>,
    /// Destination Gaussian (always a key node).
    pub dst: Vec<u32>,
    /// Kind of each edge.
    pub kind: Vec<EdgeKind>,
    /// Weight in [0, 1]; the weights leaving one source sum to 1.
    pub weight: Vec<f32>,
    /// Learned canonical length D_ij of a trained key-key edge (world units); `None` for
    /// the `edges` stage's graph and for nonkey-key edges.
    pub rest_length: Vec<Option<f32>>,
}

impl Edges {
    /// Number of edges E.
    pub fn len(&self) -> usize {
        self.src.len()
    }

    /// Whether there are no edges.
    pub fn is_empty(&self) -> bool {
        self.src.is_empty()
    }

    /// Append one edge (no learned length).
    pub fn push(&mut self, src: u32, dst: u32, kind: EdgeKind, weight: f32) {
        self.push_trained(src, dst, kind, weight, None);
    }

    /// Append one edge with its learned canonical length.
    pub fn push_trained(
        &mut self,
        src: u32,
        dst: u32,
        kind: EdgeKind,
        weight: f32,
        rest_length: Option<f32>,
    ) {
        self.src.push(src);
        self.dst.push(dst);
        self.kind.push(kind);
        self.weight.push(weight);
        self.rest_length.push(rest_length);
    }
}

/// Write `e` to `path` atomically.
pub fn write(path: &Path, e: &Edges, provenance: &Provenance) -> Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(e.src.clone())),
        Arc::new(UInt32Array::from(e.dst.clone())),
        Arc::new(StringArray::from_iter_values(e.kind.iter().map(|k| k.as_str()))),
        Arc::new(Float32Array::from(e.weight.clone())),
        Arc::new(Float32Array::from(e.rest_length.clone())),
    ];
    write_table::<EdgesTable>(path, provenance, [batch::<EdgesTable>(cols)])
}

/// Read and validate `path`: known kinds, no self-loops, weights finite in [0, 1], learned
/// lengths finite and non-negative.
pub fn read(path: &Path) -> Result<Edges> {
    let reader = TableReader::open::<EdgesTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let src = c.values::<UInt32Type>("src")?;
    let dst = c.values::<UInt32Type>("dst")?;
    let weight = c.values::<Float32Type>("weight")?;
    validate::finite(path, "weight", 0, weight)?;
    validate::in_range(path, "weight", 0, weight, 0.0, 1.0)?;
    let value_err = |column: &str, row: usize, msg: String| Error::Value {
        path: path.to_path_buf(),
        column: column.into(),
        row: row as u64,
        msg,
    };
    let mut kind = Vec::with_capacity(src.len());
    for (i, k) in c.strings("kind")?.iter().enumerate() {
        let k = EdgeKind::parse(k).ok_or_else(|| {
            value_err("kind", i, format!("unknown kind '{k}' (key-key or nonkey-key)"))
        })?;
        kind.push(k);
    }
    if let Some(i) = (0..src.len()).find(|&i| src[i] == dst[i]) {
        return Err(value_err("dst", i, format!("self-loop on Gaussian {}", src[i])));
    }
    let rest_length = c.opt_values::<Float32Type>("rest_length")?;
    if let Some((i, d)) = rest_length
        .iter()
        .enumerate()
        .find_map(|(i, d)| d.filter(|d| !(d.is_finite() && *d >= 0.0)).map(|d| (i, d)))
    {
        return Err(value_err("rest_length", i, format!("{d} is not a finite length >= 0")));
    }
    Ok(Edges { src: src.to_vec(), dst: dst.to_vec(), kind, weight: weight.to_vec(), rest_length })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_self_loop() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("edges.parquet");
        let mut e = Edges::default();
        e.push(1, 2, EdgeKind::KeyKey, 1.0);
        e.push(2, 1, EdgeKind::KeyKey, 1.0);
        e.push_trained(5, 1, EdgeKind::NonkeyKey, 0.25, Some(0.5));
        e.push(5, 2, EdgeKind::NonkeyKey, 0.75);
        write(&path, &e, &Provenance::default()).unwrap();
        assert_eq!(read(&path).unwrap(), e);
        e.push(3, 3, EdgeKind::NonkeyKey, 1.0);
        write(&path, &e, &Provenance::default()).unwrap();
        let err = read(&path).unwrap_err().to_string();
        assert_eq!(
            err,
            format!("{}: column 'dst', row 4: self-loop on Gaussian 3", path.display())
        );
    }
}
