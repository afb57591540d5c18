//! The `gaussians` table: per-Gaussian static attributes of a 4D model, one row per
//! Gaussian, in the model's canonical order (the order every per-frame table repeats).
//!
//! Scales are linear (not log), opacities in [0, 1], colour is the RGB of the degree-0
//! term; `sh_rest` holds the higher-order SH coefficients `[K, 3]` flattened (K =
//! (degree+1)^2 - 1, empty at degree 0).

use std::path::Path;
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, BooleanArray, Float32Array, ListArray, UInt8Array, UInt32Array,
};
use arrow::buffer::OffsetBuffer;
use arrow::datatypes::{DataType, Float32Type, Schema, SchemaRef, UInt8Type, UInt32Type};

use super::io::{Columns, Table, TableReader, batch, field, list, write_table};
use super::{Error, Provenance, Result, validate};

/// Static per-Gaussian attributes, `[N]` each, indexed by canonical position (not id).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gaussians {
    /// Stable `gaussian_id` of each Gaussian.
    pub id: Vec<u32>,
    /// Whether the Gaussian moves (dynamic) or is part of the static background.
    pub dynamic: Vec<bool>,
    /// Linear scales along the Gaussian's local axes, world units.
    pub scale: Vec<[f32; 3]>,
    /// Opacity in [0, 1].
    pub opacity: Vec<f32>,
    /// RGB colour of the SH degree-0 term, nominally [0, 1].
    pub color: Vec<[f32; 3]>,
    /// SH degree (0..=3) shared by all Gaussians.
    pub sh_degree: u8,
    /// Higher-order SH coefficients `[N, K, 3]` flattened, K = (degree+1)^2 - 1.
    pub sh_rest: Vec<f32>,
}

impl Gaussians {
    /// Number of Gaussians N.
    pub fn len(&self) -> usize {
        self.id.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.id.is_empty()
    }

    /// Number of `sh_rest` floats per Gaussian (3·K).
    pub fn sh_rest_len(&self) -> usize {
        3 * ((self.sh_degree as usize + 1).pow(2) - 1)
    }
}

/// Marker type of the `gaussians` table.
pub struct GaussiansTable;

impl Table for GaussiansTable {
    const NAME: &'static str = "gaussians";
    const VERSION: u32 = 1;
    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            field("gaussian_id", DataType::UInt32),
            field("dynamic", DataType::Boolean),
            field("scale_x", DataType::Float32),
            field("scale_y", DataType::Float32),
            field("scale_z", DataType::Float32),
            field("opacity", DataType::Float32),
            field("r", DataType::Float32),
            field("g", DataType::Float32),
            field("b", DataType::Float32),
            field("sh_degree", DataType::UInt8),
            field("sh_rest", list(DataType::Float32)),
        ]))
    }
}

/// Write `g` to `path` atomically.
pub fn write(path: &Path, g: &Gaussians, provenance: &Provenance) -> Result<()> {
    let n = g.len();
    let k3 = g.sh_rest_len();
    let offsets = OffsetBuffer::from_lengths(std::iter::repeat_n(k3, n));
    let item = Arc::new(arrow::datatypes::Field::new("item", DataType::Float32, false));
    let sh = ListArray::new(item, offsets, Arc::new(Float32Array::from(g.sh_rest.clone())), None);
    let col = |k: usize, v: &Vec<[f32; 3]>| {
        Arc::new(Float32Array::from_iter_values(v.iter().map(|s| s[k])))
    };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from(g.id.clone())),
        Arc::new(BooleanArray::from(g.dynamic.clone())),
        col(0, &g.scale),
        col(1, &g.scale),
        col(2, &g.scale),
        Arc::new(Float32Array::from(g.opacity.clone())),
        col(0, &g.color),
        col(1, &g.color),
        col(2, &g.color),
        Arc::new(UInt8Array::from(vec![g.sh_degree; n])),
        Arc::new(sh),
    ];
    write_table::<GaussiansTable>(path, provenance, [batch::<GaussiansTable>(cols)])
}

/// Read and validate the Gaussians of `path`.
pub fn read(path: &Path) -> Result<Gaussians> {
    let reader = TableReader::open::<GaussiansTable>(path)?;
    let b = reader.read_all()?;
    let c = Columns::new(path, &b);
    let id = c.values::<UInt32Type>("gaussian_id")?;
    validate::unique_ids(path, "gaussian_id", 0, id)?;
    let mut f = Vec::new();
    for name in ["scale_x", "scale_y", "scale_z", "opacity", "r", "g", "b"] {
        let v = c.values::<Float32Type>(name)?;
        validate::finite(path, name, 0, v)?;
        f.push(v);
    }
    for (k, name) in ["scale_x", "scale_y", "scale_z"].iter().enumerate() {
        if let Some(i) = f[k].iter().position(|s| *s < 0.0) {
            return Err(Error::Value {
                path: path.into(),
                column: name.to_string(),
                row: i as u64,
                msg: format!("negative scale {} (scales are linear, not log)", f[k][i]),
            });
        }
    }
    validate::in_range(path, "opacity", 0, f[3], 0.0, 1.0)?;
    let deg = c.values::<UInt8Type>("sh_degree")?;
    let sh_degree = deg.first().copied().unwrap_or(0);
    if let Some(i) = deg.iter().position(|d| *d != sh_degree || *d > 3) {
        return Err(Error::Value {
            path: path.into(),
            column: "sh_degree".into(),
            row: i as u64,
            msg: format!("degree {} (all rows must share one degree, at most 3)", deg[i]),
        });
    }
    let sh = c.get::<ListArray>("sh_rest")?;
    let k3 = 3 * ((sh_degree as usize + 1).pow(2) - 1);
    let offsets = sh.value_offsets();
    if let Some(i) = (0..sh.len()).find(|&i| (offsets[i + 1] - offsets[i]) as usize != k3) {
        return Err(Error::Value {
            path: path.into(),
            column: "sh_rest".into(),
            row: i as u64,
            msg: format!(
                "{} coefficients, degree {sh_degree} needs {k3}",
                offsets[i + 1] - offsets[i]
            ),
        });
    }
    let values =
        sh.values().as_any().downcast_ref::<Float32Array>().ok_or_else(|| Error::Schema {
            path: path.into(),
            table: GaussiansTable::NAME,
            problems: "sh_rest items are not f32".into(),
        })?;
    let start = offsets[0] as usize;
    let sh_rest = values.values()[start..start + k3 * sh.len()].to_vec();
    validate::finite(path, "sh_rest", 0, &sh_rest)?;
    let tri = |a: &[f32], b: &[f32], c: &[f32]| (0..a.len()).map(|i| [a[i], b[i], c[i]]).collect();
    Ok(Gaussians {
        id: id.to_vec(),
        dynamic: c.bools("dynamic")?,
        scale: tri(f[0], f[1], f[2]),
        opacity: f[3].to_vec(),
        color: tri(f[4], f[5], f[6]),
        sh_degree,
        sh_rest,
    })
}
